"""Shared fixtures: dtypes and devices, and real volumes from ../shared/data or the built-in sample."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest
import SimpleITK as sitk
import torch

from dpcn_med.preprocess import solver_grid, solver_slice
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
    image = mni152_t1() if name == "mni" else sitk.ReadImage(str(SHARED_DATA / name))
    return solver_slice(image, size, dtype=torch.float64)


def axial_slice(name: str, size: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The axial slice through the foreground centre, ``(1, 1, size, size)``, head spanning about half the grid."""
    if name != "mni":
        shared_path(name)
    return _slice_of(name, size).to(dtype)
