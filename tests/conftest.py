"""Shared fixtures: dtypes and devices, real volumes from ../shared/data, and known random poses."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import torch

from dpcn_med.geometry import geodesic_distance, random_rotation, rotation_2d, warp
from dpcn_med.preprocess import canonical_grid, normalize_intensity, solver_grid
from dpcn_med.samples import mni152_t1

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
# Tolerances per dtype for checks that compare two computations of the same quantity.
TOLERANCE = {torch.float32: 1e-4, torch.float64: 1e-10}


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    return request.param


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)


def shared_path(relative: str) -> Path:
    """A file under ../shared/data, or skip the test with the reason."""
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"{path} is absent: the shared data volumes sit beside the checkout (../shared/data) in CI")
    return path


@functools.lru_cache(maxsize=8)
def _grid_of(name: str, size: int) -> torch.Tensor:
    image = mni152_t1() if name == "mni" else sitk.ReadImage(str(SHARED_DATA / name))
    return solver_grid(image, size, dtype=torch.float64)[0]


def volume_grid(name: str, size: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """A real volume on its canonical ``size^3`` cube, ``(1, 1, N, N, N)``; ``name`` is "mni" or under shared/data."""
    if name != "mni":
        shared_path(name)
    return _grid_of(name, size).to(dtype)


@functools.lru_cache(maxsize=4)
def _slice_of(name: str, size: int) -> torch.Tensor:
    image = normalize_intensity(mni152_t1() if name == "mni" else sitk.ReadImage(str(SHARED_DATA / name)))
    grid = canonical_grid(image, size, fill=0.55)
    reference = sitk.Image([size, size, 1], sitk.sitkFloat32)
    reference.SetSpacing([grid.spacing] * 3)
    reference.SetOrigin((*grid.origin[:2], grid.centre[2]))
    axial = sitk.Resample(image, reference, sitk.Transform(), sitk.sitkLinear, 0.0, sitk.sitkFloat32)
    return torch.from_numpy(sitk.GetArrayFromImage(axial)[0].astype(np.float64))[None, None]


def axial_slice(name: str, size: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The axial slice through the foreground centre, ``(1, 1, size, size)``, head spanning about half the grid."""
    if name != "mni":
        shared_path(name)
    return _slice_of(name, size).to(dtype)


@dataclass
class Pose:
    """``fixed(p) = moving(scale * rotation @ p + translation)``, voxel units."""

    rotation: torch.Tensor
    scale: float
    translation: torch.Tensor

    def moving_from(self, fixed: torch.Tensor) -> torch.Tensor:
        """The moving grid that this pose maps onto ``fixed``: ``moving(q) = fixed(A^-1 (q - t))``."""
        inverse = torch.linalg.inv(self.scale * self.rotation.to(fixed.dtype))
        return warp(fixed, inverse[None], -(inverse @ self.translation.to(fixed.dtype))[None])


def random_poses(count: int, size: int, seed: int, *, similarity: bool = True, dim: int = 3,
                 max_shift: float | None = None) -> list[Pose]:
    """Rotations uniform over SO(3) (or [0, 360) degrees in 2-D), shifts up to 20% of the grid (or ``max_shift``),
    scales in [0.8, 1.2] (or 1)."""
    generator = torch.Generator().manual_seed(seed)
    poses = []
    for _ in range(count):
        if dim == 3:
            rotation = random_rotation(1, generator)[0]
        else:
            rotation = rotation_2d(torch.rand((), generator=generator, dtype=torch.float64) * 2 * math.pi)
        scale = float(torch.empty(()).uniform_(0.8, 1.2, generator=generator)) if similarity else 1.0
        direction = torch.randn(dim, generator=generator, dtype=torch.float64)
        length = float(torch.rand((), generator=generator)) * (max_shift if max_shift is not None else 0.2 * size)
        poses.append(Pose(rotation, scale, direction / direction.norm() * length))
    return poses


def pose_errors(rotation: torch.Tensor, scale: torch.Tensor, translation: torch.Tensor, pose: Pose
                ) -> tuple[float, float, float]:
    """(rotation error in degrees, translation error in voxels, relative scale error) of one estimate."""
    if rotation.shape[-1] == 3:
        angle = geodesic_distance(rotation.double(), pose.rotation.double()).item()
    else:
        relative = rotation.double().T @ pose.rotation.double()
        angle = abs(math.atan2(relative[1, 0].item(), relative[0, 0].item()))
    return (math.degrees(angle), (translation.double() - pose.translation).norm().item(),
            abs(scale.item() / pose.scale - 1))
