"""The 2-D DPC solver: rotation over the full turn, scale and translation (4 DoF)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dpcn_med.geometry import rotation_2d, warp
from dpcn_med.solver.config import SolverConfig, StageTemperatures, override
from dpcn_med.solver.log_polar import LogPolarEstimate, log_polar_rotation_scale
from dpcn_med.solver.spectrum import magnitude_spectrum
from dpcn_med.solver.translation import TranslationEstimate, phase_translation
from dpcn_med.solver.validation import check_grids, check_mode


@dataclass
class Solve2dResult:
    """Pose found by :func:`solve2d`: ``fixed(p) ~ moving(scale * rotation @ p + translation)``.

    Attributes:
        rotation: ``(batch, 2, 2)`` ``fixed_to_moving`` rotation acting on pixel ``(x, y)`` from the grid centre.
        angle: ``(batch,)`` its angle in radians, ``[-pi, pi)``, counter-clockwise.
        scale: ``(batch,)`` (ones in rigid mode).
        translation: ``(batch, 2)`` pixels, order ``(x, y)``.
        confidence: ``(batch,)`` in ``[0, 1]``: softmax mass of the chosen translation peak.
        log_polar_estimate: the first (global) log-polar pass.
        translation_estimate: the translation stage of the last pass.
    """

    rotation: Tensor
    angle: Tensor
    scale: Tensor
    translation: Tensor
    confidence: Tensor
    log_polar_estimate: LogPolarEstimate
    translation_estimate: TranslationEstimate


def _translate(fixed_image: Tensor, moving: Tensor, linear: Tensor, config: SolverConfig,
               temperatures: StageTemperatures) -> TranslationEstimate:
    """Translation stage: ``moving (batch, 1, N, N)`` compensated by ``linear (batch, 2, 2)`` and phase-correlated
    with ``fixed_image (batch, N, N)``."""
    return phase_translation(fixed_image, warp(moving, linear)[:, 0], temperatures.translation, dim=2,
                             taper=config.taper, refine=config.refine, upsample=config.upsample)


def _rotation_scale(fixed_magnitude: Tensor, current: Tensor, config: SolverConfig, temperatures: StageTemperatures
                    ) -> LogPolarEstimate:
    """One log-polar pass: rotation (modulo half a turn) and scale of ``current (batch, N, N)`` against the fixed
    image's magnitude spectrum ``(batch, N, N)``."""
    return log_polar_rotation_scale(fixed_magnitude, magnitude_spectrum(current, 2, config.taper),
                                    config.log_polar_band, config.log_polar_radii, config.log_polar_angles,
                                    temperatures.rotation, refine=config.refine, upsample=config.upsample)


def _resolve_half_turn(fixed_image: Tensor, moving: Tensor, angle: Tensor, scale: Tensor, config: SolverConfig,
                       temperatures: StageTemperatures) -> Tensor:
    """Of ``angle`` and ``angle + pi`` (``(batch,)`` radians), the one whose compensated moving image has the higher
    translation peak: ``(batch,)``. ``|FFT|`` is point-symmetric, so the log-polar pass cannot tell them apart."""
    twins = torch.stack([angle, angle + math.pi], 1)  # (batch, 2)
    heights = []
    for k in range(2):
        trial = scale[:, None, None] * rotation_2d(twins[:, k])
        heights.append(_translate(fixed_image, moving, trial, config, temperatures).height)
    return twins.gather(1, torch.stack(heights, 1).argmax(1, keepdim=True))[:, 0]


def solve2d(fixed: Tensor, moving: Tensor, mode: str = "similarity", *, config: SolverConfig | None = None,
            temperatures: StageTemperatures | None = None, **options) -> Solve2dResult:
    """Globally register two images on the same square grid by phase correlation (4 or 3 DoF).

    Args:
        fixed: ``(batch, 1, N, N)`` real grid (torch order y, x), ``N`` even.
        moving: ``(batch, 1, N, N)`` same shape, device and dtype.
        mode: ``"similarity"`` (rotation, scale, translation) or ``"rigid"`` (scale fixed to 1).
        config: settings; defaults to :class:`SolverConfig` (the ``log_polar_*`` and ``iterations`` fields).
        temperatures: ``rotation`` is used for the log-polar correlation, ``translation`` for the translation.
        **options: overrides of ``config`` fields.

    Returns:
        A :class:`Solve2dResult` with ``fixed(p) ~ moving(scale * rotation @ p + translation)``.

    Raises:
        InputError: malformed grids, an unknown mode, or a setting or temperature out of range.

    Notes:
        Rotation and scale come from one correlation of the log-polar magnitude spectra, which is
        point-symmetric: the angle is known modulo 180 degrees. Both candidates are compensated and
        phase-correlated for translation; the higher peak wins. Later passes (``iterations``) warp the moving image
        by the estimate and measure the small residual, where interpolation errors are smallest.
    """
    config = override(config, **options)
    temperatures = temperatures or StageTemperatures()
    check_grids(fixed, moving, 2)
    check_mode(mode)
    batch = fixed.shape[0]
    fixed_image = fixed[:, 0]
    fixed_magnitude = magnitude_spectrum(fixed_image, 2, config.taper)
    angle = fixed.new_zeros(batch)
    scale = fixed.new_ones(batch)
    translation = fixed.new_zeros(batch, 2)
    first = None
    for iteration in range(config.iterations):
        current = moving[:, 0] if iteration == 0 else warp(moving, scale[:, None, None] * rotation_2d(angle),
                                                          translation)[:, 0]
        estimate = _rotation_scale(fixed_magnitude, current, config, temperatures)
        step_scale = estimate.scale if mode == "similarity" else torch.ones_like(estimate.scale)
        if iteration == 0:
            first = estimate
            step_angle = _resolve_half_turn(fixed_image, moving, estimate.angle, step_scale, config, temperatures)
        else:
            step_angle = estimate.angle
        # Compose the residual: moving(A (A_r p + t_r) + t) with t_r = 0 here; translation is re-measured below.
        angle = angle + step_angle
        scale = scale * step_scale
        linear = scale[:, None, None] * rotation_2d(angle)
        shift = _translate(fixed_image, moving, linear, config, temperatures)
        translation = (linear @ shift.shift[..., None])[..., 0]
    angle = torch.remainder(angle + math.pi, 2 * math.pi) - math.pi
    return Solve2dResult(rotation=rotation_2d(angle), angle=angle, scale=scale, translation=translation,
                         confidence=shift.peak.mass, log_polar_estimate=first, translation_estimate=shift)
