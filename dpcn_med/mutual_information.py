"""Mattes mutual information in torch, batched over poses and differentiable in them.

The same estimator as ITK's ``MattesMutualInformationImageToImageMetricv4`` (Mattes et al. 2003), written in torch so
that the refinement runs on the solver's device and scores every candidate pose in one pass: the fixed intensities
fall in their bin (a zero-order Parzen window), the moving ones spread over four bins by a cubic B-spline window,
whose derivative carries the gradient to the pose. ITK's metric is one pose per call and CPU only, hence our own.

Convention:
    ``fixed_bins`` are ``(N,)`` bin indices of N fixed samples, shared by every pose; ``moving`` and ``valid`` are
    ``(K, N)``: the moving image at each sample mapped by each of K poses, and whether the sample fell inside the
    moving image (and its mask). The value is ``-MI`` in nats: lower is better, as ITK's.
"""

from __future__ import annotations

import torch
from torch import Tensor

PADDING = 2
"""Empty bins at each end of the moving histogram, where the cubic window of the extreme values reaches (ITK's)."""

MIN_VALID_FRACTION = 0.01
"""A pose whose valid samples are fewer than this share of all samples (or fewer than :data:`MIN_VALID_SAMPLES`)
does not overlap: its metric is ``inf``, as ITK's metric raises 'do not sufficiently overlap'."""

MIN_VALID_SAMPLES = 64


def fixed_bins(values: Tensor, low: float, high: float, bins: int) -> Tensor:
    """Bin indices ``(N,)`` (int64, in ``[0, bins)``) of fixed intensities ``values`` spread over ``[low, high]``."""
    width = max(high - low, 1e-12) / bins
    return ((values - low) / width).floor().clamp(0, bins - 1).long()


def moving_window(values: Tensor, low: float, high: float, bins: int) -> tuple[Tensor, Tensor]:
    """The cubic B-spline Parzen window of moving intensities ``values`` (any shape ``S``) over ``bins`` bins of
    ``[low, high]`` (:data:`PADDING` empty bins each side): ``(first, weights)``, the first of four bins each value
    touches (int64, shape ``S``) and the four weights (shape ``S + (4,)``, summing to 1), differentiable in
    ``values``."""
    width = max(high - low, 1e-12) / (bins - 2 * PADDING)
    position = ((values - low) / width + PADDING).clamp(PADDING, bins - PADDING - 1e-4)
    floor = position.detach().floor()
    t = position - floor
    t2, t3 = t * t, t * t * t
    weights = torch.stack([(1 - t) ** 3, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], dim=-1) / 6
    return floor.long() - 1, weights


def negative_mutual_information(fixed: Tensor, moving: Tensor, valid: Tensor, moving_range: tuple[float, float],
                                bins: int) -> Tensor:
    """``-MI`` of each pose, ``(K,)``: ``fixed`` ``(N,)`` bin indices (:func:`fixed_bins`), ``moving`` ``(K, N)``
    intensities, ``valid`` ``(K, N)`` bool; ``inf`` for a pose with too few valid samples
    (:data:`MIN_VALID_FRACTION`)."""
    poses, count = moving.shape
    first, weights = moving_window(moving, *moving_range, bins)
    weights = weights * valid.unsqueeze(-1).to(weights.dtype)
    joint_index = (fixed.view(1, count, 1) * bins + first.unsqueeze(-1)
                   + torch.arange(4, device=moving.device).view(1, 1, 4))
    joint = torch.zeros(poses, bins * bins, dtype=weights.dtype, device=moving.device)
    joint = joint.scatter_add(1, joint_index.view(poses, -1), weights.view(poses, -1)).view(poses, bins, bins)
    total = joint.sum((1, 2), keepdim=True)
    p = joint / total.clamp_min(1e-12)
    p_fixed, p_moving = p.sum(2), p.sum(1)

    def entropy_terms(q: Tensor, dims: tuple[int, ...]) -> Tensor:  # sum q log q; empty bins contribute nothing
        return (q * q.clamp_min(1e-12).log()).sum(dims)

    information = entropy_terms(p, (1, 2)) - entropy_terms(p_fixed, (1,)) - entropy_terms(p_moving, (1,))
    valid_count = valid.sum(1)
    overlaps = (valid_count >= MIN_VALID_SAMPLES) & (valid_count >= MIN_VALID_FRACTION * count)
    return torch.where(overlaps, -information, torch.full_like(information, float("inf")))


def bin_entropy(bins: Tensor, count: int) -> float:
    """Shannon entropy (nats) of the histogram of bin indices ``bins`` ``(N,)`` over ``count`` bins: the fixed
    samples' entropy ``H(F)``, the most mutual information any pose can reach with them."""
    p = torch.bincount(bins, minlength=count).double() / max(int(bins.numel()), 1)
    return float(-(p * p.clamp_min(1e-300).log()).sum())
