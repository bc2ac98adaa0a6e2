"""Defaults of the solver, defined once, and its learnable temperatures."""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, fields, replace

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dpcn_med.arguments import check_flag, check_integer, check_pair, check_real, check_sequence, shown
from dpcn_med.errors import InputError
from dpcn_med.solver.validation import MAX_BANDWIDTH

_COUNT_MINIMUMS = {
    "sphere_radii": 1, "peaks": 1, "rotation_half_width": 0, "refine_oversample": 1, "refine_iterations": 0,
    "scale_bandwidth": 1, "scale_radii": 16, "candidate_size": 8, "finalists": 1, "finalist_size": 8,
    "alternatives": 0, "upsample": 1, "log_polar_angles": 12, "log_polar_radii": 20, "iterations": 1,
}
"""Least value of each integer field of :class:`SolverConfig`: below it the solver fails or measures a wrong pose
(the measurements: docs/design_notes/solver.md)."""

_COUNT_MAXIMUMS = {
    "sphere_radii": 1024, "peaks": 64, "rotation_half_width": 16, "refine_oversample": 8, "refine_iterations": 30,
    "scale_bandwidth": MAX_BANDWIDTH, "scale_radii": 4096, "candidate_size": 2 * MAX_BANDWIDTH, "finalists": 64,
    "finalist_size": 2 * MAX_BANDWIDTH, "upsample": 256, "log_polar_angles": 8192,
    "log_polar_radii": 8192, "iterations": 32,
}
"""Most of each integer field of :class:`SolverConfig`, far above the defaults and every shipped setting: beyond
them a value is a typo. ``alternatives`` has no maximum: only the candidates there are come back (the reasons:
docs/design_notes/solver.md)."""

_FLAGS = ("log_magnitude", "half_turns", "refine", "profile")

DEFAULT_BANDWIDTH = 32
"""The bandwidth ``B`` of a registration and of a new model when none is given: fast on a CPU."""

MIN_TEMPERATURE = 1e-12
"""Least float temperature, ten orders of magnitude below the defaults: anything near it is a hard arg-max already
(why this value: docs/design_notes/solver.md)."""


@dataclass(frozen=True)
class SolverConfig:
    """Settings of :func:`dpcn_med.solver.solve` and :func:`dpcn_med.solver.solve2d`.

    Attributes:
        bandwidth: ``B`` of the sphere and the SO(3) grid; ``None`` means half the grid size. At most half the grid
            size and at most 128.
        taper: apodisation window: fraction of the radius over which it falls to zero.
        sphere_band: radii aggregated onto the sphere, as fractions of the Nyquist radius (the band-pass).
        extra_sphere_bands: further bands, each with its own SO(3) correlation whose peaks join the candidates (the
            primary ``sphere_band`` alone gives the training's rotation distribution; why a second band:
            docs/design_notes/solver.md).
        sphere_radii: samples per ray, log-spaced.
        log_magnitude: aggregate ``log |FFT|`` (True) or ``|FFT|``.
        degree_two_weight: 3-D only: weight, in ``[0, 1]``, of the spheres' degree-2 harmonics in the rotation
            correlation and its refinement (1: as every other degree; 0: left out; degree 0, the mean, never takes
            part). Degree 2, the spectrum's ellipsoid, is where resolution that differs by direction (thick slices)
            shows most; weighted down it helps such pairs and hurts slabs (measured: docs/design_notes/solver.md).
        extra_degree_two_weights: 3-D only: further correlations of the primary ``sphere_band`` with degree 2 at
            each of these weights, whose peaks join the candidates (like ``extra_sphere_bands``').
        entropy_bins: 3-D only: when at least 2, the entropy images (:mod:`dpcn_med.solver.entropy`) of both volumes,
            with this many histogram bins, go through every correlation the volumes go through, and their peaks join
            the candidates: rotations that a non-monotonic intensity map between the two volumes does not move.
            Near-duplicates are dropped within each source; all are ranked together, as ``entropy_ranking_weight``
            says. 0: none (why 8: docs/design_notes/solver.md).
        entropy_sigma: the entropy images' window, standard deviation in grid voxels.
        extra_entropy_bins: 3-D only: further sources of candidates, each the entropy images of both volumes with
            this many bins (2 to 256; the window of ``entropy_sigma``), through every correlation the volumes go
            through. Near-duplicates are dropped within each source; they propose and take no part in the ranking.
            Empty (the default): none, as the learning-free ranking gains nothing from them (measured:
            docs/design_notes/solver.md).
        entropy_ranking_weight: 3-D only, with ``entropy_bins``: the candidates are ranked by their translation peak
            on the volumes plus this times their peak on the entropy images, each divided by its best over the
            volume's candidates (0: by the volumes' peak alone). Not where :func:`dpcn_med.solver.solve` ranks on
            ``score_volumes`` (a model's translation features, whose ranking it trains). Why 1:
            docs/design_notes/solver.md.
        cooccurrence_bins: 3-D only: when at least 2, the co-occurrence spectra (:mod:`dpcn_med.solver.cooccurrence`)
            of both volumes, over this many soft intensity bins, go through every correlation the volumes go through,
            and their peaks join the candidates as a source of their own (near-duplicates dropped within it; ranked
            with the others). 0 (the default): none (measured: docs/design_notes/solver.md).
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
        scale_radii: samples per profile, log-spaced; at least 16.
        max_scale: the scale stage searches ``[1 / max_scale, max_scale]`` (3-D; ``solve2d``'s log-polar grid
            searches every scale its radii span).
        candidate_size: grid size on which all candidates are scored by their translation peak (downsampled).
        finalists: the best this many are scored again on a grid of ``finalist_size``.
        finalist_size: grid size of the second scoring.
        alternatives: also return up to this many runner-up candidates (the other finalists first), each with its own
            scale and translation, for a choice by another similarity (:attr:`SolveResult.alternatives`); 0: none.
        upsample: sub-grid refinement factor of the translation and scale peaks.
        log_polar_angles: 2-D only: angular samples of the log-polar grid over 180 degrees; at least 12.
        log_polar_radii: 2-D only: log-radial samples; at least 20.
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
    degree_two_weight: float = 1.0
    extra_degree_two_weights: tuple[float, ...] = (0.3,)
    entropy_bins: int = 8
    entropy_sigma: float = 1.0
    extra_entropy_bins: tuple[int, ...] = ()
    entropy_ranking_weight: float = 1.0
    cooccurrence_bins: int = 0
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

    def __post_init__(self) -> None:
        """Check every field's type and range; store lists as tuples and numpy scalars as Python numbers.

        Raises:
            InputError: a value of the wrong type or out of range, named with the range expected.
        """
        checked = {name: check_integer(name, getattr(self, name), minimum=minimum, maximum=_COUNT_MAXIMUMS.get(name))
                   for name, minimum in _COUNT_MINIMUMS.items()}
        checked.update({name: check_flag(name, getattr(self, name)) for name in _FLAGS})
        if self.bandwidth is not None:
            checked["bandwidth"] = check_integer("bandwidth", self.bandwidth, minimum=4, maximum=MAX_BANDWIDTH)
        checked["taper"] = check_real("taper", self.taper, minimum=0.0, maximum=1.0)
        checked["duplicate_degrees"] = check_real("duplicate_degrees", self.duplicate_degrees, minimum=0.0,
                                                  maximum=180.0)
        checked["sphere_margin"] = check_real("sphere_margin", self.sphere_margin, minimum=0.0)
        checked["degree_two_weight"] = check_real("degree_two_weight", self.degree_two_weight, minimum=0.0,
                                                  maximum=1.0)
        checked["extra_degree_two_weights"] = tuple(
            check_real(f"extra_degree_two_weights[{index}]", weight, minimum=0.0, maximum=1.0)
            for index, weight in enumerate(check_sequence("extra_degree_two_weights", self.extra_degree_two_weights,
                                                          nonempty=False)))
        checked["entropy_bins"] = check_integer("entropy_bins", self.entropy_bins, minimum=0, maximum=256)
        if checked["entropy_bins"] == 1:
            raise InputError("entropy_bins is 1: one bin has no entropy; expected 0 (no entropy images) or 2 to 256")
        checked["extra_entropy_bins"] = tuple(
            check_integer(f"extra_entropy_bins[{index}]", bins, minimum=2, maximum=256)
            for index, bins in enumerate(check_sequence("extra_entropy_bins", self.extra_entropy_bins,
                                                        nonempty=False)))
        checked["cooccurrence_bins"] = check_integer("cooccurrence_bins", self.cooccurrence_bins, minimum=0,
                                                     maximum=256)
        if checked["cooccurrence_bins"] == 1:
            raise InputError("cooccurrence_bins is 1: one bin co-occurs everywhere; expected 0 (none) or 2 to 256")
        checked["entropy_sigma"] = check_real("entropy_sigma", self.entropy_sigma, minimum=0.0, above=True,
                                              maximum=16.0)
        checked["entropy_ranking_weight"] = check_real("entropy_ranking_weight", self.entropy_ranking_weight,
                                                       minimum=0.0, maximum=16.0)
        checked["max_scale"] = check_real("max_scale", self.max_scale, minimum=1.0, above=True)
        for name in ("sphere_band", "scale_band", "log_polar_band"):
            checked[name] = _band(name, getattr(self, name))
        checked["extra_sphere_bands"] = tuple(
            _band(f"extra_sphere_bands[{index}]", band)
            for index, band in enumerate(check_sequence("extra_sphere_bands", self.extra_sphere_bands,
                                                        nonempty=False)))
        for name, value in checked.items():
            object.__setattr__(self, name, value)  # frozen: the normalised value replaces the given one


def override(config: SolverConfig | None, **options: object) -> SolverConfig:
    """``config`` (default :class:`SolverConfig`) with the fields in ``options`` replaced, each checked.

    Raises:
        InputError: ``config`` that is no :class:`SolverConfig`, an option that is no field of it (the message
            suggests the closest field), or a value out of range.
    """
    if config is not None and not isinstance(config, SolverConfig):
        raise InputError(f"config is {shown(config)}; expected a SolverConfig or None")
    names = [field.name for field in fields(SolverConfig)]
    for name in options:
        if name not in names:
            close = difflib.get_close_matches(name, names, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise InputError(f"solver option {name!r} is unknown{hint}; expected one of {', '.join(names)}")
    return replace(config or SolverConfig(), **options)


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

    def __post_init__(self) -> None:
        """Check that each temperature is a finite number of at least :data:`MIN_TEMPERATURE` or a 0-d
        floating-point tensor.

        Raises:
            InputError: a temperature that is neither.
        """
        for name in ("rotation", "scale", "translation"):
            setattr(self, name, _temperature(f"{name} temperature", getattr(self, name)))


def _band(name: str, value: object) -> tuple[float, float]:
    """``(low, high)`` radii as fractions of the Nyquist radius, ``0 < low < high <= 1`` (beyond 1 a ray leaves
    the spectrum along the axes, and the log spacing needs ``low > 0``)."""
    return check_pair(name, value, minimum=0.0, maximum=1.0, above=True, note=" (fractions of the Nyquist radius)")


def _temperature(name: str, value: object) -> Tensor | float:
    """``value`` if it is a finite float of at least :data:`MIN_TEMPERATURE`, or a 0-d floating-point tensor, whose
    value is not read (no device synchronisation; why: docs/design_notes/solver.md)."""
    if not isinstance(value, Tensor):
        return check_real(name, value, minimum=MIN_TEMPERATURE)
    if not value.is_floating_point() or value.dim() != 0:
        raise InputError(f"{name} is {shown(value)} of shape {tuple(value.shape)} and dtype {value.dtype}; expected "
                         f"a finite number >= {MIN_TEMPERATURE} (a float) or a 0-d floating-point tensor")
    return value


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
