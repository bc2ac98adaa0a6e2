"""Entropy images: a structural representation of a volume that a one-to-one intensity map barely changes.

Each voxel gets the Shannon entropy of the intensity histogram of its neighbourhood (Wachinger and Navab,
"Entropy and Laplacian images: structural representations for multi-modal registration", Medical Image Analysis 2012).
Relabelling the intensities, even in a non-monotonic order (two MR contrasts that order the tissues differently),
permutes the histogram's bins and leaves the entropy as it was (nearly: the soft bins spread each level over its
neighbours, which a reordering changes): uniform tissue maps to low values, boundaries between tissues to high ones,
on either side of a pair. The solver correlates the entropy images' spheres as one more source of rotation
candidates (:attr:`dpcn_med.solver.SolverConfig.entropy_bins`), and ranks every candidate by its translation peak on
the entropy images beside the volumes' (:attr:`dpcn_med.solver.SolverConfig.entropy_ranking_weight`); the translation
is found on the volumes themselves.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

BIN_WIDTH = 0.5
"""Standard deviation, in bins, of the Gaussian that spreads each voxel over the histogram's bins (Parzen window):
soft bins keep the image differentiable and a little intensity noise from jumping between bins."""


def _smooth(volumes: Tensor, sigma: float) -> Tensor:
    """Separable Gaussian of ``sigma`` voxels over the last three dimensions of ``(..., N, N, N)``, edges replicated.

    Written here rather than taken from MONAI: the solver is pure PyTorch, and torch has no 3-D Gaussian filter. Each
    axis is one product with an ``(N, N)`` matrix that holds the kernel and the replicated edges, which is several
    times faster on a CPU than ``conv3d`` with a one-dimensional kernel.
    """
    size = volumes.shape[-1]
    radius = max(1, math.ceil(3.0 * sigma))
    taps = torch.arange(-radius, radius + 1, device=volumes.device, dtype=volumes.dtype)
    kernel = torch.exp(-0.5 * (taps / sigma) ** 2)
    kernel = kernel / kernel.sum()
    rows = torch.arange(size, device=volumes.device)[:, None]
    columns = (rows + torch.arange(-radius, radius + 1, device=volumes.device)).clamp(0, size - 1)
    matrix = torch.zeros(size, size, device=volumes.device, dtype=volumes.dtype)
    matrix.index_put_((rows.expand_as(columns), columns), kernel.expand_as(columns), accumulate=True)
    values = volumes @ matrix.T  # x
    values = matrix @ values  # y
    return (matrix @ values.flatten(-2)).view(volumes.shape)  # z


def soft_bins(volume: Tensor, bins: int) -> Tensor:
    """Each voxel's membership of ``bins`` histogram bins spread evenly over its volume's own intensity range.

    Args:
        volume: ``(batch, N, N, N)`` real grids.
        bins: number of bins; the lowest is centred on the volume's minimum, the highest on its maximum.

    Returns:
        ``(bins, batch, N, N, N)`` memberships (a Gaussian of :data:`BIN_WIDTH` bins around each voxel's position on
        the bins' scale, normalised over the bins): non-negative, summing to 1 over the first axis.
    """
    flat = volume.flatten(1)
    low = flat.amin(1).view(-1, 1, 1, 1)
    span = (flat.amax(1).view(-1, 1, 1, 1) - low).clamp_min(torch.finfo(volume.dtype).tiny)
    position = (volume - low) / span * (bins - 1)
    centres = torch.arange(bins, device=volume.device, dtype=volume.dtype).view(-1, 1, 1, 1, 1)
    return torch.softmax(-0.5 * ((position[None] - centres) / BIN_WIDTH) ** 2, dim=0)


def entropy_image(volume: Tensor, bins: int, sigma: float) -> Tensor:
    """The local-histogram entropy of each voxel.

    Args:
        volume: ``(batch, N, N, N)`` real grids.
        bins: histogram bins, spread evenly over each volume's own intensity range (its minimum to its maximum).
        sigma: standard deviation, in voxels, of the Gaussian window each voxel's histogram is taken over.

    Returns:
        ``(batch, N, N, N)`` entropies in nats, in ``[0, log(bins)]``; differentiable with respect to ``volume``.
        A uniform region maps to the entropy of its soft bins alone (about 0.37 nats on a bin centre), a boundary
        between tissues to more.
    """
    histogram = _smooth(soft_bins(volume, bins), sigma)
    histogram = histogram / histogram.sum(0, keepdim=True).clamp_min(torch.finfo(volume.dtype).tiny)
    return -(histogram * torch.log(histogram.clamp_min(torch.finfo(volume.dtype).tiny))).sum(0)
