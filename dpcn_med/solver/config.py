"""Defaults of the solver, defined once, and its learnable temperatures."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn


@dataclass(frozen=True)
class SolverConfig:
    """Settings of :func:`dpcn_med.solver.solve` and :func:`dpcn_med.solver.solve2d`.

    Attributes:
        bandwidth: ``B`` of the sphere and the SO(3) grid; ``None`` means half the grid size. At most half the grid
            size and at most 128.
        taper: apodisation window: fraction of the radius over which it falls to zero.
        sphere_band: radii aggregated onto the sphere, as fractions of the Nyquist radius (the band-pass).
        extra_sphere_bands: further bands, each with its own SO(3) correlation whose peaks join the candidates (the
            primary ``sphere_band`` alone gives the training's rotation distribution). The lowest radii carry the
            volume's outline, which cutting a slab or masking changes, and how high the anatomy's signal reaches
            depends on the image: slabs of 60% of the seg3d head (pseudo-CT to T1) registered more often with a band
            from 0.2 than from 0.05 (16 of 20 poses against 13), the upper half of the (smooth, averaged) MNI head
            the reverse (1 of 9 against 9 of 9). With 0.05-0.6 and 0.3-0.9 together (the higher band reaches the
            finer anatomy of a slab on the usual grid): 18 of 20 and 9 of 9 (docs/registration.md).
        sphere_radii: samples per ray, log-spaced.
        log_magnitude: aggregate ``log |FFT|`` (True) or ``|FFT|``.
        peaks: rotation peaks carried through scale and translation (top-k).
        half_turns: also try each peak composed with the 180-degree turns about the grid axes (both frames).
        rotation_half_width: half-width, in grid cells, of the SO(3) soft arg-max window.
        refine: inference mode: arg-max plus continuous/sub-grid refinement (True), or the differentiable soft
            arg-max everywhere (False, for training).
        refine_oversample: the fixed sphere used by the continuous rotation refinement has this times the bandwidth.
        refine_iterations: halvings of the rotation refinement's step.
        duplicate_degrees: candidates closer than this to a better one are dropped.
        sphere_margin: candidates whose sphere correlation is this much below the best are dropped.
        scale_bandwidth: the scale stage's profiles follow the SOFT grid of this bandwidth (``4 b^2`` directions).
        scale_band: radii of the scale profiles, fractions of the Nyquist radius.
        scale_radii: samples per profile, log-spaced.
        max_scale: the scale stage searches ``[1 / max_scale, max_scale]``.
        candidate_size: grid size on which all candidates are scored by their translation peak (downsampled).
        finalists: the best this many are scored again on a grid of ``finalist_size``.
        finalist_size: grid size of the second scoring.
        alternatives: also return up to this many runner-up candidates (the other finalists first), each with its own
            scale and translation, for a choice by another similarity (:attr:`SolveResult.alternatives`); 0: none.
        upsample: sub-grid refinement factor of the translation and scale peaks.
        log_polar_angles: 2-D only: angular samples of the log-polar grid over 180 degrees.
        log_polar_radii: 2-D only: log-radial samples.
        log_polar_band: 2-D only: radii as fractions of the Nyquist radius.
        iterations: 2-D only: log-polar passes; each later pass measures the residual pose after warping.
        profile: record per-stage wall-clock times in the result (synchronises CUDA at stage boundaries).
    """

    bandwidth: int | None = None
    taper: float = 0.25
    sphere_band: tuple[float, float] = (0.05, 0.6)
    extra_sphere_bands: tuple[tuple[float, float], ...] = ((0.3, 0.9),)
    sphere_radii: int = 24
    log_magnitude: bool = True
    peaks: int = 4
    half_turns: bool = True
    rotation_half_width: int = 1
    refine: bool = True
    refine_oversample: int = 2
    refine_iterations: int = 7
    duplicate_degrees: float = 20.0
    sphere_margin: float = 0.25
    scale_bandwidth: int = 8
    scale_band: tuple[float, float] = (0.05, 0.8)
    scale_radii: int = 64
    max_scale: float = 2.0
    candidate_size: int = 32
    finalists: int = 4
    finalist_size: int = 64
    alternatives: int = 0
    upsample: int = 16
    log_polar_angles: int = 360
    log_polar_radii: int = 256
    log_polar_band: tuple[float, float] = (0.03, 0.9)
    iterations: int = 2
    profile: bool = False


@dataclass
class StageTemperatures:
    """Softmax temperatures per stage (floats, or positive tensors when they are learned).

    Attributes:
        rotation: SO(3) correlation (3-D) or log-polar correlation (2-D); correlations lie in ``[-1, 1]``.
        scale: 1-D log-radius correlation (3-D).
        translation: phase correlation, whose peak is about 1 for a perfect match.
    """

    rotation: Tensor | float = 0.02
    scale: Tensor | float = 0.02
    translation: Tensor | float = 0.01


def _inverse_softplus(value: float) -> float:
    return value + math.log(-math.expm1(-value))


class Temperatures(nn.Module):
    """Learnable, positive temperatures: ``xi = softplus(parameter)``, initialised to :class:`StageTemperatures`."""

    def __init__(self, initial: StageTemperatures | None = None) -> None:
        super().__init__()
        initial = initial or StageTemperatures()
        self.raw = nn.ParameterDict({
            name: nn.Parameter(torch.tensor(_inverse_softplus(float(getattr(initial, name)))))
            for name in ("rotation", "scale", "translation")
        })

    def forward(self) -> StageTemperatures:
        """The current temperatures, differentiable with respect to the parameters."""
        return StageTemperatures(**{name: F.softplus(raw) for name, raw in self.raw.items()})
