"""LC2, the linear correlation of linear combination (Wein et al. 2008), in torch, batched over poses and
differentiable in them: the refinement's similarity where one image is ultrasound.

Ultrasound shows tissue boundaries, with echoes that grow with the change of acoustic impedance across them, and
speckle; neither its intensities nor their histogram map one-to-one to a CT's or an MR's, which is what mutual
information assumes. LC2 fits the ultrasound locally, in every window of the ultrasound image, as a linear combination
``alpha * I + beta * |grad I| + gamma`` of the other image's intensity ``I`` and gradient magnitude, and scores the
share of the ultrasound's local variance that the fit explains. The windows' scores are pooled weighted by the
ultrasound's local variance, so that textured windows count and flat ones (shadow, fluid) do not. A probe on the
benchmark's cones (docs/design_notes/registration.md) found LC2 peaked within 4 mm of the true pose on 18 of 24
axis sweeps, Mattes mutual information on 2. No library offers it batched over poses on torch (ImFusion's is
closed), hence our own.

The windows tile the ultrasound's grid without overlapping (Wein et al. centre one on every voxel): each voxel is
read once, which made the search a tenth as costly, and held the true pose more often on the benchmark's cones (18
of 20 registrations started there, against 14; docs/design_notes/registration.md).

Convention:
    Every tensor is ``(K, T, V)``: ``K`` poses, ``T`` windows of ``V`` voxels each. ``ultrasound`` is the same for
    every pose (it broadcasts from ``(1, T, V)``); ``intensity`` and ``gradient`` are the other image sampled at each
    voxel mapped by each pose; ``valid`` (bool) says where both images hold data. The value is ``-LC2``, in
    ``[-1, 0]``: lower is better, as the refinement's mutual information.
"""

from __future__ import annotations

import torch
from torch import Tensor

WINDOW = 7
"""Voxels along each side of the cubic windows: Wein et al.'s patch size."""

MIN_WINDOW_SHARE = 0.5
"""A window scores only where at least this share of its voxels is valid: a fit on a few voxels at the edge of the
overlap explains anything."""

RIDGE = 1e-5
"""Added to the variances of ``intensity`` and ``gradient`` (both in ``[0, 1]``) before the local fit: a window where
the other image is flat (air, a uniform organ) explains nothing instead of dividing by zero."""

MIN_SCORED_WINDOWS = 8
"""A pose scoring fewer windows does not overlap the ultrasound: its value is ``inf``, as mutual information's is."""


def negative_lc2(ultrasound: Tensor, intensity: Tensor, gradient: Tensor, valid: Tensor) -> Tensor:
    """``-LC2`` of each pose, ``(K,)`` (module docstring for the shapes); ``inf`` for a pose that scores fewer than
    :data:`MIN_SCORED_WINDOWS` windows. Differentiable in ``intensity`` and ``gradient``."""
    weight = valid.to(intensity.dtype)
    count = weight.sum(-1)
    scored = count >= MIN_WINDOW_SHARE * valid.shape[-1]

    def mean(values: Tensor) -> Tensor:  # the mean over each window's valid voxels
        return (values * weight).sum(-1) / count.clamp_min(1)

    ultrasound = ultrasound.expand_as(intensity)
    mu, mi, mg = mean(ultrasound), mean(intensity), mean(gradient)
    u, i, g = ultrasound - mu.unsqueeze(-1), intensity - mi.unsqueeze(-1), gradient - mg.unsqueeze(-1)
    var_u, cov_ui, cov_ug = mean(u * u), mean(u * i), mean(u * g)
    var_i, cov_ig, var_g = mean(i * i) + RIDGE, mean(i * g), mean(g * g) + RIDGE
    # The least-squares fit of u by (i, g) explains c^T S^-1 c of u's variance, S the 2 x 2 covariance of (i, g) and
    # c their covariances with u; written out, as a batched solve per window costs more than the formula.
    determinant = (var_i * var_g - cov_ig * cov_ig).clamp_min(RIDGE * RIDGE)
    explained = (var_g * cov_ui * cov_ui - 2 * cov_ig * cov_ui * cov_ug + var_i * cov_ug * cov_ug) / determinant
    explained = torch.minimum(explained.clamp_min(0), var_u)
    weights = scored.to(var_u.dtype)
    total = (var_u * weights).sum(-1)
    value = -(explained * weights).sum(-1) / total.clamp_min(1e-12)
    enough = (scored.sum(-1) >= MIN_SCORED_WINDOWS) & (total > 0)
    return torch.where(enough, value, torch.full_like(value, float("inf")))
