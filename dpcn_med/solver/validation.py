"""Checks of the solver's inputs, with messages that name the problem and the fix."""

from __future__ import annotations

import numbers

import torch
from torch import Tensor

from dpcn_med.errors import InputError

MAX_BANDWIDTH = 128

MIN_GRID_SIZE = {3: 16, 2: 32}
"""Least grid size ``N`` per dimension: the least that still measured a pose on real volumes (the measurements:
docs/design_notes/solver.md)."""


def check_grids(fixed: Tensor, moving: Tensor, dim: int) -> int:
    """Validate a pair of solver grids and return their size ``N``.

    Args:
        fixed: ``(batch, 1, N, N, N)`` (``dim = 3``) or ``(batch, 1, N, N)`` (``dim = 2``).
        moving: same shape, device and dtype.
        dim: 2 or 3.

    Raises:
        InputError: wrong rank, an empty batch, channels, non-square, odd or too small (:data:`MIN_GRID_SIZE`) size,
            mismatch, non-float dtype, NaN or Inf.
    """
    layout = "(B, 1, N, N, N)" if dim == 3 else "(B, 1, N, N)"
    other = "solve2d" if dim == 3 else "solve"
    for name, grid in (("fixed", fixed), ("moving", moving)):
        if not isinstance(grid, Tensor):
            raise InputError(f"{name} must be a torch.Tensor of shape {layout}, got {type(grid).__name__}")
        if grid.dim() != dim + 2:
            raise InputError(f"{name} has shape {tuple(grid.shape)}; expected {layout} (for the other dimension use "
                             f"{other})")
        if grid.shape[0] == 0:
            raise InputError(f"{name} holds no grids (batch size 0, shape {tuple(grid.shape)}); expected at least one")
        if grid.shape[1] != 1:
            raise InputError(f"{name} has {grid.shape[1]} channels (shape {tuple(grid.shape)}); expected 1")
        sizes = tuple(grid.shape[2:])
        if len(set(sizes)) != 1:
            raise InputError(f"{name} grid is not cubic: spatial shape {sizes}; resample it onto an N^{dim} grid")
        if sizes[0] % 2 or sizes[0] < MIN_GRID_SIZE[dim]:
            raise InputError(f"{name} grid size is {sizes[0]}; expected an even N >= {MIN_GRID_SIZE[dim]} ("
                             f"{'N = 2B; ' if dim == 3 else ''}smaller {dim}-D grids gave wrong poses)")
        if grid.dtype not in (torch.float32, torch.float64):
            raise InputError(f"{name} has dtype {grid.dtype}; expected torch.float32 or torch.float64")
        if not torch.isfinite(grid).all():
            raise InputError(f"{name} contains NaN or Inf values; replace them (e.g. torch.nan_to_num) first")
    if fixed.shape != moving.shape:
        raise InputError(f"fixed and moving shapes differ: {tuple(fixed.shape)} vs {tuple(moving.shape)}")
    if fixed.dtype != moving.dtype or fixed.device != moving.device:
        raise InputError(f"fixed ({fixed.dtype}, {fixed.device}) and moving ({moving.dtype}, {moving.device}) must "
                         "share dtype and device")
    return fixed.shape[-1]


def check_bandwidth(bandwidth: int | None, size: int, *, minimum: int = 4) -> int:
    """The bandwidth to use for grids of size ``size``: ``size // 2`` by default, else ``minimum <= B <= size // 2,
    128``."""
    if bandwidth is None:
        bandwidth = size // 2
    if isinstance(bandwidth, numbers.Integral) and not isinstance(bandwidth, bool):
        bandwidth = int(bandwidth)  # numpy integers too
    top = min(size // 2, MAX_BANDWIDTH)
    if not isinstance(bandwidth, int) or not minimum <= bandwidth <= top:
        limit = f" (half the grid size {size})" if top < MAX_BANDWIDTH else ""
        raise InputError(f"bandwidth {bandwidth!r} is out of range: use an integer in [{minimum}, {top}]{limit}")
    return bandwidth


def check_grid_bandwidth(bandwidth: int) -> int:
    """A bandwidth ``B`` for callers that build ``(2B)^3`` grids (register, the models, training), refused before any
    work when the grid would be under :data:`MIN_GRID_SIZE`."""
    return check_bandwidth(bandwidth, 2 * MAX_BANDWIDTH, minimum=MIN_GRID_SIZE[3] // 2)


def check_mode(mode: str) -> str:
    """``'similarity'`` or ``'rigid'``."""
    if mode not in ("similarity", "rigid"):
        raise InputError(f"mode {mode!r} is not supported; use 'similarity' (with scale) or 'rigid'")
    return mode
