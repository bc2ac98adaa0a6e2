"""Helpers of the model tests: a tiny network and pairs with known poses."""

from __future__ import annotations

import torch

from dpcn_med.models import ModelConfig
from dpcn_med.solver import PoseTarget
from dpcn_med.synth import random_poses
from tests.conftest import volume_grid

TINY = ModelConfig(bandwidth=8, channels=(4, 8, 16), residual_units=0)


def pairs(size: int, count: int, seed: int, mode: str = "similarity") -> tuple[torch.Tensor, torch.Tensor, PoseTarget]:
    """The MNI template on a ``size^3`` grid and moved copies with known poses (small shifts, all of SO(3))."""
    base = volume_grid("mni", size)
    poses = random_poses(count, size, seed, similarity=mode == "similarity", scale_range=(0.9, 1.1),
                         max_shift=0.1 * size)
    moving = torch.cat([pose.moving_from(base) for pose in poses])
    target = PoseTarget(torch.stack([p.rotation for p in poses]).float(), torch.tensor([p.scale for p in poses]),
                        torch.stack([p.translation for p in poses]).float())
    return base.expand(count, -1, -1, -1, -1), moving, target
