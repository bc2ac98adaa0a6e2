"""The feature extractor of one modality and stage: a MONAI 3-D UNet, added to its input through a learnable gain."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

NEGATIVE_SLOPE = 0.1
"""LeakyReLU slope of the UNets (DESIGN 3: LeakyReLU, as in the paper)."""


class FeatureExtractor(nn.Module):
    """``features = volume + gain * UNet(volume)``, ``gain`` starting at 0.

    Starting at the identity makes an untrained model exactly the learning-free solver, the baseline that always
    works (DESIGN 3), and training moves away from it only as far as the pose loss asks (the "ReZero" start:
    Bachlechner et al., 2021). The UNet is MONAI's, with LeakyReLU and instance normalisation.

    Args:
        channels: feature channels per level; ``len(channels) - 1`` downsamplings by 2.
        residual_units: MONAI's ``num_res_units``.
    """

    def __init__(self, channels: Sequence[int] = (8, 16, 32, 64), residual_units: int = 1) -> None:
        super().__init__()
        from monai.networks.nets import (
            UNet,  # imported here: MONAI takes a second to load and inference may not need it
        )

        self.unet = UNet(spatial_dims=3, in_channels=1, out_channels=1, channels=tuple(channels),
                         strides=(2,) * (len(channels) - 1), num_res_units=residual_units,
                         act=("LeakyReLU", {"negative_slope": NEGATIVE_SLOPE}), norm="INSTANCE")
        self.gain = nn.Parameter(torch.zeros(()))

    def forward(self, volume: Tensor) -> Tensor:
        """``(B, 1, N, N, N)`` -> ``(B, 1, N, N, N)`` feature grid; ``N`` divisible by ``2 ** (len(channels) - 1)``."""
        return volume + self.gain * self.unet(volume)
