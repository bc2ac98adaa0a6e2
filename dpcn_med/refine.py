"""The local refinement: SimpleITK Mattes mutual information from the global candidates, and the choice among them.

:func:`choose_and_refine` is the fourth step of :func:`dpcn_med.register`: every start (the solver's candidates, the
stored pose last) runs the coarsest level of one shared image pyramid (:func:`search_levels`), the best go on level by
level (:func:`refine_candidates`), and the refined transform is kept only where it lowers the metric. Where one image
is ultrasound the metric is LC2 on the ultrasound's grid instead (:func:`correlation_levels`). The settings are
:class:`Refinement`; the measurements behind them are in docs/design_notes/registration.md.

Convention:
    Every transform maps fixed points to moving points (ITK's resampling direction), LPS mm. ``masks`` are
    ``(fixed, moving)``: binary images in each image's physical space that restrict where the metric is sampled, or
    ``None``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
import torch

from dpcn_med.arguments import check_flag, check_integer, check_real, check_sequence
from dpcn_med.errors import InputError
from dpcn_med.geometry import homogeneous_matrix, similarity_transform
from dpcn_med.local_search import (
    CorrelationLevel,
    Level,
    Samples,
    Volume,
    correlation_level,
    fixed_samples,
    itk_step_weights,
    pyramid_level,
    regular_step_descent,
    residual_matrices,
    volume,
    with_gradient,
)
from dpcn_med.mutual_information import bin_entropy
from dpcn_med.preprocess import bounding_box, clip_outliers, dilate
from dpcn_med.threads import side_by_side

Masks = tuple[sitk.Image | None, sitk.Image | None]

CPU = torch.device("cpu")

MIN_STEP_MM = 0.01
"""The finest level's descent stops when its step falls under this (mm; ITK's examples' minimum step)."""

COARSE_STOP_VOXELS = 0.02
"""A coarser level's descent stops when its step falls under this share of the level's finest voxel spacing (0.08 mm on
4 mm voxels), the finest level's at :data:`MIN_STEP_MM`: the next level goes on from there with a step of half its
own voxel (why this share: docs/design_notes/registration.md)."""


@dataclass(frozen=True)
class Refinement:
    """Settings of the local Mattes mutual-information refinement (SimpleITK), defined once (the measurements behind
    the defaults: docs/design_notes/registration.md). Where one image is ultrasound the refinement scores LC2 on one
    level instead (:data:`ULTRASOUND_PYRAMID`, :data:`ULTRASOUND_STARTS`): ``shrink_factors``, ``smoothing_mm``,
    ``histogram_bins`` and ``survivors`` do not apply to it.

    Attributes:
        shrink_factors: image pyramid, coarse to fine (integers >= 1).
        smoothing_mm: Gaussian sigma per level, mm (>= 0, one per shrink factor).
        samples: random metric samples per level (capped at every voxel), at least 1000.
        coarse_samples: at least 1000, or ``None`` for ``samples``: at most this many of them on the coarsest level of
            :func:`refine_candidates`, where every start runs, when there are several levels (the finer levels and
            :func:`refine_transform` take ``samples``).
        histogram_bins: Mattes histogram bins, at least 8.
        iterations: optimiser iterations per level, at least 1.
        max_step_mm: largest first step of the regular-step gradient descent at the coarsest level, as a physical
            shift in mm (> 0), or ``None`` (default) for half the finest voxel spacing of the fixed image's coarsest
            level (:func:`first_step_mm`): 4 mm for a 2 mm image shrunk 4 times, 2 mm for a 1 mm one. In
            :func:`refine_candidates` each finer level starts at this times its shrink factor over the coarsest
            one's (4, 2, 1 mm for the 2 mm image); :func:`refine_transform`, one SimpleITK run over the levels,
            starts each at this step.
        mask_margin_voxels: the fixed foreground, dilated by this many (preprocessing) voxels, is where the metric is
            sampled when the user gives no fixed mask.
        starts: global candidates refined: the solver's choice and up to ``starts - 1`` runner-ups (1: its choice
            only). Every one runs the coarsest pyramid level (:func:`refine_candidates`).
        survivors: at most how many of them (at least 1) go on to each next level, by their metric (the last value
            holds for the rest); only those ``close`` to the best go on.
        close: in ``(0, 1]``: a start stays in the search only while its metric (``-MI``) is at most ``close`` times
            the best start's: it stops when the best has converged on a level, and goes on to the next level only
            if it is that close (1: only ties go on; the best goes on alone where no other is close).
        stored_start: the stored pose (identity) is one more start, after the solver's candidates, so that inputs
            already roughly aligned (one scanner frame, or aligned by hand) stay aligned where phase correlation
            misses. Where the stored pose leaves no overlap (unrelated scanner frames) it is dropped before any work,
            like any candidate.
        seed: sampling seed in ``[1, 2**32 - 1]`` (the same inputs give the same result; SimpleITK takes 0 for
            ``sitkWallClock``, a new seed on every run).

    Raises:
        InputError: a value of the wrong type or out of range, named with its value.
    """

    shrink_factors: tuple[int, ...] = (4, 2, 1)
    smoothing_mm: tuple[float, ...] = (2.0, 1.0, 0.0)
    samples: int = 30_000
    coarse_samples: int | None = 10_000
    histogram_bins: int = 32
    iterations: int = 100
    max_step_mm: float | None = None
    mask_margin_voxels: int = 3
    starts: int = 16
    survivors: tuple[int, ...] = (6, 1)
    close: float = 0.5
    stored_start: bool = True
    seed: int = 20261123

    def __post_init__(self) -> None:
        factors = tuple(check_integer(f"shrink_factors[{level}]", factor, minimum=1)
                        for level, factor in enumerate(check_sequence("shrink_factors", self.shrink_factors)))
        smoothing = check_sequence("smoothing_mm", self.smoothing_mm)
        if len(smoothing) != len(factors):
            raise InputError(f"smoothing_mm is {self.smoothing_mm!r}: {len(smoothing)} values; expected "
                             f"{len(factors)}, one per level of shrink_factors {factors}")
        checked = {
            "shrink_factors": factors,
            "smoothing_mm": tuple(check_real(f"smoothing_mm[{level}]", sigma, minimum=0)
                                  for level, sigma in enumerate(smoothing)),
            "samples": check_integer("samples", self.samples, minimum=1000),
            "coarse_samples": None if self.coarse_samples is None else check_integer(
                "coarse_samples", self.coarse_samples, minimum=1000),
            "histogram_bins": check_integer("histogram_bins", self.histogram_bins, minimum=8),
            "iterations": check_integer("iterations", self.iterations, minimum=1),
            "max_step_mm": None if self.max_step_mm is None else check_real("max_step_mm", self.max_step_mm,
                                                                             minimum=0, above=True),
            "mask_margin_voxels": check_integer("mask_margin_voxels", self.mask_margin_voxels, minimum=0),
            "starts": check_integer("starts", self.starts, minimum=1),
            "survivors": tuple(check_integer(f"survivors[{level}]", count, minimum=1)
                               for level, count in enumerate(check_sequence("survivors", self.survivors))),
            "close": check_real("close", self.close, minimum=0, above=True, maximum=1),
            "stored_start": check_flag("stored_start", self.stored_start),
            # SimpleITK's seed is an unsigned 32-bit integer, and 0 is sitkWallClock: a new seed on every run.
            "seed": check_integer("seed", self.seed, minimum=1, maximum=2 ** 32 - 1),
        }
        for name, value in checked.items():
            object.__setattr__(self, name, value)


MIN_LEVEL_VOXELS = 4
"""The refinement's pyramid shrinks an axis no further than to this many voxels."""


def level_factors(size: Sequence[int], factor: int) -> list[int]:
    """Per-axis shrink factors of a pyramid level of ``factor`` for an image of ``size`` voxels: an axis keeps at
    least :data:`MIN_LEVEL_VOXELS` voxels (thinner, ITK's metric fails on the level's images)."""
    return [max(1, min(factor, length // MIN_LEVEL_VOXELS)) for length in size]


def first_step_mm(settings: Refinement, spacing: Sequence[float]) -> float:
    """The regular-step gradient descent's first step (mm) at the coarsest level of fixed voxel ``spacing`` (mm):
    ``settings.max_step_mm``, or half the finest of ``spacing`` where that is ``None``."""
    return settings.max_step_mm if settings.max_step_mm is not None else 0.5 * float(min(spacing))


def check_mask_extent(mask: sitk.Image | None, name: str, settings: Refinement) -> None:
    """Refuse a mask too small for the refinement: its box must span :data:`MIN_LEVEL_VOXELS` voxels of the coarsest
    pyramid level along each axis, as every level's images do.

    Args:
        mask: a binary mask already checked (not empty), or ``None`` (nothing to check).
        name: the mask's file or argument, for the message.

    Raises:
        InputError: the mask's box is thinner than that along some axis; the message gives both sizes in mm.
    """
    if mask is None:
        return
    box = bounding_box(mask)[1]  # io.check_mask refused an empty mask
    needed = MIN_LEVEL_VOXELS * np.asarray(level_factors(mask.GetSize(), settings.shrink_factors[0]))
    if (box < needed).any():
        spacing = np.asarray(mask.GetSpacing())
        raise InputError(f"{name}: too small to refine: its box is {_mm(box * spacing)} mm; the refinement needs at "
                         f"least {_mm(needed * spacing)} mm ({MIN_LEVEL_VOXELS} voxels of its coarsest level along "
                         "each axis); give a larger mask, or register without refinement (refine=False, "
                         "--no-refine), whose confidence then says whether the mask held enough")


def _mm(lengths: np.ndarray) -> str:
    return " x ".join(f"{length:g}" for length in np.round(lengths, 1))


def metric_masks(fixed_mask: sitk.Image | None, fixed_foreground: sitk.Image, moving_mask: sitk.Image | None,
                 settings: Refinement, *, ultrasound: str | None = None) -> Masks:
    """Where the metric is sampled: the user's masks; without a fixed one, the fixed foreground dilated by
    ``settings.mask_margin_voxels`` (background air otherwise dominates the joint histogram), unless the fixed image
    is the ``ultrasound`` (``"fixed"``): its foreground is its brightest echoes, and LC2 reads the whole cone
    (:func:`correlation_levels`)."""
    if fixed_mask is not None or ultrasound == "fixed":
        return fixed_mask, moving_mask
    return dilate(fixed_foreground, settings.mask_margin_voxels), moving_mask


def _registration_method(fixed: sitk.Image, masks: Masks, settings: Refinement) -> sitk.ImageRegistrationMethod:
    method = sitk.ImageRegistrationMethod()
    method.SetMetricAsMattesMutualInformation(numberOfHistogramBins=settings.histogram_bins)
    method.SetInterpolator(sitk.sitkLinear)
    # Gradients at the sample points only: ITK's default filters the whole image, seconds on a 1 mm head.
    method.MetricUseFixedImageGradientFilterOff()
    method.MetricUseMovingImageGradientFilterOff()
    if masks[0] is not None:
        method.SetMetricFixedMask(masks[0])
    if masks[1] is not None:
        method.SetMetricMovingMask(masks[1])
    method.SetMetricSamplingStrategy(method.RANDOM)
    voxels = np.prod(fixed.GetSize())
    fractions = [min(1.0, settings.samples * factor ** 3 / voxels) for factor in settings.shrink_factors]
    method.SetMetricSamplingPercentagePerLevel(fractions, settings.seed)
    return method


def _crop_to_mask(image: sitk.Image, mask: sitk.Image) -> sitk.Image:
    """``image`` cropped to the box (on its own grid) that holds every voxel of ``mask`` (any grid, same space)."""
    box = bounding_box(mask)
    if box is None:
        return image
    start, size = box
    corners = [mask.TransformContinuousIndexToPhysicalPoint((start + (size - 1) * np.asarray(corner) + 0.5 * (
        2 * np.asarray(corner) - 1)).tolist()) for corner in np.ndindex(2, 2, 2)]
    indices = np.array([image.TransformPhysicalPointToContinuousIndex(point) for point in corners])
    low = np.clip(np.floor(indices.min(0)).astype(int), 0, np.asarray(image.GetSize()) - 1)
    high = np.clip(np.ceil(indices.max(0)).astype(int), 0, np.asarray(image.GetSize()) - 1)
    return sitk.RegionOfInterest(image, (high - low + 1).tolist(), low.tolist())


def _float32(image: sitk.Image) -> sitk.Image:
    """``image`` as float32, the pixel type the registration method wants; no copy when it is one already."""
    return image if image.GetPixelID() == sitk.sitkFloat32 else sitk.Cast(image, sitk.sitkFloat32)


def mattes_metric(fixed: sitk.Image, moving: sitk.Image, fixed_to_moving: sitk.Transform, masks: Masks,
                  settings: Refinement = Refinement(), *, crop: bool = True) -> float | None:
    """Mattes mutual information of the pair under ``fixed_to_moving`` at full resolution (lower is better).

    Every voxel of the fixed mask counts, whatever the sampling settings (SimpleITK's ``MetricEvaluate`` visits them
    all), and the fixed image is cropped to the mask's box first, which gives the same value.

    Args:
        crop: crop the fixed image to the fixed mask's box; ``False`` where the caller has cropped it already.

    Returns:
        The metric, or ``None`` where the transform maps no sampled fixed point into the moving image (no overlap,
        e.g. two unrelated scanner frames taken as they are stored).
    """
    method = _registration_method(fixed, masks, settings)
    if crop and masks[0] is not None:
        fixed = _crop_to_mask(fixed, masks[0])
    method.SetMetricSamplingStrategy(method.NONE)
    method.SetInitialTransform(fixed_to_moving)
    try:
        return method.MetricEvaluate(_float32(fixed), _float32(moving))
    except RuntimeError as error:
        if _lost_overlap(error):
            return None
        raise


def _lost_overlap(error: RuntimeError) -> bool:
    """Whether SimpleITK's metric failed because the images, as mapped, (almost) do not overlap."""
    return "do not sufficiently overlap" in str(error) or "outside moving image buffer" in str(error)


@dataclass(frozen=True)
class Choice:
    """What :func:`choose_and_refine` chose.

    Attributes:
        index: the start it kept, an index into its ``starts``.
        fixed_to_moving: that start refined, or the start itself where refining did not lower the metric.
        refined: whether ``fixed_to_moving`` is the refined transform.
        metric: the similarity (lower is better) at ``"stored"`` (identity), ``"dpc"`` (the start kept) and
            ``"refined"`` on the finest level (``None`` where the pose leaves no overlap, or nothing was refined).
        candidate_metrics: each start's metric after the coarsest level (``None`` without overlap).
        fixed_entropy: entropy (nats) of the finest level's fixed samples over the metric's bins, the most mutual
            information a pose can reach with them (``None`` without refinement, or with LC2): the metric's own
            scale.
        similarity: ``"mattes"`` (``-MI``, nats) or ``"lc2"`` (``-LC2``, where one image is ultrasound).
    """

    index: int
    fixed_to_moving: sitk.Transform
    refined: bool
    metric: dict[str, float | None]
    candidate_metrics: list[float | None]
    fixed_entropy: float | None = None
    similarity: str = "mattes"


def search_levels(fixed: sitk.Image, moving: sitk.Image, masks: Masks, centre: np.ndarray,
                  settings: Refinement = Refinement(), device: torch.device = CPU) -> list[Level]:
    """The search's levels, coarse to fine, on ``device``: both images smoothed (``settings.smoothing_mm``) and
    shrunk (``settings.shrink_factors``, :func:`level_factors`) once for every start, and up to ``settings.samples``
    fixed samples of each inside the fixed mask (on the coarsest of several levels at most
    ``settings.coarse_samples``), drawn with ``settings.seed``."""
    counts = [settings.samples] * len(settings.shrink_factors)
    if len(counts) > 1 and settings.coarse_samples is not None:
        counts[0] = min(settings.coarse_samples, settings.samples)

    def fixed_side() -> list[Samples]:
        fixed_volume, generator = volume(fixed, device), torch.Generator().manual_seed(settings.seed)
        return [fixed_samples(pyramid_level(fixed_volume, level_factors(fixed.GetSize(), factor), sigma), masks[0],
                              count, settings.histogram_bins, centre, generator)
                for factor, sigma, count in zip(settings.shrink_factors, settings.smoothing_mm, counts, strict=True)]

    def moving_side() -> list[tuple[Volume, tuple[float, float]]]:
        """Each level's moving image with its gradient (:func:`with_gradient`), and the range of its values."""
        moving_volume, levels = volume(moving, device), []
        for factor, sigma in zip(settings.shrink_factors, settings.smoothing_mm, strict=True):
            level = pyramid_level(moving_volume, level_factors(moving.GetSize(), factor), sigma)
            levels.append((with_gradient(level), (float(level.values.min()), float(level.values.max()))))
        return levels

    # The two sides at once: 0.20 s against 0.25 s on the demo pair (docs/design_notes/registration.md).
    samples, moving_levels = side_by_side(fixed_side, moving_side)
    moving_mask = None if masks[1] is None else volume(masks[1], device)
    return [Level(samples=level_samples, moving=gradient, moving_mask=moving_mask, bins=settings.histogram_bins,
                  moving_range=moving_range)
            for level_samples, (gradient, moving_range) in zip(samples, moving_levels, strict=True)]


ULTRASOUND_SIDES = ("fixed", "moving")


def ultrasound_side(fixed_modality: str, moving_modality: str) -> str | None:
    """Which image the refinement scores as ultrasound (by LC2) for a pair of modalities as used (``"ct"``,
    ``"mr"``, ``"us"``): ``"fixed"`` or ``"moving"`` where exactly one is ``"us"``, else ``None`` (Mattes mutual
    information; two ultrasound volumes share their kind of intensities)."""
    if (fixed_modality == "us") == (moving_modality == "us"):
        return None
    return "fixed" if fixed_modality == "us" else "moving"


ULTRASOUND_PYRAMID = {"shrink_factors": (1,), "smoothing_mm": (0.0,)}
"""The LC2 search's one level: the images as they are. Coarser or smoother levels first led it away from the true
pose on the benchmark's cones (docs/design_notes/registration.md)."""

ULTRASOUND_STARTS = 2
"""Starts refined by LC2, those of best LC2 where they are (:func:`_refine_best_starts`)."""


def correlation_levels(fixed: sitk.Image, moving: sitk.Image, masks: Masks, centre: np.ndarray, ultrasound: str,
                       settings: Refinement = Refinement(), device: torch.device = CPU) -> list[CorrelationLevel]:
    """The search's levels, coarse to fine, where the ``ultrasound`` image (``"fixed"`` or ``"moving"``) is scored
    by LC2 against the other (:class:`dpcn_med.local_search.CorrelationLevel`): both images smoothed and shrunk as
    in :func:`search_levels`.

    The ultrasound holds data where it is nonzero (outside its cone a scanner writes 0) and inside its mask; on each
    level, where that stays whole after the level's smoothing and shrinking (a voxel the smoothing mixed with the
    outside is left out). The other image's mask restricts where it is read. Both images are taken as read: far
    outliers are clipped here (:func:`dpcn_med.preprocess.clip_outliers`), after the ultrasound's zeros are found."""
    us_image, other_image = (fixed, moving) if ultrasound == "fixed" else (moving, fixed)
    us_mask, other_mask = masks if ultrasound == "fixed" else masks[::-1]
    inside = sitk.Cast(us_image != 0, sitk.sitkUInt8)
    us_image, other_image = clip_outliers(us_image), clip_outliers(other_image)
    if us_mask is not None:
        inside = inside * sitk.Resample(sitk.Cast(us_mask > 0, sitk.sitkUInt8), us_image, sitk.Transform(),
                                        sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
    us_volume, inside_volume = volume(us_image, device), volume(inside, device)
    other_volume = volume(other_image, device)
    other_mask_volume = None if other_mask is None else volume(other_mask, device)
    generator = torch.Generator().manual_seed(settings.seed)
    levels = []
    for factor, sigma in zip(settings.shrink_factors, settings.smoothing_mm, strict=True):
        us_factors = level_factors(us_image.GetSize(), factor)
        us_level = pyramid_level(us_volume, us_factors, sigma)
        whole = pyramid_level(inside_volume, us_factors, sigma).values >= 0.999
        other_level = pyramid_level(other_volume, level_factors(other_image.GetSize(), factor), sigma)
        samples = fixed_samples(us_level if ultrasound == "fixed" else other_level, masks[0], settings.samples,
                                settings.histogram_bins, centre, generator)
        levels.append(correlation_level(us_level, whole, other_level, other_mask_volume, samples,
                                        ultrasound_fixed=ultrasound == "fixed"))
    return levels


def choose_and_refine(fixed: sitk.Image, moving: sitk.Image, starts: list[sitk.Transform], masks: Masks,
                      settings: Refinement = Refinement(), progress: Callable[[float], None] | None = None,
                      device: torch.device = CPU, ultrasound: str | None = None) -> Choice:
    """Refine every start (:func:`refine_candidates`), keep the best, and keep its refined transform only if that
    lowers the metric on the finest level.

    Args:
        fixed: the fixed image as read.
        moving: the moving image as read.
        starts: fixed to moving, the solver's choice first, the stored pose last when it is one; all rigid
            (``VersorRigid3DTransform``) or all similarity transforms.
        masks: where the metric is sampled (:func:`metric_masks`).
        progress: called with the fraction of the refinement done, in ``[0, 1]``.
        device: where the search runs (the solver's device).
        ultrasound: which image is ultrasound, ``"fixed"`` or ``"moving"``: the search scores LC2
            (:func:`correlation_levels`) instead of Mattes mutual information, and the choice's ``metric`` holds
            ``-LC2`` (``fixed_entropy`` is then ``None``); ``None``: neither.
    """
    if ultrasound is not None and ultrasound not in ULTRASOUND_SIDES:
        raise InputError(f"ultrasound is {ultrasound!r}; expected one of {ULTRASOUND_SIDES} or None")
    centre = np.asarray(starts[0].GetFixedParameters()[:3])
    rigid = starts[0].GetName() == "VersorRigid3DTransform"
    levels: list[Level] | list[CorrelationLevel]
    if ultrasound is None:
        # The metric's histogram spans each image's range: far outliers would squeeze the anatomy into its first bin.
        levels = search_levels(*side_by_side(lambda: clip_outliers(fixed), lambda: clip_outliers(moving)), masks, centre,
                               settings, device)
    else:
        settings = dataclasses.replace(settings, **ULTRASOUND_PYRAMID)
        levels = correlation_levels(fixed, moving, masks, centre, ultrasound, settings, device)
    matrices = torch.as_tensor(np.stack([homogeneous_matrix(start) for start in starts]), device=device)
    if ultrasound is None:
        index, refined, candidate_metrics = refine_candidates(levels, matrices, centre, rigid, settings, progress)
    else:
        index, refined, candidate_metrics = _refine_best_starts(levels, matrices, centre, rigid, settings, progress)
    finest = levels[-1]
    checked = torch.stack([torch.eye(4, dtype=torch.float64, device=device), matrices[index],
                           matrices[index] if refined is None else refined])
    values = finest.metric(checked, torch.zeros(3, 6 if rigid else 7, dtype=torch.float64, device=device),
                           centre).tolist()
    metric: dict[str, float | None] = {key: value if math.isfinite(value) else None
                                       for key, value in zip(("stored", "dpc", "refined"), values)}
    entropy = bin_entropy(finest.samples.bins, finest.bins) if ultrasound is None else None
    similarity = "mattes" if ultrasound is None else "lc2"
    if refined is None or metric["dpc"] is None:
        metric["refined"] = None
    # The local optimiser only ever starts from a global estimate; keep it only if it improved the metric.
    elif metric["refined"] is not None and metric["refined"] <= metric["dpc"]:
        transform = similarity_transform(refined.cpu().numpy(), centre, rigid=rigid)
        return Choice(index, transform, True, metric, candidate_metrics, entropy, similarity)
    return Choice(index, starts[index], False, metric, candidate_metrics, entropy, similarity)


def _refine_best_starts(levels: list[CorrelationLevel], starts: torch.Tensor, centre: np.ndarray, rigid: bool,
                        settings: Refinement, progress: Callable[[float], None] | None
                        ) -> tuple[int, torch.Tensor | None, list[float | None]]:
    """:func:`refine_candidates` on LC2 levels from the :data:`ULTRASOUND_STARTS` starts of best LC2 as they are, and
    the last start (the stored pose, where it is one).

    LC2 holds the true pose only within a few millimetres (docs/design_notes/registration.md): a start farther off
    stays about where it was, at about its value, so one batched evaluation ranks them at a fraction of refining
    each. The starts left out keep that value as their metric."""
    count = 6 if rigid else 7
    with torch.no_grad():
        values = levels[0].metric(starts, torch.zeros(len(starts), count, dtype=torch.float64,
                                                      device=starts.device), centre)
    ranked = [index for index in torch.argsort(values).tolist() if math.isfinite(float(values[index]))]
    # The last start (the stored pose, where it is one) always goes on: a tracked probe's pose is right within LC2's
    # reach, and a wrong pose elsewhere in the head can hold more LC2 before refining.
    kept = sorted(set(ranked[:ULTRASOUND_STARTS]) | ({len(starts) - 1} & set(ranked)))
    metrics: list[float | None] = [float(value) if math.isfinite(float(value)) else None for value in values]
    if not kept:
        return 0, None, metrics
    index, refined, refined_metrics = refine_candidates(levels, starts[kept], centre, rigid, settings, progress)
    for place, value in zip(kept, refined_metrics, strict=True):
        metrics[place] = value
    return kept[index], refined, metrics


def refine_candidates(levels: list[Level], starts: torch.Tensor, centre: np.ndarray, rigid: bool,
                      settings: Refinement = Refinement(), progress: Callable[[float], None] | None = None
                      ) -> tuple[int, torch.Tensor | None, list[float | None]]:
    """The local search from several global candidates, by successive halving over the pyramid.

    Every candidate that overlaps runs the coarsest level, all in one batch; after each level only the
    ``settings.survivors`` best (by the metric on that level) go on. Starts that reach one pose are merged
    (:func:`_merge_same_poses`).

    Args:
        levels: :func:`search_levels` of the pair.
        starts: ``(K, 4, 4)`` float64 fixed-to-moving matrices on the levels' device: the solver's global estimates,
            its own choice first, and the stored pose last when it is one (:attr:`Refinement.stored_start`).
        centre: the residual transforms' centre (mm).
        rigid: 6 parameters (rigid) or 7 (similarity).

    Returns:
        ``(index, matrix, metrics)``: the winner's index in ``starts``, its refined ``(4, 4)`` matrix (``None`` when
        no candidate overlaps the fixed mask) and every candidate's metric after the coarsest level (``None``
        without overlap).
    """
    count = 6 if rigid else 7
    zeros = torch.zeros(len(starts), count, dtype=torch.float64, device=starts.device)
    overlapping = torch.isfinite(levels[0].metric(starts, zeros, centre)).cpu()
    survivors = [(index, starts[index]) for index in range(len(starts)) if overlapping[index]]
    # Each level's first step shrinks with its images, as ITK's multi-resolution examples (MultiResImageRegistration1)
    # shrink the optimiser's step between levels (Refinement.max_step_mm).
    coarsest = first_step_mm(settings, levels[0].samples.spacing)
    metrics: list[float | None] = [None] * len(starts)
    leading: dict[int, float] = {}  # each survivor's metric on the last level
    for level, (search, factor) in enumerate(zip(levels, settings.shrink_factors, strict=True)):
        if level > 0:
            survivors = survivors[:settings.survivors[min(level, len(settings.survivors)) - 1]]
            survivors = [survivor for survivor in survivors if leading[survivor[0]] <= settings.close * leading[
                survivors[0][0]] or leading[survivors[0][0]] >= 0]
        if not survivors:
            break
        batch = torch.stack([matrix for _, matrix in survivors])
        parameters, values = regular_step_descent(
            lambda parameters, poses: search.metric(batch[poses], parameters, centre),  # noqa: B023
            zeros[:len(survivors)],
            coarsest * factor / settings.shrink_factors[0], settings.iterations, settle=settings.close,
            min_step=MIN_STEP_MM if level == len(levels) - 1 else COARSE_STOP_VOXELS * min(search.samples.spacing),
            weights=itk_step_weights(count, search.samples.radius, starts.device))
        refined = batch @ residual_matrices(parameters, centre, search.samples.radius)
        scored = [(value, index, matrix) for value, (index, _), matrix in zip(values.tolist(), survivors, refined)]
        leading = {index: value for value, index, _ in scored}
        if level == 0:
            for value, index, _ in scored:
                metrics[index] = value if math.isfinite(value) else None
        if progress is not None:
            progress((level + 1) / len(levels))
        survivors = [(index, matrix) for _, index, matrix in _merge_same_poses(
            sorted(scored, key=lambda item: item[0]), search.samples, float(search.samples.spacing.max()))]
    if not survivors:
        return 0, None, metrics
    return survivors[0][0], survivors[0][1], metrics


def _merge_same_poses(scored: list[tuple[float, int, torch.Tensor]], samples: Samples, tolerance: float
                      ) -> list[tuple[float, int, torch.Tensor]]:
    """``scored`` (metric, start index, refined ``(4, 4)`` matrix; best metric first) with the starts that reached
    one pose (within ``tolerance`` mm on average over the corners of the ``samples``' box) merged: the best metric
    and its matrix, under the lowest start index (the solver's ranking, the stored pose last)."""
    points = samples.points.double()
    low, high = points.min(0).values, points.max(0).values
    corners = torch.stack([torch.where(torch.tensor(corner, device=points.device).bool(), high, low)
                           for corner in np.ndindex(2, 2, 2)]) if len(points) else torch.zeros(1, 3)
    merged: list[tuple[float, int, torch.Tensor]] = []

    def distance(first: torch.Tensor, second: torch.Tensor) -> float:
        difference = corners @ (first - second)[:3, :3].T.to(corners) + (first - second)[:3, 3].to(corners)
        return float(difference.norm(dim=1).mean())

    for value, index, matrix in scored:
        same = next((place for place, (_, _, other) in enumerate(merged)
                     if math.isfinite(value) and distance(matrix, other) < tolerance), None)
        if same is None:
            merged.append((value, index, matrix))
        elif index < merged[same][1]:
            merged[same] = (merged[same][0], index, merged[same][2])
    return merged


def refine_transform(fixed: sitk.Image, moving: sitk.Image, initial: sitk.Transform, masks: Masks,
                     settings: Refinement = Refinement(), progress: Callable[[float], None] | None = None
                     ) -> sitk.Transform:
    """Multi-resolution Mattes mutual-information registration started from ``initial``, in one SimpleITK run: every
    level's first step is the coarsest level's (:func:`first_step_mm`; :func:`refine_candidates` shrinks it level by
    level).

    The optimiser moves a residual transform ``D`` near the identity and the result is ``initial o D`` (why:
    docs/design_notes/registration.md).

    Returns:
        A new transform of ``initial``'s type (rigid or similarity), fixed to moving, same centre; ``initial`` is left
        untouched.
    """
    method = _registration_method(fixed, masks, settings)
    coarsest = np.asarray(fixed.GetSpacing()) * level_factors(fixed.GetSize(), settings.shrink_factors[0])
    method.SetOptimizerAsRegularStepGradientDescent(learningRate=first_step_mm(settings, coarsest), minStep=1e-2,
                                                    numberOfIterations=settings.iterations,
                                                    relaxationFactor=0.5, gradientMagnitudeTolerance=1e-6)
    method.SetOptimizerScalesFromPhysicalShift()
    method.SetShrinkFactorsPerLevel(list(settings.shrink_factors))
    method.SetSmoothingSigmasPerLevel(list(settings.smoothing_mm))
    method.SmoothingSigmasAreSpecifiedInPhysicalUnitsOn()
    rigid = initial.GetName() == "VersorRigid3DTransform"
    centre = initial.GetFixedParameters()[:3]
    residual = sitk.VersorRigid3DTransform() if rigid else sitk.Similarity3DTransform()
    residual.SetCenter(centre)
    method.SetMovingInitialTransform(initial)
    method.SetInitialTransform(residual, inPlace=True)
    if progress is not None:
        levels = len(settings.shrink_factors)
        method.AddCommand(sitk.sitkMultiResolutionIterationEvent,
                          lambda: progress(method.GetCurrentLevel() / levels))
    method.Execute(_float32(fixed), _float32(moving))
    # ITK's registration maps a fixed point through the optimised transform first, then the moving initial one.
    return similarity_transform(homogeneous_matrix(initial) @ homogeneous_matrix(residual), np.asarray(centre),
                                rigid=rigid)
