"""The 3-D DPC solver: rotation, then scale, then translation, with candidate resolution (7 or 6 DoF)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from dpcn_med.errors import InputError
from dpcn_med.geometry import geodesic_distance, half_turns, warp
from dpcn_med.solver.config import SolverConfig, StageTemperatures, override
from dpcn_med.solver.cooccurrence import cooccurrence_spectrum
from dpcn_med.solver.entropy import entropy_image
from dpcn_med.solver.harmonics import isht, sht
from dpcn_med.solver.phase_correlation import phase_correlation
from dpcn_med.solver.scale import ScaleEstimate, log_polar_scale
from dpcn_med.solver.so3 import (
    deduplicate,
    refine_rotation,
    so3_correlation,
    so3_log_prob,
    so3_peaks,
    soft_argmax_so3,
    sphere_correlation,
)
from dpcn_med.solver.spectrum import apodize, magnitude_spectrum
from dpcn_med.solver.sphere import (
    even_degrees,
    log_radii,
    normalize_sphere,
    quadrature_weights,
    sphere_directions,
    to_sphere,
)
from dpcn_med.solver.timing import StageClock
from dpcn_med.solver.translation import TranslationEstimate, phase_translation
from dpcn_med.solver.validation import check_bandwidth, check_grids, check_mode


@dataclass
class Alternatives:
    """The runner-up candidates of :func:`solve`, best first, each with its own scale and translation: global poses
    for a later choice by an image similarity that phase correlation lacks (mutual information across modalities).

    ``A`` is at most ``SolverConfig.alternatives``: the plausible runner-ups of the volume of the batch that has the
    most, and at least 1. None is within ``SolverConfig.duplicate_degrees`` of a better-ranked candidate.

    Attributes:
        rotation: ``(batch, A, 3, 3)``, as :attr:`SolveResult.rotation`.
        scale: ``(batch, A)``.
        translation: ``(batch, A, 3)`` voxels ``(x, y, z)``.
        confidence: ``(batch, A)`` softmax mass of each translation peak, as :attr:`SolveResult.confidence`.
        score: ``(batch, A)`` the solver's ranking score: the translation-peak height (with the entropy images',
            the sum of each relative to its best: ``SolverConfig.entropy_ranking_weight``) on the finalist grid for
            the finalists, on the coarse grid after them; ``-inf`` marks a slot for which no plausible candidate was
            left: ignore its pose.
    """

    rotation: Tensor
    scale: Tensor
    translation: Tensor
    confidence: Tensor
    score: Tensor


@dataclass
class Ranking:
    """Every candidate of :func:`solve`, ranked best first (what a learned choice among them trains on).

    Attributes:
        rotation: ``(batch, K, 3, 3)`` fixed-to-moving rotations.
        scale: ``(batch, K)`` their scales (ones in rigid mode).
        score: ``(batch, K)`` the ranking score (as :attr:`Alternatives.score`); ``-inf`` marks a near-duplicate or
            implausible candidate.
    """

    rotation: Tensor
    scale: Tensor
    score: Tensor

    def errors(self, truth: Tensor) -> Tensor:
        """``(batch, K)`` each candidate's angle to ``truth`` ``(batch, 3, 3)``, in degrees (float64, no gradient);
        ``inf`` where the candidate was dropped."""
        angles = torch.rad2deg(geodesic_distance(self.rotation.detach().double(), truth.detach().double()[:, None]))
        return angles.masked_fill(self.score == float("-inf"), float("inf"))


@dataclass
class SolveResult:
    """Pose found by :func:`solve`: ``fixed(p) ~ moving(scale * rotation @ p + translation)``.

    Attributes:
        rotation: ``(batch, 3, 3)`` ``fixed_to_moving`` rotation acting on voxel ``(x, y, z)`` from the grid centre.
        scale: ``(batch,)`` isotropic scale (ones in rigid mode).
        translation: ``(batch, 3)`` voxels, order ``(x, y, z)``.
        confidence: ``(batch,)`` in ``[0, 1]``: softmax mass of the translation peak of the chosen candidate.
        rotation_log_prob: ``(batch, 2B, 2B, 2B)`` log-softmax over the Euler grid ``[alpha, beta, gamma]``
            (Haar-weighted), for the rotation KL loss.
        scale_estimate: the scale stage of the chosen candidate (``None`` in rigid mode).
        translation_estimate: the translation stage of the chosen candidate (shift before ``scale * rotation``).
        candidates: ``(batch,)`` number of rotation candidates left after dropping near-duplicates.
        timings: seconds per stage when ``profile=True`` (empty otherwise).
        alternatives: the runner-up candidates when ``alternatives > 0`` in the config, else (or with a single
            candidate) ``None``.
        ranking: every candidate, ranked (no translations: cheap).
    """

    rotation: Tensor
    scale: Tensor
    translation: Tensor
    confidence: Tensor
    rotation_log_prob: Tensor
    scale_estimate: ScaleEstimate | None
    translation_estimate: TranslationEstimate
    candidates: Tensor
    timings: dict[str, float]
    alternatives: Alternatives | None = None
    ranking: Ranking | None = None


@dataclass
class _Spectra:
    """What steps 1-3a of :func:`solve` leave for the later ones.

    Attributes:
        fixed_magnitude: ``(batch, N, N, N)`` ``fftshift``-ed magnitude spectrum of the fixed volume.
        moving_magnitude: same for the moving volume.
        directions: ``(2B, 2B, 3)`` unit vectors of the SOFT grid.
        weights: ``(2B,)`` its quadrature weights.
        degrees: the even degrees of the harmonic coefficients.
        spheres: ``(fixed, moving)`` normalised spheres ``(batch, 2B, 2B)`` per correlation, the primary band first:
            the volumes' correlations, then, for each entropy source (``entropy_bins``, then each of
            ``extra_entropy_bins``), as many of its entropy images in the same order.
        fixed_coeffs: ``(batch, L, 2M + 1)`` harmonic coefficients of each correlation's fixed sphere, weighted by
            degree.
        moving_coeffs: same for the moving spheres.
        entropy: ``(fixed, moving)`` the volumes' entropy images ``(batch, N, N, N)`` of ``entropy_bins`` (no graph),
            or ``None`` without it.
        sources: how many sources the correlations come from: the volumes, then each entropy source; each has as
            many correlations.
    """

    fixed_magnitude: Tensor
    moving_magnitude: Tensor
    directions: Tensor
    weights: Tensor
    degrees: tuple[int, ...]
    spheres: list[tuple[Tensor, Tensor]]
    fixed_coeffs: list[Tensor]
    moving_coeffs: list[Tensor]
    entropy: tuple[Tensor, Tensor] | None = None
    sources: int = 1


def _sphere(magnitude: Tensor, band: tuple[float, float], config: SolverConfig, directions: Tensor, weights: Tensor
            ) -> Tensor:
    """Normalised sphere ``(batch, 2B, 2B)`` of a magnitude spectrum ``(batch, N, N, N)``, aggregated over ``band``.

    ``directions (2B, 2B, 3)`` and ``weights (2B,)`` are the SOFT grid's unit vectors and quadrature weights.
    """
    radii = log_radii(magnitude.shape[-1], band, config.sphere_radii, device=magnitude.device, dtype=magnitude.dtype)
    batch_directions = directions.expand(magnitude.shape[0], *directions.shape)
    return normalize_sphere(to_sphere(magnitude, batch_directions, radii, log_magnitude=config.log_magnitude), weights)


def _spectra(fixed_volume: Tensor, moving_volume: Tensor, bandwidth: int, config: SolverConfig) -> _Spectra:
    """Steps 1-3a: magnitude spectra of ``(batch, N, N, N)`` volumes, their spheres per band, the spheres' harmonics
    (then, for each of ``config.extra_degree_two_weights``, the primary band's spheres and harmonics once more), and
    all of these again for the volumes' entropy images of ``config.entropy_bins`` and of each of
    ``config.extra_entropy_bins``, and for their co-occurrence spectra of ``config.cooccurrence_bins``."""
    directions = sphere_directions(bandwidth, device=fixed_volume.device, dtype=fixed_volume.dtype)
    weights = quadrature_weights(bandwidth, device=fixed_volume.device, dtype=fixed_volume.dtype)
    degrees = even_degrees(bandwidth)
    magnitudes = (magnitude_spectrum(fixed_volume, 3, config.taper), magnitude_spectrum(moving_volume, 3, config.taper))
    spheres, fixed_coeffs, moving_coeffs = _correlated(*magnitudes, config, directions, weights, degrees)
    entropy = None
    proposals = []  # (fixed, moving) spectra of each further source of candidates; why: docs/design_notes/solver.md
    # Proposals only, without a graph: no loss reaches them but through the choice, which is made under no_grad, and
    # their graph would double a training step's time and memory.
    with torch.no_grad():
        for bins in filter(None, (config.entropy_bins, *config.extra_entropy_bins)):
            images = tuple(entropy_image(volume, bins, config.entropy_sigma) for volume in (fixed_volume, moving_volume))
            if entropy is None and config.entropy_bins:  # the first source ranks beside the volumes
                entropy = images
            proposals.append(tuple(magnitude_spectrum(image, 3, config.taper) for image in images))
        if config.cooccurrence_bins:
            proposals.append(tuple(cooccurrence_spectrum(volume, config.cooccurrence_bins, config.taper)
                                   for volume in (fixed_volume, moving_volume)))
        for fixed_spectrum, moving_spectrum in proposals:
            more = _correlated(fixed_spectrum, moving_spectrum, config, directions, weights, degrees)
            spheres, fixed_coeffs, moving_coeffs = (first + second for first, second in
                                                    zip((spheres, fixed_coeffs, moving_coeffs), more))
    return _Spectra(fixed_magnitude=magnitudes[0], moving_magnitude=magnitudes[1], directions=directions,
                    weights=weights, degrees=degrees, spheres=spheres, fixed_coeffs=fixed_coeffs,
                    moving_coeffs=moving_coeffs, entropy=entropy, sources=1 + len(proposals))


def _correlated(fixed_magnitude: Tensor, moving_magnitude: Tensor, config: SolverConfig, directions: Tensor,
                weights: Tensor, degrees: tuple[int, ...]) -> tuple[list[tuple[Tensor, Tensor]], list[Tensor],
                                                                    list[Tensor]]:
    """Steps 2-3a for two magnitude spectra: ``(spheres, fixed_coeffs, moving_coeffs)``, one entry per correlation
    (each band's, then the primary band's once more for each of ``config.extra_degree_two_weights``), the
    coefficients weighted by degree."""
    bands = (config.sphere_band, *config.extra_sphere_bands)
    spheres = [(_sphere(fixed_magnitude, band, config, directions, weights),
                _sphere(moving_magnitude, band, config, directions, weights)) for band in bands]
    fixed_coeffs = [sht(fixed_sphere, degrees) for fixed_sphere, _ in spheres]
    moving_coeffs = [sht(moving_sphere, degrees) for _, moving_sphere in spheres]
    # Each extra degree-2 weight is one more correlation of the primary band, its peaks more candidates: the
    # primary band's spheres again, their coefficients weighted otherwise.
    weighting = [config.degree_two_weight] * len(spheres) + list(config.extra_degree_two_weights)
    spheres += [spheres[0]] * len(config.extra_degree_two_weights)
    fixed_coeffs += [fixed_coeffs[0]] * len(config.extra_degree_two_weights)
    moving_coeffs += [moving_coeffs[0]] * len(config.extra_degree_two_weights)
    return (spheres, [c * _degree_weights(degrees, w, c) for c, w in zip(fixed_coeffs, weighting)],
            [c * _degree_weights(degrees, w, c) for c, w in zip(moving_coeffs, weighting)])


def _degree_weights(degrees: tuple[int, ...], degree_two: float, like: Tensor) -> Tensor:
    """``(L, 1)`` weights of the harmonic coefficients ``like`` ``(batch, L, 2M + 1)`` of ``degrees``: ``degree_two``
    for degree 2, 1 for the others.

    Degree 2 is weighted in place rather than left out: the SO(3) tables are built for every even degree. A bandwidth
    of 4 has no other degree, and keeps it.
    """
    two = degree_two if len(degrees) > 1 else 1.0
    return torch.tensor([two if degree == 2 else 1.0 for degree in degrees], device=like.device,
                        dtype=like.real.dtype)[:, None]


def _with_half_turns(rotation: Tensor) -> Tensor:
    """``(batch, K, 3, 3)`` -> ``(batch, 7K, 3, 3)``: each rotation, then with the three half-turns on either side.

    A half-turn on the right is about a fixed-grid axis, on the left about a moving-grid axis: whichever volume has its
    mirror plane along the grid, the ambiguous twin of ``R`` is among these.
    """
    turns = half_turns(device=rotation.device, dtype=rotation.dtype)
    right = rotation[:, :, None] @ turns  # (batch, K, 4, 3, 3), the first is R itself
    left = turns[1:] @ rotation[:, :, None]  # (batch, K, 3, 3, 3)
    return torch.cat([right, left], dim=2).flatten(1, 2)


def _rotation_peaks(correlations: list[Tensor], config: SolverConfig, temperature: Tensor | float
                    ) -> tuple[list[Tensor], Tensor]:
    """Step 3b: the rotation candidates of each band's SO(3) correlation ``(batch, 2B, 2B, 2B)``.

    Returns:
        ``(per_band, origin)``: ``(batch, K_b, 3, 3)`` soft arg-max rotations of each band's peaks (with their
        half-turn twins when ``config.half_turns``), and ``(K,)`` the band each of the concatenated candidates came
        from.
    """
    per_band = []
    for correlation in correlations:
        peak_rotation, _ = soft_argmax_so3(correlation, so3_peaks(correlation, config.peaks), temperature,
                                           half_width=config.rotation_half_width)
        per_band.append(_with_half_turns(peak_rotation) if config.half_turns else peak_rotation)
    origin = torch.cat([torch.full((rotations.shape[1],), index, device=correlations[0].device)
                        for index, rotations in enumerate(per_band)])
    return per_band, origin


def _scale_stage(spectra: _Spectra, rotation: Tensor, config: SolverConfig, temperatures: StageTemperatures
                 ) -> ScaleEstimate:
    """Step 4: the scale for ``(batch, K, 3, 3)`` rotations."""
    return log_polar_scale(spectra.fixed_magnitude, spectra.moving_magnitude, rotation, config.scale_band,
                           config.scale_radii, temperatures.scale, directions_bandwidth=config.scale_bandwidth,
                           max_scale=config.max_scale, refine=config.refine, upsample=config.upsample)


def _downsample(volume: Tensor, size: int) -> Tensor:
    """Average-pool ``(batch, N, N, N)`` to ``(batch, n, n, n)``, ``n = size``, when ``N`` is a multiple of it; else as
    is."""
    factor = volume.shape[-1] // size
    if factor <= 1 or volume.shape[-1] % size:
        return volume
    return F.avg_pool3d(volume[:, None], factor)[:, 0]


def candidate_scores(fixed: Tensor, moving: Tensor, linear: Tensor, size: int, taper: float,
                     keep: Tensor | None = None) -> Tensor:
    """Phase-correlation peak of each candidate on a downsampled grid: ``fixed, moving (batch, N, N, N)`` and
    ``linear (batch, K, 3, 3)`` -> ``(batch, K)``, differentiable with respect to both volumes.

    The peak height measures how well the whole volume (not only its spectrum) agrees once rotated and scaled: it is
    what tells a rotation from its mirror twin. With ``keep (batch, K)``, only the candidates that some volume of the
    batch keeps are scored (most are near-duplicates or implausible), and the others are ``-inf``.
    """
    columns = None if keep is None else keep.any(0).nonzero()[:, 0]
    coarse_fixed = _downsample(fixed, size)
    coarse_moving = _downsample(moving, size)
    scored = linear if columns is None else linear[:, columns]
    warped = warp(coarse_moving[:, None], scored)[:, 0]  # (batch, K, n, n, n)
    # The fixed volume's spectrum broadcasts over the K candidates: one FFT, not K.
    surface, _ = phase_correlation(apodize(coarse_fixed, 3, taper)[:, None], apodize(warped, 3, taper), 3)
    scores = surface.flatten(2).amax(-1)
    if columns is None:
        return scores
    return scores.new_full(keep.shape, float("-inf")).index_copy(1, columns, scores).masked_fill(~keep, float("-inf"))


def _ranking_scores(fixed: Tensor, moving: Tensor, entropy: tuple[Tensor, Tensor] | None, linear: Tensor,
                    size: int, config: SolverConfig, keep: Tensor | None = None) -> Tensor:
    """:func:`candidate_scores` on the volumes, and with ``entropy`` (both volumes' entropy images) plus
    ``entropy_ranking_weight`` times the same on the entropy images, each divided by its best over the volume's
    candidates (their peaks have scales of their own)."""
    scores = candidate_scores(fixed, moving, linear, size, config.taper, keep=keep)
    if entropy is None:
        return scores
    images = candidate_scores(*entropy, linear, size, config.taper, keep=keep)
    return sum(weight * part / part.amax(-1, keepdim=True).clamp_min(torch.finfo(part.dtype).tiny)
               for weight, part in ((1.0, scores), (config.entropy_ranking_weight, images)))


def _rank_candidates(fixed: Tensor, moving: Tensor, linear: Tensor, sphere_score: Tensor, keep: Tensor,
                     config: SolverConfig, entropy: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """The candidates ``linear (batch, K, 3, 3)`` (scaled rotations) ranked, best first: indices ``(batch, K)`` and
    scores ``(batch, K)``: the finalists by their fine score, then the others by their coarse score; ``-inf`` marks
    an implausible candidate.

    Candidates whose sphere correlation falls more than ``sphere_margin`` below the best are implausible; the rest
    are scored by their translation peak on a coarse grid, and the ``finalists`` best are scored again on a finer one
    (why two grids: docs/design_notes/solver.md); with ``entropy``, the volumes' entropy images ``(fixed, moving)``,
    each score is :func:`_ranking_scores`' sum over the volumes and their entropy images.
    """
    plausible = keep & (sphere_score >= sphere_score.masked_fill(~keep, float("-inf")).amax(-1, keepdim=True)
                        - config.sphere_margin)
    coarse = _ranking_scores(fixed, moving, entropy, linear, config.candidate_size, config, keep=plausible)
    finalists = coarse.topk(min(config.finalists, coarse.shape[1]), dim=-1)
    finalist_linear = linear.gather(1, finalists.indices[..., None, None].expand(-1, -1, 3, 3))
    fine = _ranking_scores(fixed, moving, entropy, finalist_linear, config.finalist_size, config,
                           keep=finalists.values > float("-inf"))
    ranked = fine.sort(-1, descending=True)
    # The other candidates follow, by their coarse score (-inf: implausible).
    rest = coarse.scatter(1, finalists.indices, float("-inf")).sort(-1, descending=True)
    others = coarse.shape[1] - finalists.indices.shape[1]
    return (torch.cat([finalists.indices.gather(1, ranked.indices), rest.indices[:, :others]], 1),
            torch.cat([ranked.values, rest.values[:, :others]], 1))


def _resolve_candidates(fixed_volume: Tensor, moving_volume: Tensor, spectra: _Spectra, per_band: list[Tensor],
                        candidates: Tensor, mode: str, config: SolverConfig, temperatures: StageTemperatures,
                        entropy: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Drop near-duplicate and implausible candidates, measure each one's scale, rank them by translation peak.

    Args:
        fixed_volume, moving_volume: ``(batch, N, N, N)`` the volumes the candidates are scored on.
        spectra: steps 1-3a of both volumes.
        per_band: ``(batch, K_b, 3, 3)`` the candidates of each band.
        candidates: ``(batch, K, 3, 3)`` all of them, ``per_band`` concatenated.
        mode, config, temperatures: as :func:`solve`.
        entropy: entropy images ``(fixed, moving)`` to rank on beside the volumes (:func:`_rank_candidates`).

    Returns:
        ``(keep, scale, ranked, score)``: ``(batch, K)`` the candidates left after dropping near-duplicates, their
        scales (ones in rigid mode), and the ranking of :func:`_rank_candidates` (indices and scores).
    """
    # Each candidate's sphere correlation in its own band, less that band's best: correlations of different
    # bands are not comparable, their shortfalls from the best are.
    sphere_score = torch.cat([score - score.amax(-1, keepdim=True) for score in (
        sphere_correlation(moving_sphere, fixed_sphere, spectra.weights, spectra.directions, rotations)
        for (fixed_sphere, moving_sphere), rotations in zip(spectra.spheres, per_band))], 1)
    # Near-duplicates are dropped within each source: sphere scores of the volumes and of their entropy images do
    # not say which of two close candidates is the better one.
    per_source = len(per_band) // spectra.sources  # each source has as many correlations
    sizes = [sum(rotations.shape[1] for rotations in per_band[start:start + per_source])
             for start in range(0, len(per_band), per_source)]
    keep = torch.cat([deduplicate(part, score, math.radians(config.duplicate_degrees)) for part, score in
                      zip(candidates.split(sizes, 1), sphere_score.split(sizes, 1))], 1)
    if mode == "similarity":
        scale = _scale_stage(spectra, candidates, config, temperatures).scale
    else:
        scale = torch.ones(*candidates.shape[:2], device=candidates.device, dtype=candidates.dtype)
    ranked, score = _rank_candidates(fixed_volume, moving_volume, scale[..., None, None] * candidates, sphere_score,
                                     keep, config, entropy)
    return keep, scale, ranked, score


def _translation_stage(fixed: Tensor, moving: Tensor, linear: Tensor, temperature: Tensor | float,
                       config: SolverConfig, refine: bool) -> tuple[Tensor, TranslationEstimate]:
    """Translation for each scaled rotation ``linear (batch, K, 3, 3)``: ``moving (batch, 1, N, N, N)`` compensated by
    it and phase-correlated with ``fixed (batch, N, N, N)``, as one batch of ``batch * K`` pairs.

    Returns:
        ``translation (batch, K, 3)`` voxels ``(x, y, z)`` and the estimate over the ``batch * K`` pairs (its shift is
        before ``linear``).
    """
    batch, count = linear.shape[:2]
    compensated = warp(moving, linear)[:, 0].flatten(0, 1)  # (batch * K, N, N, N)
    repeated = fixed[:, None].expand(-1, count, *fixed.shape[1:]).flatten(0, 1)
    estimate = phase_translation(repeated, compensated, temperature, dim=3, taper=config.taper, refine=refine,
                                 upsample=config.upsample)
    return (linear @ estimate.shift.view(batch, count, 3, 1))[..., 0], estimate


def _alternatives(fixed_volume: Tensor, moving: Tensor, candidates: Tensor, scale: Tensor, ranked: Tensor,
                  score: Tensor, config: SolverConfig, temperatures: StageTemperatures) -> Alternatives:
    """The runner-up candidates (``ranked[:, 1:]``, up to ``config.alternatives``), each with a full-resolution
    translation; near-duplicates of a better-ranked candidate (of the other source, the entropy images' or the
    volumes') are passed over."""
    rows = torch.arange(candidates.shape[0], device=candidates.device)[:, None]
    rank = torch.arange(ranked.shape[1], device=ranked.device, dtype=score.dtype)
    distinct = deduplicate(candidates[rows, ranked], (-rank).expand_as(score), math.radians(config.duplicate_degrees))
    runner_up = distinct & (score > float("-inf")) & (rank > 0)
    # The runner-ups first, in their order; slots no volume of the batch has one for are left out rather than
    # translated at full resolution (one at least, so that the shapes stay those of a runner-up).
    order = (~runner_up).to(torch.int8).sort(dim=-1, stable=True).indices
    count = max(1, min(config.alternatives, int(runner_up.sum(-1).amax())))
    others, valid = ranked.gather(1, order[:, :count]), runner_up.gather(1, order[:, :count])
    rotations, scales = candidates[rows, others], scale[rows, others]
    translations, estimate = _translation_stage(fixed_volume, moving, scales[..., None, None] * rotations,
                                                temperatures.translation, config, refine=True)
    return Alternatives(rotation=rotations, scale=scales, translation=translations,
                        confidence=estimate.peak.mass.view(scales.shape),
                        score=score.gather(1, order[:, :count]).masked_fill(~valid, float("-inf")))


def _refine_chosen(spectra: _Spectra, rotation: Tensor, band: Tensor, bandwidth: int, config: SolverConfig) -> Tensor:
    """Continuous refinement of the chosen ``(batch, 3, 3)`` rotations, each on the sphere of its ``(batch,)`` band,
    the fixed one re-sampled ``config.refine_oversample`` times finer."""
    refined = rotation
    for index in band.unique().tolist():
        fine_sphere = isht(spectra.fixed_coeffs[index], spectra.degrees, bandwidth * config.refine_oversample)
        candidate, _ = refine_rotation(spectra.spheres[index][1], fine_sphere, spectra.weights, spectra.directions,
                                       rotation[:, None], step=math.pi / bandwidth, iterations=config.refine_iterations)
        refined = torch.where((band == index)[:, None, None], candidate[:, 0], refined)
    return refined


def _chosen_scale(spectra: _Spectra, rotation: Tensor, mode: str, config: SolverConfig,
                  temperatures: StageTemperatures) -> tuple[ScaleEstimate | None, Tensor]:
    """Step 4 for the chosen ``(batch, 3, 3)`` rotations: the estimate (``None`` in rigid mode) and ``(batch,)``
    scales (ones in rigid mode)."""
    if mode != "similarity":
        return None, torch.ones(rotation.shape[0], device=rotation.device, dtype=rotation.dtype)
    estimate = _scale_stage(spectra, rotation[:, None], config, temperatures)
    return estimate, estimate.scale[:, 0]


def solve(fixed: Tensor, moving: Tensor, mode: str = "similarity", *, config: SolverConfig | None = None,
          temperatures: StageTemperatures | None = None, score_volumes: tuple[Tensor, Tensor] | None = None,
          scale_rotation: Tensor | None = None, **options) -> SolveResult:
    """Globally register two volumes on the same cubic grid by differentiable phase correlation (DPC).

    Args:
        fixed: ``(batch, 1, N, N, N)`` real grid (torch order z, y, x), ``N`` even.
        moving: ``(batch, 1, N, N, N)`` same shape, device and dtype.
        mode: ``"similarity"`` (rotation, isotropic scale, translation: 7 DoF) or ``"rigid"`` (6 DoF).
        config: settings; defaults to :class:`SolverConfig`.
        temperatures: softmax temperatures; defaults to :class:`StageTemperatures`.
        score_volumes: ``(fixed, moving)`` grids shaped as ``fixed`` on which the candidates are ranked by their
            translation peak (a learned model's translation-stage features); defaults to ``fixed`` and ``moving``.
        scale_rotation: ``(batch, 3, 3)`` rotation the scale stage measures at instead of the chosen one (training:
            the true rotation, as the translation stage is compensated by the truth); the result's rotation is still
            the chosen one.
        **options: overrides of ``config`` fields, e.g. ``bandwidth=32, refine=False``.

    Returns:
        A :class:`SolveResult` with ``fixed(p) ~ moving(scale * rotation @ p + translation)``. With ``refine=False``
        every estimate is a soft arg-max, differentiable with respect to both inputs and the temperatures (but for a
        rotation chosen from the entropy images' candidates, which are computed without a graph).

    Raises:
        InputError: malformed grids (shape, size, dtype, NaN/Inf, empty batch), a bandwidth out of range, an unknown
            mode, a setting or temperature out of range, or score_volumes not shaped as the inputs.

    Convention:
        Voxel coordinates ``(x, y, z)`` from the grid centre, ZYZ Euler grid and pull resampling, all as in
        :mod:`dpcn_med.geometry`. The stages: docs/design_notes/solver.md.

    References:
        Chen et al., "DPCN++: Differentiable Phase Correlation Network for Versatile Pose Registration", IEEE TPAMI
        2024.
    """
    config = override(config, **options)
    temperatures = temperatures or StageTemperatures()
    size = check_grids(fixed, moving, 3)
    check_mode(mode)
    bandwidth = check_bandwidth(config.bandwidth, size)
    fixed_volume, moving_volume = fixed[:, 0], moving[:, 0]
    if score_volumes is None:
        score_fixed, score_moving = fixed_volume, moving_volume
    else:
        if any(volume.shape != fixed.shape for volume in score_volumes):
            raise InputError(f"score_volumes {[tuple(v.shape) for v in score_volumes]}: expected two grids of the "
                             f"inputs' shape {tuple(fixed.shape)}")
        score_fixed, score_moving = (volume[:, 0] for volume in score_volumes)
    clock = StageClock(fixed.device, config.profile)
    with clock("spectrum and sphere"):
        spectra = _spectra(fixed_volume, moving_volume, bandwidth, config)
    with clock("so3 correlation"):
        correlations = [so3_correlation(moving_band, fixed_band, bandwidth)
                        for fixed_band, moving_band in zip(spectra.fixed_coeffs, spectra.moving_coeffs)]
    with clock("peaks"):
        per_band, origin = _rotation_peaks(correlations, config, temperatures.rotation)
        candidates = torch.cat(per_band, 1)
    with clock("candidates"), torch.no_grad():
        # The volumes' entropy images rank beside them, not beside a model's translation features, which it trains
        # to rank alone.
        entropy = spectra.entropy if score_volumes is None and config.entropy_ranking_weight > 0 else None
        keep, candidate_scale, ranked, ranked_score = _resolve_candidates(
            score_fixed.detach(), score_moving.detach(), spectra, per_band, candidates, mode, config, temperatures,
            entropy)
    rows = torch.arange(fixed.shape[0], device=fixed.device)[:, None]
    rotation = candidates[rows[:, 0], ranked[:, 0]]
    alternatives = None
    if config.alternatives > 0 and candidates.shape[1] > 1:  # one candidate (one peak, no half-turns): no runner-up
        with clock("alternatives"), torch.no_grad():
            alternatives = _alternatives(fixed_volume, moving, candidates, candidate_scale, ranked, ranked_score,
                                         config, temperatures)
    if config.refine:  # inference only: a local search has no useful gradient, so build no graph for it
        with clock("rotation refinement"), torch.no_grad():
            rotation = _refine_chosen(spectra, rotation, origin[ranked[:, 0]], bandwidth, config)
    with clock("scale"):
        scale_estimate, scale = _chosen_scale(spectra, rotation if scale_rotation is None else
                                              scale_rotation.to(rotation.dtype), mode, config, temperatures)
    with clock("translation"):
        translation, translation_estimate = _translation_stage(
            fixed_volume, moving, (scale[:, None, None] * rotation)[:, None], temperatures.translation, config,
            config.refine)
    return SolveResult(rotation=rotation, scale=scale, translation=translation[:, 0],
                       confidence=translation_estimate.peak.mass,
                       rotation_log_prob=so3_log_prob(correlations[0], temperatures.rotation),  # the primary band's
                       scale_estimate=scale_estimate, translation_estimate=translation_estimate,
                       candidates=keep.sum(-1), timings=clock.seconds, alternatives=alternatives,
                       ranking=Ranking(rotation=candidates[rows, ranked], scale=candidate_scale[rows, ranked],
                                       score=ranked_score))
