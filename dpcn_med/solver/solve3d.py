"""The 3-D DPC solver: rotation, then scale, then translation, with candidate resolution (7 or 6 DoF)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor

from dpcn_med.geometry import affine_points, half_turns, sample, warp
from dpcn_med.solver.config import SolverConfig, StageTemperatures
from dpcn_med.solver.harmonics import even_degrees, isht, sht
from dpcn_med.solver.phase_correlation import phase_correlation
from dpcn_med.solver.scale import ScaleEstimate, log_polar_scale
from dpcn_med.solver.so3 import (deduplicate, refine_rotation, so3_correlation, so3_log_prob, so3_peaks, soft_argmax_so3,
                                 sphere_correlation)
from dpcn_med.solver.spectrum import apodize, magnitude_spectrum
from dpcn_med.solver.sphere import log_radii, normalize_sphere, quadrature_weights, sphere_directions, to_sphere
from dpcn_med.solver.translation import TranslationEstimate, phase_translation
from dpcn_med.solver.validation import check_bandwidth, check_grids, check_mode


@dataclass
class SolveResult:
    """Pose found by :func:`solve`: ``fixed(p) ~ moving(scale * rotation @ p + translation)``.

    Attributes:
        rotation: ``(B, 3, 3)`` ``moving_from_fixed`` rotation acting on voxel ``(x, y, z)`` from the grid centre.
        scale: ``(B,)`` isotropic scale (ones in rigid mode).
        translation: ``(B, 3)`` voxels, order ``(x, y, z)``.
        confidence: ``(B,)`` in ``[0, 1]``: softmax mass of the translation peak of the chosen candidate.
        rotation_log_prob: ``(B, 2B, 2B, 2B)`` log-softmax over the Euler grid ``[alpha, beta, gamma]`` (Haar-weighted),
            for the rotation KL loss.
        scale_estimate: the scale stage of the chosen candidate (``None`` in rigid mode).
        translation_estimate: the translation stage of the chosen candidate (shift before ``scale * rotation``).
        candidates: ``(B,)`` number of distinct rotation candidates that were scored.
    """

    rotation: Tensor
    scale: Tensor
    translation: Tensor
    confidence: Tensor
    rotation_log_prob: Tensor
    scale_estimate: ScaleEstimate | None
    translation_estimate: TranslationEstimate
    candidates: Tensor


def _spheres(fixed: Tensor, moving: Tensor, config: SolverConfig, bandwidth: int
             ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Magnitude spectra ``(B, N, N, N)`` and normalised spheres ``(B, 2B, 2B)`` of both volumes."""
    size = fixed.shape[-1]
    fixed_magnitude = magnitude_spectrum(fixed, 3, config.taper)
    moving_magnitude = magnitude_spectrum(moving, 3, config.taper)
    radii = log_radii(size, config.sphere_band, config.sphere_radii, device=fixed.device, dtype=fixed.dtype)
    directions = sphere_directions(bandwidth, device=fixed.device, dtype=fixed.dtype)
    weights = quadrature_weights(bandwidth, device=fixed.device, dtype=fixed.dtype)
    batch_directions = directions.expand(fixed.shape[0], *directions.shape)
    fixed_sphere = normalize_sphere(to_sphere(fixed_magnitude, batch_directions, radii,
                                              log_magnitude=config.log_magnitude), weights)
    moving_sphere = normalize_sphere(to_sphere(moving_magnitude, batch_directions, radii,
                                               log_magnitude=config.log_magnitude), weights)
    return fixed_magnitude, moving_magnitude, fixed_sphere, moving_sphere


def _with_half_turns(rotation: Tensor) -> Tensor:
    """``(B, K, 3, 3)`` -> ``(B, 7K, 3, 3)``: each rotation, then composed with the three half-turns on either side.

    A half-turn on the right is about a fixed-grid axis, on the left about a moving-grid axis: whichever volume has its
    mirror plane along the grid, the ambiguous twin of ``R`` is among these.
    """
    turns = half_turns(device=rotation.device, dtype=rotation.dtype)
    right = rotation[:, :, None] @ turns  # (B, K, 4, 3, 3), the first is R itself
    left = turns[1:] @ rotation[:, :, None]  # (B, K, 3, 3, 3)
    return torch.cat([right, left], dim=2).flatten(1, 2)


def _downsample(volume: Tensor, size: int) -> Tensor:
    """Average-pool ``(B, N, N, N)`` to ``(B, size, size, size)`` when ``N`` is a multiple of ``size``; else as is."""
    factor = volume.shape[-1] // size
    if factor <= 1 or volume.shape[-1] % size:
        return volume
    return F.avg_pool3d(volume[:, None], factor)[:, 0]


def _candidate_scores(fixed: Tensor, moving: Tensor, linear: Tensor, config: SolverConfig) -> Tensor:
    """Phase-correlation peak of each candidate on a coarse grid: ``linear (B, K, 3, 3)`` -> ``(B, K)``.

    The peak height measures how well the whole volume (not only its spectrum) agrees once rotated and scaled: it is
    what tells a rotation from its mirror twin.
    """
    coarse_fixed = _downsample(fixed, config.candidate_size)
    coarse_moving = _downsample(moving, config.candidate_size)
    batch, count = linear.shape[:2]
    sizes = tuple(coarse_moving.shape[-3:])
    warped = sample(coarse_moving[:, None], affine_points(sizes, linear))[:, 0]  # (B, K, n, n, n)
    fixed_batch = apodize(coarse_fixed, 3, config.taper)[:, None].expand(batch, count, *sizes).flatten(0, 1)
    surface, _ = phase_correlation(fixed_batch, apodize(warped.flatten(0, 1), 3, config.taper), 3)
    return surface.flatten(1).max(-1).values.reshape(batch, count)


def solve(fixed: Tensor, moving: Tensor, mode: str = "similarity", *, config: SolverConfig | None = None,
          temperatures: StageTemperatures | None = None, **options) -> SolveResult:
    """Globally register two volumes on the same cubic grid by differentiable phase correlation (DPC).

    Args:
        fixed: ``(B, 1, N, N, N)`` real grid (torch order z, y, x), ``N`` even.
        moving: ``(B, 1, N, N, N)`` same shape, device and dtype.
        mode: ``"similarity"`` (rotation, isotropic scale, translation: 7 DoF) or ``"rigid"`` (6 DoF).
        config: settings; defaults to :class:`SolverConfig`.
        temperatures: softmax temperatures; defaults to :class:`StageTemperatures`.
        **options: overrides of ``config`` fields, e.g. ``bandwidth=32, refine=False``.

    Returns:
        A :class:`SolveResult` with ``fixed(p) ~ moving(scale * rotation @ p + translation)``.

    Raises:
        InputError: malformed grids (shape, size, dtype, NaN/Inf), a bandwidth out of range or an unknown mode.

    Convention:
        Voxel coordinates ``(x, y, z)`` from the grid centre, ZYZ Euler grid and pull resampling, all as in
        :mod:`dpcn_med.geometry`.

    Notes:
        1. ``|FFT|`` of the apodised volumes removes translation; 2. averaging ``log |FFT|`` along rays onto the
        SOFT sphere removes scale; 3. the SO(3) correlation of the spheres gives the rotation peaks; each peak and its
        half-turn twins are refined and 4. carried through the log-radius scale stage and 5. a coarse translation
        phase correlation; the candidate with the highest translation peak wins and gets a full-resolution
        translation. With ``refine=False`` every estimate is a soft arg-max, differentiable with respect to both
        inputs and the temperatures.

    References:
        Chen et al., "DPCN++: Differentiable Phase Correlation Network for Versatile Pose Registration", IEEE TPAMI
        2024.
    """
    config = replace(config or SolverConfig(), **options)
    temperatures = temperatures or StageTemperatures()
    size = check_grids(fixed, moving, 3)
    check_mode(mode)
    bandwidth = check_bandwidth(config.bandwidth, size)
    fixed_volume, moving_volume = fixed[:, 0], moving[:, 0]
    batch = fixed.shape[0]

    fixed_magnitude, moving_magnitude, fixed_sphere, moving_sphere = _spheres(
        fixed_volume, moving_volume, config, bandwidth)
    degrees = even_degrees(bandwidth)
    fixed_coeffs = sht(fixed_sphere, degrees)
    correlation = so3_correlation(sht(moving_sphere, degrees), fixed_coeffs, bandwidth)
    peaks = so3_peaks(correlation, config.peaks)
    peak_rotation, _ = soft_argmax_so3(correlation, peaks, temperatures.rotation,
                                       half_width=config.rotation_half_width)
    candidates = _with_half_turns(peak_rotation) if config.half_turns else peak_rotation
    count = candidates.shape[1]
    weights = quadrature_weights(bandwidth, device=fixed.device, dtype=fixed.dtype)
    directions = sphere_directions(bandwidth, device=fixed.device, dtype=fixed.dtype)
    scale_radii = log_radii(size, config.scale_band, config.scale_radii, device=fixed.device, dtype=fixed.dtype)

    def scale_stage(rotation: Tensor) -> ScaleEstimate:
        """Scale for ``(B, K, 3, 3)`` rotations."""
        return log_polar_scale(fixed_magnitude, moving_magnitude, rotation, scale_radii, temperatures.scale,
                               directions_bandwidth=config.scale_bandwidth, max_scale=config.max_scale,
                               refine=config.refine,
                               upsample=config.upsample)

    with torch.no_grad():
        sphere_score = sphere_correlation(moving_sphere, fixed_sphere, weights, directions, candidates)
        keep = deduplicate(candidates, sphere_score, math.radians(config.duplicate_degrees))
        if mode == "similarity":
            candidate_scale = scale_stage(candidates).scale
        else:
            candidate_scale = torch.ones(batch, count, device=fixed.device, dtype=fixed.dtype)
        scores = _candidate_scores(fixed_volume, moving_volume, candidate_scale[..., None, None] * candidates,
                                   config)
        best = scores.masked_fill(~keep, float("-inf")).argmax(-1)
    rotation = candidates[torch.arange(batch, device=fixed.device), best]
    if config.refine:
        fine = bandwidth * config.refine_oversample
        fine_sphere = isht(fixed_coeffs, degrees, fine)  # the band-limited fixed sphere, finely sampled
        rotation, _ = refine_rotation(moving_sphere, fine_sphere, weights, directions, rotation[:, None],
                                      step=math.pi / bandwidth, iterations=config.refine_iterations)
        rotation = rotation[:, 0]

    scale_estimate = scale_stage(rotation[:, None]) if mode == "similarity" else None
    scale = scale_estimate.scale[:, 0] if scale_estimate is not None else torch.ones(
        batch, device=fixed.device, dtype=fixed.dtype)
    linear = scale[:, None, None] * rotation
    compensated = warp(moving, linear)[:, 0]
    translation_estimate = phase_translation(fixed_volume, compensated, temperatures.translation, dim=3,
                                             taper=config.taper, refine=config.refine, upsample=config.upsample)
    translation = (linear @ translation_estimate.shift[..., None])[..., 0]
    rotation_log_prob = so3_log_prob(correlation, temperatures.rotation)
    return SolveResult(rotation=rotation, scale=scale, translation=translation,
                       confidence=translation_estimate.peak.mass, rotation_log_prob=rotation_log_prob,
                       scale_estimate=scale_estimate, translation_estimate=translation_estimate,
                       candidates=keep.sum(-1))
