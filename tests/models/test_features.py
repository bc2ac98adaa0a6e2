"""dpcn_med.models.features: the feature extractor."""

from __future__ import annotations

import torch

from dpcn_med.models import FeatureExtractor


class TestFeatureExtractor:
    def test_starts_as_the_identity_and_keeps_the_shape(self):
        extractor = FeatureExtractor((4, 8), residual_units=0)
        volume = torch.rand(2, 1, 16, 16, 16)
        assert torch.equal(extractor(volume), volume)
        with torch.no_grad():
            extractor.gain.fill_(1.0)
        assert extractor(volume).shape == volume.shape and not torch.equal(extractor(volume), volume)
