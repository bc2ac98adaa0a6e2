"""Input checks and seeded draws shared by the synthetic-data modules.

Draws happen on the generator's device and are moved to the data's device and dtype: a CPU generator gives the same
data on every device, a generator on the data's device avoids copying noise volumes from the host.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dpcn_med.errors import InputError

MIN_SIZE = 4
"""Fewest voxels along an axis (as :func:`dpcn_med.io.read_image` asks; why: docs/design_notes/synth.md)."""


def check_volumes(name: str, volumes: Tensor, *, cubic: bool = False) -> int:
    """Refuse anything but a finite float32 or float64 batch ``(B, 1, D, H, W)`` with at least :data:`MIN_SIZE`
    voxels along each axis (cubic when asked); return ``D``."""
    if volumes.dim() != 5 or volumes.shape[1] != 1 or min(volumes.shape, default=0) == 0:
        raise InputError(f"{name} has shape {tuple(volumes.shape)}; expected a batch of volumes (B, 1, D, H, W) in "
                         "torch order (z, y, x)")
    if min(volumes.shape[2:]) < MIN_SIZE:
        raise InputError(f"{name} has spatial shape {tuple(volumes.shape[2:])}; expected at least {MIN_SIZE} voxels "
                         "along each axis")
    # Half precision is refused too: the poses' matrix inverse (torch.linalg.inv_ex) has no float16 or bfloat16 kernel.
    if volumes.dtype not in (torch.float32, torch.float64):
        raise InputError(f"{name} has dtype {volumes.dtype}; expected float32 or float64 intensities in [0, 1]")
    if cubic and len(set(volumes.shape[2:])) != 1:
        raise InputError(f"{name} has spatial shape {tuple(volumes.shape[2:])}, not cubic; resample onto a canonical "
                         "N^3 grid first (dpcn_med.preprocess.solver_grid)")
    if not bool(torch.isfinite(volumes).all()):
        raise InputError(f"{name} contains NaN or infinite values; expected finite intensities in [0, 1]")
    return volumes.shape[2]


def uniform(generator: torch.Generator, shape: tuple[int, ...], low: float, high: float, *, like: Tensor) -> Tensor:
    """Uniform draws in ``[low, high)`` of ``shape``, on ``like``'s device and dtype."""
    draws = torch.rand(shape, generator=generator, device=generator.device, dtype=like.dtype)
    return (low + (high - low) * draws).to(like.device)


def normal(generator: torch.Generator, shape: tuple[int, ...], *, like: Tensor) -> Tensor:
    """Standard normal draws of ``shape``, on ``like``'s device and dtype."""
    return torch.randn(shape, generator=generator, device=generator.device, dtype=like.dtype).to(like.device)


def integers(generator: torch.Generator, high: int, count: int) -> list[int]:
    """``count`` integers uniform in ``[0, high)``, as Python ints (they choose axes and branches)."""
    return torch.randint(high, (count,), generator=generator, device=generator.device).tolist()


def host_generator(generator: torch.Generator) -> torch.Generator:
    """``generator`` itself on the CPU, else a CPU generator seeded from one of its draws.

    For the helpers that draw on the CPU only (:func:`dpcn_med.geometry.random_rotation`).
    """
    if generator.device.type == "cpu":
        return generator
    seed = torch.randint(2 ** 62, (), generator=generator, device=generator.device)
    return torch.Generator().manual_seed(int(seed))
