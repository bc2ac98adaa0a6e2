"""Mattes mutual information in torch: the estimator's values, its gradient, overlap, ITK's metric and devices."""

from __future__ import annotations

import math

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from dpcn_med.evaluation import moved_copy, random_similarity
from dpcn_med.geometry import homogeneous_matrix, similarity_transform
from dpcn_med.mutual_information import fixed_bins, moving_window, negative_mutual_information
from dpcn_med.preprocess import foreground_box, foreground_mask
from dpcn_med.refine import Refinement, mattes_metric, search_levels
from tests.test_registration import mni_2mm

BINS = 32


def _values(count: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(count, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 100


class TestEstimator:
    def test_a_window_spreads_one_unit_over_four_bins(self):
        first, weights = moving_window(_values(1000), 0.0, 100.0, BINS)
        torch.testing.assert_close(weights.sum(-1), torch.ones(1000, dtype=torch.float64))
        assert (weights >= 0).all() and first.min() >= 0 and (first + 3).max() <= BINS - 1

    def test_information_is_high_for_one_image_and_none_for_independent_ones(self):
        fixed = _values(20_000)
        bins = fixed_bins(fixed, 0.0, 100.0, BINS)
        valid = torch.ones(1, 20_000, dtype=torch.bool)
        same = negative_mutual_information(bins, fixed[None], valid, (0.0, 100.0), BINS)
        independent = negative_mutual_information(bins, _values(20_000, seed=1)[None], valid, (0.0, 100.0), BINS)
        # The same image shares most of its binned entropy (log 32 = 3.47 nats, less the moving window's spread).
        assert -same.item() > 2.0
        assert abs(independent.item()) < 0.05

    def test_information_does_not_care_how_intensities_map(self):
        """A monotonic remapping of the moving intensities (another contrast) keeps the information."""
        fixed = _values(20_000)
        bins = fixed_bins(fixed, 0.0, 100.0, BINS)
        valid = torch.ones(1, 20_000, dtype=torch.bool)
        same = negative_mutual_information(bins, fixed[None], valid, (0.0, 100.0), BINS)
        inverted = negative_mutual_information(bins, (100 - fixed)[None], valid, (0.0, 100.0), BINS)
        assert inverted.item() == pytest.approx(same.item(), rel=0.02)

    def test_a_pose_with_too_few_valid_samples_does_not_overlap(self):
        fixed = _values(10_000)
        bins = fixed_bins(fixed, 0.0, 100.0, BINS)
        valid = torch.zeros(2, 10_000, dtype=torch.bool)
        valid[0, :5000] = True
        valid[1, :50] = True  # under 1% and under 64 samples
        value = negative_mutual_information(bins, fixed.expand(2, -1), valid, (0.0, 100.0), BINS)
        assert math.isfinite(value[0].item()) and value[1].item() == math.inf

    def test_the_gradient_is_the_derivative(self):
        fixed = _values(300)
        bins = fixed_bins(fixed, 0.0, 100.0, 8)
        # Inside the range: at its ends the window is clamped, and the derivative one-sided.
        moving = (fixed + 10 * torch.sin(fixed)).clamp(1, 99)[None].clone().requires_grad_(True)
        valid = torch.ones(1, 300, dtype=torch.bool)
        assert torch.autograd.gradcheck(lambda values: negative_mutual_information(bins, values, valid, (0.0, 100.0),
                                                                                    8), (moving,))


class TestAgainstITK:
    def test_it_reads_like_itks_mattes_metric(self):
        """On the 2 mm MNI head, every fixed voxel of the mask (ITK) against 200 000 jittered samples (ours), at poses
        0 to 16 mm and degrees off the truth: within 10% of each other, in the same order."""
        fixed = mni_2mm()
        centre = foreground_box(fixed)[0]
        truth = random_similarity(np.random.default_rng(0), centre)
        moving = moved_copy(fixed, truth)
        mask = sitk.BinaryDilate(foreground_mask(fixed), [3, 3, 3])
        level = search_levels(fixed, moving, (mask, None), centre,
                              Refinement(shrink_factors=(1,), smoothing_mm=(0.0,), samples=200_000))[0]
        ours, theirs = [], []
        for offset in (0, 2, 4, 8, 16):
            residual = sitk.Euler3DTransform(centre.tolist(), math.radians(offset), 0, 0, (offset, 0, 0))
            matrix = homogeneous_matrix(truth) @ homogeneous_matrix(residual)
            ours.append(level.metric(torch.as_tensor(matrix)[None], torch.zeros(1, 6, dtype=torch.float64),
                                     centre).item())
            theirs.append(mattes_metric(fixed, moving, similarity_transform(matrix, centre, rigid=True),
                                        (mask, None)))
        np.testing.assert_allclose(ours, theirs, rtol=0.1)
        assert np.all(np.diff(ours) > 0) and np.all(np.diff(theirs) > 0)


class TestDevices:
    def test_it_runs_on_the_meta_device(self):
        """Every tensor it makes follows its inputs' device: none is made on the CPU behind the caller's back."""
        meta = torch.device("meta")
        bins = torch.zeros(1000, dtype=torch.long, device=meta)
        moving = torch.empty(3, 1000, device=meta, requires_grad=True)
        valid = torch.empty(3, 1000, dtype=torch.bool, device=meta)
        value = negative_mutual_information(bins, moving, valid, (0.0, 1.0), BINS)
        assert value.device == meta and value.shape == (3,)
        gradient, = torch.autograd.grad(value.sum(), moving)
        assert gradient.device == meta and gradient.shape == (3, 1000)
