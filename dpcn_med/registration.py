"""The public registration API: two volumes (files or SimpleITK images) in, a physical transform out.

:func:`register` checks its arguments and options, then runs five steps:

1. read the inputs: the images and masks, checked as files are (:mod:`dpcn_med.io`);
2. prepare the grids: normalise both images and resample them onto canonical cubes with one shared spacing
   (:mod:`dpcn_med.preprocess`);
3. global candidates: solve for the pose over all of SO(3) with the DPC solver (:mod:`dpcn_med.solver`) or a learned
   model, each candidate turned into an ITK transform (:func:`dpcn_med.geometry.physical_transform`), the stored pose
   last;
4. choose and refine: by default, polish the candidates locally with SimpleITK's Mattes mutual information and keep
   the best (:mod:`dpcn_med.refine`);
5. the result: overlap, resampled image, confidence (:class:`RegistrationResult`).
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import SimpleITK as sitk
import torch

from dpcn_med import io
from dpcn_med.arguments import check_flag, shown
from dpcn_med.errors import InputError
from dpcn_med.geometry import (
    CanonicalGrid,
    homogeneous_matrix,
    physical_transform,
    similarity_transform,
)
from dpcn_med.options import LEARNING_FREE, check_options, load_feature_model  # noqa: F401  (public here too)
from dpcn_med.preprocess import (
    PreparedImage,
    Preprocessing,
    pair_grids,
    prepare,
    resample_to_grid,
    to_tensor,
)
from dpcn_med.quality import shipped_model, signals
from dpcn_med.refine import (
    MIN_LEVEL_VOXELS,
    Choice,
    Refinement,
    check_mask_extent,
    choose_and_refine,
    metric_masks,
    ultrasound_side,
)
from dpcn_med.result import RegistrationResult, describe_transform  # noqa: F401  (public here too)
from dpcn_med.solver import SolverConfig, StageTemperatures, solve
from dpcn_med.solver.translation import phase_translation
from dpcn_med.threads import side_by_side

if TYPE_CHECKING:
    from dpcn_med.models import DPCN

ImageLike = str | os.PathLike | sitk.Image
Progress = Callable[[str, float], None]
"""``progress(stage, fraction)``: the stage's name and the fraction of the whole job done, in ``[0, 1]``."""


def _check_image_like(name: str, value: object) -> None:
    """Refuse what is neither a path nor a SimpleITK image, naming the argument (``name``)."""
    if isinstance(value, (str, os.PathLike, sitk.Image)):
        return
    hint = (" (for an array, make one with SimpleITK.GetImageFromArray and set its spacing, origin and direction)"
            if isinstance(value, (np.ndarray, torch.Tensor)) else "")
    raise InputError(f"{name} is {shown(value)}; expected a path (str or os.PathLike) or a SimpleITK image{hint}")


def _check_settings(name: str, value: object, kind: type) -> None:
    """Refuse a settings object that is neither ``None`` nor a ``kind`` (a dict passes no check of its fields)."""
    if value is not None and not isinstance(value, kind):
        hint = f" (from a dict: {kind.__name__}(**values))" if isinstance(value, dict) else ""
        raise InputError(f"{name} is {shown(value)}; expected a {kind.__name__} or None{hint}")


def load_image(source: ImageLike, role: str = "image") -> sitk.Image:
    """A checked 3-D volume from a path (image, DICOM folder, surface mesh or point cloud) or a SimpleITK image
    (checked as a file's voxels are, :func:`dpcn_med.io.check_volume`; ``role``, such as "fixed image", names it in
    messages)."""
    if isinstance(source, sitk.Image):
        image = io.check_volume(source, role)
    elif io.is_mesh_path(source):
        from dpcn_med.preprocess import voxelize

        image = io.check_volume(voxelize(io.read_mesh(source), name=os.fspath(source)), os.fspath(source))
    else:
        image = io.read_image(source)
    if min(image.GetSize()) < MIN_LEVEL_VOXELS:  # the refinement's smoothing (ITK's recursive Gaussian) needs 4
        name = role if isinstance(source, sitk.Image) else os.fspath(source)
        raise InputError(f"{name}: is {min(image.GetSize())} voxels thick (size {image.GetSize()}); registering "
                         f"needs at least {MIN_LEVEL_VOXELS} along each axis")
    return image


def _load_mask(source: ImageLike | None, image: sitk.Image, role: str) -> sitk.Image | None:
    if source is None:
        return None
    if isinstance(source, sitk.Image):
        return io.check_mask(source, image, _mask_name(source, role), role=role)
    return io.read_mask(source, image, role=role)


def _mask_name(source: ImageLike | None, role: str) -> str:
    """The mask's file, or the argument that passed it ("fixed_mask argument"), for messages."""
    if source is None or isinstance(source, sitk.Image):
        return f"{role.replace(' ', '_')} argument"
    return os.fspath(source)


def register(fixed: ImageLike, moving: ImageLike, *, mode: str = "rigid", model: str | os.PathLike | None = None,
             bandwidth: int | None = None, refine: bool = True, device: str = "auto",
             fixed_mask: ImageLike | None = None, moving_mask: ImageLike | None = None,
             fixed_modality: str = "auto", moving_modality: str = "auto", resample: bool = False,
             preprocessing: Preprocessing | None = None, refinement: Refinement | None = None,
             solver: SolverConfig | None = None, progress: Progress | None = None) -> RegistrationResult:
    """Register ``moving`` onto ``fixed`` from any starting pose.

    Args:
        fixed: the reference volume: a path (NIfTI, NRRD, MHA/MHD, a DICOM folder, or a surface mesh / point cloud
            in LPS) or a SimpleITK image.
        moving: the volume to align, same kinds.
        mode: ``"rigid"`` (6 DoF) or ``"similarity"`` (7 DoF, isotropic scale).
        model: ``None`` (or ``"none"``) for the learning-free solver, or the path of a model trained with
            ``dpcn-med train`` (its learned features replace the intensities; its bandwidth must be ``bandwidth``).
        bandwidth: solver bandwidth ``B``; grids are ``(2B)^3`` (32: fast on a CPU; 64: finer before refinement);
            ``None``: the model's, else :data:`DEFAULT_BANDWIDTH`.
        refine: polish the global estimate with multi-resolution Mattes mutual information.
        device: ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` for the solver.
        fixed_mask: binary mask on the fixed image's grid: only it is registered (also restricts the refinement).
        moving_mask: the same for the moving image.
        fixed_modality: ``"auto"``, ``"ct"``, ``"mr"`` or ``"us"`` (intensity normalisation).
        moving_modality: the same for the moving image.
        resample: also return the moving image resampled on the fixed grid.
        preprocessing: canonical-grid and intensity settings (default :class:`Preprocessing`, or the learned
            model's own).
        refinement: refinement settings (default :class:`dpcn_med.refine.Refinement`).
        solver: settings of the learning-free solver (default :class:`dpcn_med.solver.SolverConfig`; its bandwidth
            and alternatives are set from ``bandwidth`` and ``refinement``); a learned model carries its own.
        progress: called with ``(stage, fraction done)`` as the work advances.

    Returns:
        A :class:`RegistrationResult`; ``result.fixed_to_moving`` maps fixed physical points (LPS, mm) to moving
        ones.

    Raises:
        InputError: unreadable or unusable inputs, masks or options, or an argument of the wrong type; the message
            names the file or the argument and the problem.
    """
    options = _options(mode=mode, model=model, bandwidth=bandwidth, refine=refine, device=device,
                       modalities=(fixed_modality, moving_modality), resample=resample, preprocessing=preprocessing,
                       refinement=refinement, solver=solver, progress=progress,
                       images={"fixed": fixed, "moving": moving, "fixed_mask": fixed_mask, "moving_mask": moving_mask})
    clock = _Clock(progress)
    inputs = _read_inputs(fixed, moving, fixed_mask, moving_mask, clock)
    grids = _prepare_grids(inputs, options, clock)
    starts = _global_candidates(grids, options, clock)
    choice = _choose_and_refine(inputs, grids, starts, options, clock)
    return _result(inputs, grids, starts, choice, options, clock)


@dataclass(frozen=True)
class _Options:
    """:func:`register`'s options, checked and resolved (the device, the bandwidth, the model loaded)."""

    mode: str
    bandwidth: int
    device: torch.device
    network: DPCN | None
    model: str | os.PathLike | None
    modalities: tuple[str, str]
    refine: bool
    resample: bool
    preprocessing: Preprocessing
    refinement: Refinement
    solver: SolverConfig | None


def _options(*, mode: str, model: str | os.PathLike | None, bandwidth: int | None, refine: bool, device: str,
             modalities: tuple[str, str], resample: bool, preprocessing: Preprocessing | None,
             refinement: Refinement | None, solver: SolverConfig | None, progress: Progress | None,
             images: dict[str, ImageLike | None]) -> _Options:
    """Every argument of :func:`register` checked, in its order, before any work; the model loaded."""
    for name, value in images.items():
        if value is not None or name in ("fixed", "moving"):
            _check_image_like(name, value)
    refine, resample = check_flag("refine", refine), check_flag("resample", resample)
    _check_settings("preprocessing", preprocessing, Preprocessing)
    _check_settings("refinement", refinement, Refinement)
    _check_settings("solver", solver, SolverConfig)
    if progress is not None and not callable(progress):
        raise InputError(f"progress is {shown(progress)}; expected a function progress(stage, fraction) or None")
    mode, bandwidth, torch_device, network = check_options(mode=mode, model=model, bandwidth=bandwidth, device=device,
                                                           fixed_modality=modalities[0],
                                                           moving_modality=modalities[1])
    if network is not None and solver is not None:
        raise InputError(f"{model}: a learned model carries its own solver settings; pass solver= only without one")
    # A learned model saw grids made one way in training; it gets the same unless the caller says otherwise.
    preprocessing = preprocessing or (network.config.grid_preprocessing() if network is not None else Preprocessing())
    return _Options(mode=mode, bandwidth=bandwidth, device=torch_device, network=network, model=model,
                    modalities=modalities, refine=refine, resample=resample, preprocessing=preprocessing,
                    refinement=refinement or Refinement(), solver=solver)


class _Clock:
    """The wall-clock seconds of each step of one registration, and its progress callback."""

    def __init__(self, progress: Progress | None) -> None:
        self.report: Progress = progress or (lambda stage, fraction: None)
        self.timings: dict[str, float] = {}

    @contextmanager
    def step(self, key: str, stage: str, fraction: float) -> Iterator[None]:
        """Time the block under ``timings[key]`` (only if it ends without an error), reporting ``stage`` first."""
        start = time.perf_counter()
        self.report(stage, fraction)
        yield
        self.timings[key] = time.perf_counter() - start


@dataclass(frozen=True)
class _Inputs:
    """Step 1's images and masks as read, and the masks' names for messages (:func:`_mask_name`)."""

    fixed: sitk.Image
    moving: sitk.Image
    fixed_mask: sitk.Image | None
    moving_mask: sitk.Image | None
    fixed_mask_name: str
    moving_mask_name: str


def _read_inputs(fixed: ImageLike, moving: ImageLike, fixed_mask: ImageLike | None, moving_mask: ImageLike | None,
                 clock: _Clock) -> _Inputs:
    """Step 1: read and check both images, at once, then both masks."""
    with clock.step("read", "reading", 0.0):
        fixed_image, moving_image = side_by_side(lambda: load_image(fixed, "fixed image"),
                                                 lambda: load_image(moving, "moving image"))
        return _Inputs(fixed=fixed_image, moving=moving_image,
                       fixed_mask=_load_mask(fixed_mask, fixed_image, "fixed mask"),
                       moving_mask=_load_mask(moving_mask, moving_image, "moving mask"),
                       fixed_mask_name=_mask_name(fixed_mask, "fixed mask"),
                       moving_mask_name=_mask_name(moving_mask, "moving mask"))


@dataclass(frozen=True)
class _Grids:
    """Step 2's prepared images, their canonical grids, and the images on them as ``(1, 1, N, N, N)`` tensors on the
    solver's device."""

    fixed: PreparedImage
    moving: PreparedImage
    fixed_grid: CanonicalGrid
    moving_grid: CanonicalGrid
    fixed_tensor: torch.Tensor
    moving_tensor: torch.Tensor


def _prepare_grids(inputs: _Inputs, options: _Options, clock: _Clock) -> _Grids:
    """Step 2: normalise both images (and refuse masks too small to refine, or modalities the model was not trained
    for), then resample them onto canonical cubes of ``2B`` voxels with one shared spacing."""
    with clock.step("preprocess", "preprocessing", 0.1):
        fixed, moving = side_by_side(
            lambda: prepare(inputs.fixed, modality=options.modalities[0], mask=inputs.fixed_mask,
                            config=options.preprocessing, mask_name=inputs.fixed_mask_name),
            lambda: prepare(inputs.moving, modality=options.modalities[1], mask=inputs.moving_mask,
                            config=options.preprocessing, mask_name=inputs.moving_mask_name))
        if options.refine:
            check_mask_extent(inputs.fixed_mask, inputs.fixed_mask_name, options.refinement)
            check_mask_extent(inputs.moving_mask, inputs.moving_mask_name, options.refinement)
        if options.network is not None:
            _check_model_modalities(options.model, options.network, options.modalities,
                                    (fixed.modality, moving.modality))
        fixed_grid, moving_grid = pair_grids(fixed, moving, 2 * options.bandwidth, options.preprocessing)
        return _Grids(fixed=fixed, moving=moving, fixed_grid=fixed_grid, moving_grid=moving_grid,
                      fixed_tensor=to_tensor(resample_to_grid(fixed.image, fixed_grid)).to(options.device),
                      moving_tensor=to_tensor(resample_to_grid(moving.image, moving_grid)).to(options.device))


@dataclass(frozen=True)
class _Starts:
    """Step 3's starts for the refinement: ``(fixed_to_moving, confidence)``, the solver's choice first, then its
    runner-ups; ``stored`` is the stored pose's index, when it is a start (its confidence, ``None`` here, is measured
    only if it wins: with a model, that takes two UNet passes)."""

    candidates: list[tuple[sitk.Transform, float | None]]
    stored: int | None

    @property
    def transforms(self) -> list[sitk.Transform]:
        return [transform for transform, _ in self.candidates]


def _global_candidates(grids: _Grids, options: _Options, clock: _Clock) -> _Starts:
    """Step 3: the solver's (or the model's) global candidates as physical transforms, and the stored pose after
    them when it is a start.

    Raises:
        InputError: a pose or confidence that is not finite.
    """
    with clock.step("solve", "solving", 0.3):
        solution, alternatives = _solve(grids, options, clock.timings)
    if not all(torch.isfinite(value[0]).all() for value in (solution.rotation, solution.scale, solution.translation,
                                                            solution.confidence)):
        raise _non_finite(options.model if options.network is not None else None)

    def fixed_to_moving(rotation: torch.Tensor, scale: torch.Tensor, translation: torch.Tensor) -> sitk.Transform:
        return physical_transform(rotation, float(scale) if options.mode == "similarity" else None, translation,
                                  grids.fixed_grid, grids.moving_grid)

    candidates: list[tuple[sitk.Transform, float | None]] = [
        (fixed_to_moving(solution.rotation[0], solution.scale[0], solution.translation[0]),
         float(solution.confidence[0]))]
    if alternatives is not None:
        candidates += [(fixed_to_moving(alternatives.rotation[0, k], alternatives.scale[0, k],
                                        alternatives.translation[0, k]), float(alternatives.confidence[0, k]))
                       for k in range(alternatives.score.shape[1]) if alternatives.score[0, k] > float("-inf")]
    stored = len(candidates) if options.refine and options.refinement.stored_start else None
    if stored is not None:
        candidates.append((similarity_transform(np.eye(4), np.asarray(grids.fixed_grid.centre),
                                                rigid=options.mode == "rigid"), None))
    return _Starts(candidates=candidates, stored=stored)


def _solve(grids: _Grids, options: _Options, timings: dict[str, float]) -> tuple:
    """The global solve on the canonical grids: ``(solution, alternatives)``, the solver's
    :class:`~dpcn_med.solver.SolveResult` (or the model's result) and its runner-ups
    (:class:`~dpcn_med.solver.Alternatives`, or ``None``); the learning-free solver's stage timings go into
    ``timings`` as ``solver.*``."""
    # Runner-ups only where a local search can tell them apart (Refinement.starts).
    runner_ups = options.refinement.starts - 1 if options.refine else 0
    if options.network is None:
        solution = solve(grids.fixed_tensor, grids.moving_tensor, options.mode, config=options.solver,
                         bandwidth=options.bandwidth, profile=True, alternatives=runner_ups)
        timings.update({f"solver.{stage}": seconds for stage, seconds in solution.timings.items()})
        return solution, solution.alternatives
    with torch.no_grad():
        try:
            solution = options.network(grids.fixed_tensor, grids.moving_tensor, mode=options.mode,
                                       alternatives=runner_ups)
        except InputError as error:  # features that overflow: the model's fault, not the images'
            raise InputError(f"{options.model}: {error}") from None
    return solution, solution.stage.alternatives


def _choose_and_refine(inputs: _Inputs, grids: _Grids, starts: _Starts, options: _Options, clock: _Clock) -> Choice:
    """Step 4: the refinement's choice among the starts (:func:`dpcn_med.refine.choose_and_refine`); without
    refinement, the solver's own choice as it is."""
    if not options.refine:
        return Choice(index=0, fixed_to_moving=starts.candidates[0][0], refined=False,
                      metric={"stored": None, "dpc": None, "refined": None}, candidate_metrics=[])
    with clock.step("refine", "refining", 0.4):
        ultrasound = ultrasound_side(grids.fixed.modality, grids.moving.modality)
        masks = metric_masks(inputs.fixed_mask, grids.fixed.foreground, inputs.moving_mask, options.refinement,
                             ultrasound=ultrasound)
        return choose_and_refine(inputs.fixed, inputs.moving, starts.transforms, masks, options.refinement,
                                 lambda fraction: clock.report("refining", 0.4 + 0.5 * fraction), options.device,
                                 ultrasound=ultrasound)


def _result(inputs: _Inputs, grids: _Grids, starts: _Starts, choice: Choice, options: _Options,
            clock: _Clock) -> RegistrationResult:
    """Step 5: the overlap, the resampled image when asked for, the confidence in the start kept, and the result."""
    fixed_to_moving = choice.fixed_to_moving
    overlap = field_of_view_overlap(grids.fixed.foreground, inputs.moving, fixed_to_moving)
    resampled = None
    if options.resample:
        with clock.step("resample", "resampling", 0.9):
            resampled = resample_moving(inputs.fixed, inputs.moving, fixed_to_moving)
    confidence = _start_confidence(grids, starts, choice.index, options)
    values = signals(confidence, overlap, choice.metric, choice.fixed_entropy, choice.candidate_metrics)
    clock.report("done", 1.0)
    return RegistrationResult(
        fixed_to_moving=fixed_to_moving, moving_to_fixed=fixed_to_moving.GetInverse(),
        dpc_transform=starts.candidates[choice.index][0], confidence=confidence, candidate=choice.index,
        start="stored pose" if choice.index == starts.stored else "phase correlation",
        candidate_metrics=choice.candidate_metrics, mode=options.mode, bandwidth=options.bandwidth,
        fixed_grid=grids.fixed_grid, moving_grid=grids.moving_grid,
        modalities=(grids.fixed.modality, grids.moving.modality), metric=choice.metric, refined=choice.refined,
        overlap=overlap, fixed_entropy=choice.fixed_entropy, similarity=choice.similarity,
        success_probability=None if values is None else shipped_model().probability(values), timings=clock.timings,
        device=str(options.device),
        model="learning-free" if options.network is None else os.fspath(options.model),
        fixed_image=inputs.fixed, moving_image=inputs.moving, resampled=resampled,
        fixed_foreground=grids.fixed.foreground, moving_foreground=grids.moving.foreground)


def _start_confidence(grids: _Grids, starts: _Starts, chosen: int, options: _Options) -> float:
    """The solver's confidence in the start kept; for the stored pose, measured now (:func:`stored_pose_confidence`).

    Raises:
        InputError: a confidence that is not finite, or features of the model that overflow.
    """
    confidence = starts.candidates[chosen][1]
    if chosen == starts.stored:
        try:
            confidence = stored_pose_confidence(grids.fixed_tensor, grids.moving_tensor, options.network,
                                                options.solver)
        except InputError as error:
            raise InputError(f"{options.model}: {error}") from None
    if not math.isfinite(confidence):
        raise _non_finite(options.model if options.network is not None else None)
    return confidence


def _check_model_modalities(model: str | os.PathLike, network: DPCN, given: tuple[str, str],
                            used: tuple[str, str]) -> None:
    """Refuse inputs of other modalities than the ``(fixed, moving)`` ones the model was trained for.

    ``used`` are the modalities :func:`dpcn_med.preprocess.prepare` resolved from ``given``. Detection (``"auto"``)
    answers ``ct`` only for Hounsfield units and ``mr`` for anything else: it cannot tell ultrasound from MR, nor a CT
    stored without its air at -1000, so a detected ``mr`` is not held against the model; a detected ``ct`` and a
    named modality are.
    """
    trained = tuple(network.config.modalities)
    if any(resolved != expected and (named != "auto" or resolved == "ct")
           for named, resolved, expected in zip(given, used, trained)):
        raise InputError(f"{model}: this model was trained for {trained[0]} (fixed) and {trained[1]} (moving); the "
                         f"inputs are {used[0]} and {used[1]} (fixed_modality {given[0]!r}, moving_modality "
                         f"{given[1]!r}); use a model trained for these modalities, or name them if detection "
                         "misjudged them (--fixed-modality, --moving-modality)")


def _non_finite(model: str | os.PathLike | None) -> InputError:
    """The error for a pose or confidence holding NaN or Inf (a softmax at a temperature of 0, overflowing
    features): a registration that reports it would be silently wrong."""
    if model is None:
        return InputError("the solver produced a non-finite pose or confidence (NaN or Inf) from these images")
    return InputError(f"{model}: the solver produced a non-finite pose or confidence (NaN or Inf) with this model; "
                      "its weights are unusable")


def stored_pose_confidence(fixed: torch.Tensor, moving: torch.Tensor, network: DPCN | None,
                           solver: SolverConfig | None) -> float:
    """The confidence of the stored pose as a start: the mass of the translation-correlation peak of the canonical
    grids ``(1, 1, N, N, N)`` at the stored orientation (no rotation, no scale), as the solver measures its own
    candidates' (with a learned model, on its translation features, at its temperature)."""
    with torch.no_grad():
        if network is None:
            config = solver or SolverConfig()
            estimate = phase_translation(fixed[:, 0], moving[:, 0], StageTemperatures().translation, dim=3,
                                         taper=config.taper, refine=False, upsample=config.upsample)
        else:
            estimate = network.translation_peak(fixed, moving)
    return float(estimate.peak.mass[0])


def mirrored_copy(image: sitk.Image) -> sitk.Image:
    """``image`` with its voxels reversed along the voxel axis nearest the patient's left-right (LPS x) axis and its
    header kept: what a left-right header error does to a volume, and what undoes one."""
    direction = np.asarray(image.GetDirection()).reshape(3, 3)
    axis = int(np.argmax(np.abs(direction[0])))  # the voxel axis whose direction has the largest x component
    flip = [False, False, False]
    flip[axis] = True
    mirrored = sitk.Flip(image, flip, flipAboutOrigin=False)
    mirrored.CopyInformation(image)
    return mirrored


def field_of_view_overlap(fixed_foreground: sitk.Image, moving: sitk.Image, fixed_to_moving: sitk.Transform, *,
                          samples: int = 20000, seed: int = 0) -> float:
    """Share of the fixed foreground whose points ``fixed_to_moving`` sends inside the moving image's domain.

    Args:
        fixed_foreground: binary mask in the fixed image's physical space (any grid).
        moving: the moving image (only its geometry is used).
        fixed_to_moving: the registration, fixed to moving (LPS mm).
        samples: at most this many foreground voxels are tested (a seeded random subset).
    """
    indices = np.argwhere(sitk.GetArrayViewFromImage(fixed_foreground) > 0)[:, ::-1]  # (K, 3) as (x, y, z)
    if len(indices) == 0:
        return 0.0
    if len(indices) > samples:
        indices = indices[np.random.default_rng(seed).choice(len(indices), samples, replace=False)]
    direction = np.reshape(fixed_foreground.GetDirection(), (3, 3))
    points = (direction @ (indices * fixed_foreground.GetSpacing()).T).T + fixed_foreground.GetOrigin()
    matrix = homogeneous_matrix(fixed_to_moving)
    mapped = points @ matrix[:3, :3].T + matrix[:3, 3]
    moving_direction = np.reshape(moving.GetDirection(), (3, 3))
    continuous = (moving_direction.T @ (mapped - moving.GetOrigin()).T).T / moving.GetSpacing()
    inside = np.all((continuous >= -0.5) & (continuous <= np.asarray(moving.GetSize()) - 0.5), axis=1)
    return float(inside.mean())


def resample_moving(fixed: sitk.Image, moving: sitk.Image, fixed_to_moving: sitk.Transform) -> sitk.Image:
    """The moving image on the fixed grid (linear), its pixel type kept (integers rounded to the nearest, not
    truncated towards zero), outside filled with its minimum."""
    background = float(sitk.GetArrayViewFromImage(moving).min())
    pixel = moving.GetPixelID()
    if pixel in (sitk.sitkFloat32, sitk.sitkFloat64):
        return sitk.Resample(moving, fixed, fixed_to_moving, sitk.sitkLinear, background, pixel)
    resampled = sitk.Resample(moving, fixed, fixed_to_moving, sitk.sitkLinear, background, sitk.sitkFloat64)
    return sitk.Cast(sitk.Round(resampled), pixel)  # within the input's range: linear interpolation never leaves it
