"""The public registration API: two volumes (files or SimpleITK images) in, a physical transform out.

``register`` reads and checks the inputs (:mod:`dpcn_med.io`), normalises them and resamples both onto canonical
cubes with one shared spacing (:mod:`dpcn_med.preprocess`), solves for the pose globally with the DPC solver
(:mod:`dpcn_med.solver`), turns it into an ITK transform (:func:`dpcn_med.geometry.physical_transform`) and, by
default, polishes it locally with SimpleITK's Mattes mutual information.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import SimpleITK as sitk
import torch

from dpcn_med import io
from dpcn_med.arguments import check_flag, check_integer, check_real, check_sequence, shown
from dpcn_med.errors import InputError
from dpcn_med.evaluation import target_registration_error
from dpcn_med.geometry import (
    CanonicalGrid,
    homogeneous_matrix,
    physical_transform,
    rotation_angle,
    scale_and_rotation,
    similarity_transform,
)
from dpcn_med.preprocess import (
    MODALITIES,
    Preprocessing,
    clip_outliers,
    pair_grids,
    prepare,
    resample_to_grid,
    to_tensor,
)
from dpcn_med.solver import SolverConfig, StageTemperatures, solve
from dpcn_med.solver.translation import phase_translation
from dpcn_med.solver.validation import check_grid_bandwidth, check_mode

if TYPE_CHECKING:
    from dpcn_med.models import DPCN

ImageLike = str | os.PathLike | sitk.Image
Progress = Callable[[str, float], None]
"""``progress(stage, fraction)``: the stage's name and the fraction of the whole job done, in ``[0, 1]``."""


@dataclass(frozen=True)
class Refinement:
    """Settings of the local Mattes mutual-information refinement (SimpleITK), defined once.

    Attributes:
        shrink_factors: image pyramid, coarse to fine (integers >= 1).
        smoothing_mm: Gaussian sigma per level, mm (>= 0, one per shrink factor).
        samples: random metric samples per level (capped at every voxel), at least 1000.
        histogram_bins: Mattes histogram bins, at least 8.
        iterations: optimiser iterations per level, at least 1.
        max_step_mm: largest first step of the regular-step gradient descent at the coarsest level, as a physical
            shift in mm (> 0), or ``None`` (default) for half the finest voxel spacing of the fixed image's coarsest
            level (:func:`first_step_mm`): 4 mm for a 2 mm image shrunk 4 times, 2 mm for a 1 mm one. A fixed 2 mm
            left two MNI pseudo-CT poses of the benchmark (2 mm voxels, 8 mm at the coarsest level) in a local
            optimum 16 mm off or on the half-turn twin; a fixed 4 mm took a 24 mm object in 4 mm voxels to a pose
            turned by 90 degrees (docs/registration.md, step 6). In :func:`refine_candidates` each finer level starts
            at this times its shrink factor over the coarsest one's (4, 2, 1 mm for the 2 mm image): started at 2 mm
            from 0.65 mm off, the full-resolution level of a 1 mm MRI-DIR CT pose jumped to another optimum 1.9 mm
            off. :func:`refine_transform`, one SimpleITK run over the levels, starts each at this step.
        mask_margin_voxels: the fixed foreground, dilated by this many (preprocessing) voxels, is where the metric is
            sampled when the user gives no fixed mask.
        starts: global candidates refined: the solver's choice and up to ``starts - 1`` runner-ups (1: its choice
            only). Every one runs the coarsest pyramid level (:func:`refine_candidates`), about 0.1 s each. Two sphere
            bands leave 2-16 plausible candidates on the MNI heads, and across modalities the translation peak that
            ranks them is low for all: on 4 of 60 MNI pseudo-CT poses the right one ranked 9th to 13th, so all of
            them run.
        survivors: how many of them (at least 1) go on to each next level, by their metric (the last value holds for
            the rest).
        stored_start: the stored pose (identity) is one more start, after the solver's candidates: inputs already
            roughly aligned (one scanner frame, or aligned by hand) stay aligned where phase correlation misses (a
            coronal slab of a head registered onto the whole head as stored came back 85-167 mm off, the stored
            pose refined was right). Where the stored pose leaves no overlap (unrelated scanner frames) it is dropped
            before any work, like any candidate.
        seed: sampling seed in ``[1, 2**32 - 1]`` (the same inputs give the same result; SimpleITK takes 0 for
            ``sitkWallClock``, a new seed on every run).

    Raises:
        InputError: a value of the wrong type or out of range, named with its value (3 or 5 histogram bins left the
            mutual information flat, about 1e-13, and an MNI head pose 230 mm off came back as refined).
    """

    shrink_factors: tuple[int, ...] = (4, 2, 1)
    smoothing_mm: tuple[float, ...] = (2.0, 1.0, 0.0)
    samples: int = 30_000
    histogram_bins: int = 32
    iterations: int = 100
    max_step_mm: float | None = None
    mask_margin_voxels: int = 3
    starts: int = 16
    survivors: tuple[int, ...] = (2, 1)
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
            "histogram_bins": check_integer("histogram_bins", self.histogram_bins, minimum=8),
            "iterations": check_integer("iterations", self.iterations, minimum=1),
            "max_step_mm": None if self.max_step_mm is None else check_real("max_step_mm", self.max_step_mm,
                                                                             minimum=0, above=True),
            "mask_margin_voxels": check_integer("mask_margin_voxels", self.mask_margin_voxels, minimum=0),
            "starts": check_integer("starts", self.starts, minimum=1),
            "survivors": tuple(check_integer(f"survivors[{level}]", count, minimum=1)
                               for level, count in enumerate(check_sequence("survivors", self.survivors))),
            "stored_start": check_flag("stored_start", self.stored_start),
            # SimpleITK's seed is an unsigned 32-bit integer, and 0 is sitkWallClock: a new seed on every run.
            "seed": check_integer("seed", self.seed, minimum=1, maximum=2 ** 32 - 1),
        }
        for name, value in checked.items():
            object.__setattr__(self, name, value)


@dataclass
class RegistrationResult:
    """What :func:`register` found.

    Attributes:
        fixed_to_moving: the final transform (refined unless refinement was off or did not improve the metric), LPS
            mm, fixed points to moving points: ``sitk.Resample(moving, fixed, fixed_to_moving)`` aligns them. A
            ``VersorRigid3DTransform`` (rigid) or ``Similarity3DTransform`` (similarity), centred at the fixed grid's
            centre.
        moving_to_fixed: its inverse.
        dpc_transform: the start that the refinement kept (before refinement): a global estimate, or the identity
            when ``start`` is ``"stored pose"``.
        confidence: the solver's confidence in that start, in ``[0, 1]``: the mass of its translation peak (for the
            stored pose, of the translation correlation at the stored orientation, :func:`stored_pose_confidence`).
        candidate: which start that is, chosen by :func:`refine_candidates`: 0 for the solver's own choice, ``k``
            for its ``k``-th runner-up; the stored pose is the last (``len(candidate_metrics) - 1``).
        start: ``"phase correlation"`` (one of the solver's candidates) or ``"stored pose"``
            (:attr:`Refinement.stored_start`).
        candidate_metrics: each start's metric after the coarsest refinement level, on that level's images (empty
            without refinement), in the order of ``candidate``.
        mode: ``"rigid"`` or ``"similarity"``.
        bandwidth: ``B``; the canonical grids are ``(2B)^3``.
        fixed_grid: canonical cube of the fixed volume.
        moving_grid: canonical cube of the moving volume (same spacing).
        modalities: ``(fixed, moving)`` modality used for intensity normalisation.
        metric: Mattes mutual information (SimpleITK's sign: lower is better) at ``"stored"`` (identity),
            ``"dpc"`` and ``"refined"`` (``None`` without refinement, or where the pose leaves no overlap).
        refined: whether ``fixed_to_moving`` is the refined transform.
        overlap: share of the fixed foreground that ``fixed_to_moving`` maps inside the moving image's field of view
            (:func:`field_of_view_overlap`).
        timings: wall-clock seconds per step (``read``, ``preprocess``, ``solve``, ``refine``, ``resample``) and
            per solver stage (``solver.*``).
        device: the torch device the solver ran on.
        model: ``"learning-free"`` or the path of the learned model used.
        fixed_image: the fixed input as read.
        moving_image: the moving input as read.
        resampled: the moving image on the fixed grid, when asked for.
    """

    fixed_to_moving: sitk.Transform
    moving_to_fixed: sitk.Transform
    dpc_transform: sitk.Transform
    confidence: float
    mode: str
    bandwidth: int
    fixed_grid: CanonicalGrid
    moving_grid: CanonicalGrid
    modalities: tuple[str, str]
    metric: dict[str, float | None]
    refined: bool
    candidate: int = 0
    start: str = "phase correlation"
    candidate_metrics: list[float | None] = field(default_factory=list)
    overlap: float = 1.0
    timings: dict[str, float] = field(default_factory=dict)
    device: str = "cpu"
    model: str = "learning-free"
    fixed_image: sitk.Image | None = None
    moving_image: sitk.Image | None = None
    resampled: sitk.Image | None = None

    def to_dict(self) -> dict:
        """JSON-ready summary: both estimates as 4x4 matrices and parameters, confidence, metric, timings."""
        return {
            "mode": self.mode, "bandwidth": self.bandwidth, "device": self.device, "model": self.model,
            "confidence": self.confidence, "modalities": {"fixed": self.modalities[0], "moving": self.modalities[1]},
            "canonical_grid": {"size": self.fixed_grid.size, "spacing_mm": self.fixed_grid.spacing,
                               "fixed_centre_lps": list(self.fixed_grid.centre),
                               "moving_centre_lps": list(self.moving_grid.centre)},
            "dpc": describe_transform(self.dpc_transform),
            "final": describe_transform(self.fixed_to_moving),
            "refined": self.refined, "candidate": self.candidate, "start": self.start,
            "candidate_mattes_mutual_information": self.candidate_metrics, "overlap_fraction": self.overlap,
            "mattes_mutual_information": self.metric,
            "timings_s": self.timings,
        }


DEFAULT_BANDWIDTH = 32
"""The learning-free solver's bandwidth when none is given: fast on a CPU."""


def check_options(*, mode: str, model: str | os.PathLike | None, bandwidth: int | None, device: str | torch.device,
                  fixed_modality: str, moving_modality: str
                  ) -> tuple[str, int, torch.device, DPCN | None]:
    """:func:`register`'s options checked before any work (a batch checks them once, not at every pair).

    Returns:
        ``(mode, bandwidth, device, network)``: the bandwidth and device resolved (``None``: the model's, else
        :data:`DEFAULT_BANDWIDTH`), the model loaded (``None``: learning-free).

    Raises:
        InputError: an unknown mode, modality or device, a bandwidth out of range (the grids will be ``(2B)^3``), or
            a model that cannot be used at this bandwidth.
    """
    mode = check_mode(mode)
    if bandwidth is not None:
        bandwidth = check_grid_bandwidth(check_integer("bandwidth", bandwidth))
    for name, value in (("fixed_modality", fixed_modality), ("moving_modality", moving_modality)):
        if value not in MODALITIES:
            raise InputError(f"{name} {value!r} is not supported; use one of {', '.join(MODALITIES)}")
    torch_device = resolve_device(device)
    network = load_feature_model(model, bandwidth, torch_device)
    if bandwidth is None:
        bandwidth = DEFAULT_BANDWIDTH if network is None else network.config.bandwidth
    return mode, bandwidth, torch_device, network


def describe_transform(fixed_to_moving: sitk.Transform) -> dict:
    """A transform as JSON: ITK name, parameters, centre, the 4x4 LPS matrix, its rotation angle, scale and
    ``translation_mm``, the matrix's offset (where the LPS origin goes; ITK's translation parameters are about the
    centre)."""
    matrix = homogeneous_matrix(fixed_to_moving)
    scale, rotation = scale_and_rotation(matrix[:3, :3])
    angle = float(np.degrees(rotation_angle(torch.from_numpy(rotation)).item()))
    return {"type": fixed_to_moving.GetName(), "parameters": list(fixed_to_moving.GetParameters()),
            "fixed_parameters": list(fixed_to_moving.GetFixedParameters()),
            "fixed_to_moving_lps": matrix.tolist(), "rotation_degrees": angle, "scale": scale,
            "translation_mm": matrix[:3, 3].tolist()}


def resolve_device(device: str | torch.device) -> torch.device:
    """``"auto"`` (CUDA when available, else CPU), ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (or a ``torch.device``).

    Raises:
        InputError: not a string or ``torch.device``, an unknown device, or a CUDA GPU this machine does not have.
    """
    if not isinstance(device, (str, torch.device)):
        raise InputError(f"device is {shown(device)}; expected auto, cpu, cuda or cuda:N (or a torch.device)")
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except RuntimeError as error:
        raise InputError(f"device {device!r} is not valid; use auto, cpu, cuda or cuda:N") from error
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device {device!r} asked for, but this torch build sees no CUDA GPU; use --device cpu")
    if resolved.type not in ("cpu", "cuda"):
        raise InputError(f"device {device!r} is not supported; use auto, cpu, cuda or cuda:N")
    if resolved.type == "cuda" and resolved.index is not None and resolved.index >= torch.cuda.device_count():
        count = torch.cuda.device_count()
        raise InputError(f"device {device!r} asked for, but this machine has {count} CUDA GPU"
                         f"{'s' if count > 1 else ''}; use cuda:0{f' to cuda:{count - 1}' if count > 1 else ''}")
    return resolved


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


def _check_mask_extent(mask: sitk.Image | None, name: str, settings: Refinement) -> None:
    """Refuse a mask too small for the refinement: its box must span :data:`MIN_LEVEL_VOXELS` voxels of the coarsest
    pyramid level along each axis, as every level's images do (measured on the 2 mm MNI head: ITK's metric failed on
    masks 1 to 5 voxels wide; the solver alone, on masks that small, came out 150-220 mm off with confidence under
    0.002)."""
    if mask is None:
        return
    statistics = sitk.LabelShapeStatisticsImageFilter()
    statistics.Execute(sitk.Cast(mask > 0, sitk.sitkUInt8))
    box = np.asarray(statistics.GetBoundingBox(1)[3:])  # io.check_mask refused an empty mask
    needed = MIN_LEVEL_VOXELS * np.asarray(level_factors(mask.GetSize(), settings.shrink_factors[0]))
    if (box < needed).any():
        spacing = np.asarray(mask.GetSpacing())
        raise InputError(f"{name}: too small to refine: its box is {_mm(box * spacing)} mm; the refinement needs at "
                         f"least {_mm(needed * spacing)} mm ({MIN_LEVEL_VOXELS} voxels of its coarsest level along "
                         "each axis); give a larger mask, or register without refinement (refine=False, "
                         "--no-refine), whose confidence then says whether the mask held enough")


def _mm(lengths: np.ndarray) -> str:
    return " x ".join(f"{length:g}" for length in np.round(lengths, 1))


def _mask_name(source: ImageLike | None, role: str) -> str:
    """The mask's file, or the argument that passed it ("fixed_mask argument"), for messages."""
    if source is None or isinstance(source, sitk.Image):
        return f"{role.replace(' ', '_')} argument"
    return os.fspath(source)


LEARNING_FREE = ("none", "learning-free")
"""Names of the learning-free solver for ``model`` (as is ``None``)."""


def load_feature_model(model: str | os.PathLike | None, bandwidth: int | None, device: torch.device):
    """The learned model named by ``model`` (a path to ``NAME.safetensors`` / ``NAME.json`` / ``NAME``) on
    ``device``, or ``None`` for the learning-free solver.

    Raises:
        InputNotFoundError: the model's files are missing.
        InputError: not a path (or ``None``), an empty one, not a dpcn_med model, or trained at another bandwidth
            than ``bandwidth`` (any when ``None``).
    """
    if model is None:
        return None
    if not isinstance(model, (str, os.PathLike)) or Path(model).name in ("", ".."):
        raise InputError(f"model is {shown(model)}; expected the path of a model (NAME.safetensors, NAME.json or "
                         f"NAME), or None or 'none' for the learning-free solver")
    if os.fspath(model).lower() in LEARNING_FREE:
        return None
    from dpcn_med.models import load_model

    network = load_model(model, device=device)
    if bandwidth is not None and network.config.bandwidth != bandwidth:
        raise InputError(f"{model}: this model was trained at bandwidth {network.config.bandwidth}; register with "
                         f"bandwidth={network.config.bandwidth} (--bandwidth {network.config.bandwidth})")
    return network


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
        refinement: refinement settings (default :class:`Refinement`).
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
    for name, value in (("fixed", fixed), ("moving", moving)):
        _check_image_like(name, value)
    for name, value in (("fixed_mask", fixed_mask), ("moving_mask", moving_mask)):
        if value is not None:
            _check_image_like(name, value)
    refine, resample = check_flag("refine", refine), check_flag("resample", resample)
    _check_settings("preprocessing", preprocessing, Preprocessing)
    _check_settings("refinement", refinement, Refinement)
    _check_settings("solver", solver, SolverConfig)
    if progress is not None and not callable(progress):
        raise InputError(f"progress is {shown(progress)}; expected a function progress(stage, fraction) or None")
    report = progress or (lambda stage, fraction: None)
    refinement = refinement or Refinement()
    mode, bandwidth, torch_device, network = check_options(mode=mode, model=model, bandwidth=bandwidth, device=device,
                                                           fixed_modality=fixed_modality,
                                                           moving_modality=moving_modality)
    if network is not None and solver is not None:
        raise InputError(f"{model}: a learned model carries its own solver settings; pass solver= only without one")
    # A learned model saw grids made one way in training; it gets the same unless the caller says otherwise.
    preprocessing = preprocessing or (network.config.grid_preprocessing() if network is not None else Preprocessing())
    timings: dict[str, float] = {}

    start = time.perf_counter()
    report("reading", 0.0)
    fixed_image, moving_image = load_image(fixed, "fixed image"), load_image(moving, "moving image")
    fixed_mask_image = _load_mask(fixed_mask, fixed_image, "fixed mask")
    moving_mask_image = _load_mask(moving_mask, moving_image, "moving mask")
    timings["read"] = time.perf_counter() - start

    start = time.perf_counter()
    report("preprocessing", 0.1)
    size = 2 * bandwidth
    fixed_prepared = prepare(fixed_image, modality=fixed_modality, mask=fixed_mask_image, config=preprocessing,
                             mask_name=_mask_name(fixed_mask, "fixed mask"))
    moving_prepared = prepare(moving_image, modality=moving_modality, mask=moving_mask_image, config=preprocessing,
                              mask_name=_mask_name(moving_mask, "moving mask"))
    if refine:
        for source, mask, role in ((fixed_mask, fixed_mask_image, "fixed mask"),
                                   (moving_mask, moving_mask_image, "moving mask")):
            _check_mask_extent(mask, _mask_name(source, role), refinement)
    if network is not None:
        _check_model_modalities(model, network, (fixed_modality, moving_modality),
                                (fixed_prepared.modality, moving_prepared.modality))
    fixed_grid, moving_grid = pair_grids(fixed_prepared, moving_prepared, size, preprocessing)
    fixed_tensor = to_tensor(resample_to_grid(fixed_prepared.image, fixed_grid)).to(torch_device)
    moving_tensor = to_tensor(resample_to_grid(moving_prepared.image, moving_grid)).to(torch_device)
    timings["preprocess"] = time.perf_counter() - start

    start = time.perf_counter()
    report("solving", 0.3)
    runner_ups = refinement.starts - 1 if refine else 0  # only a local search can tell them apart (see Refinement)
    if network is None:
        solution = solve(fixed_tensor, moving_tensor, mode, config=solver, bandwidth=bandwidth, profile=True,
                         alternatives=runner_ups)
        timings.update({f"solver.{stage}": seconds for stage, seconds in solution.timings.items()})
        alternatives = solution.alternatives
    else:
        with torch.no_grad():
            try:
                solution = network(fixed_tensor, moving_tensor, mode=mode, alternatives=runner_ups)
            except InputError as error:  # features that overflow: the model's fault, not the images'
                raise InputError(f"{model}: {error}") from None
        alternatives = solution.stage.alternatives
    timings["solve"] = time.perf_counter() - start
    if not all(torch.isfinite(value[0]).all() for value in (solution.rotation, solution.scale, solution.translation,
                                                            solution.confidence)):
        raise _non_finite(model if network is not None else None)
    candidates = [(physical_transform(solution.rotation[0], float(solution.scale[0]) if mode == "similarity" else None,
                                      solution.translation[0], fixed_grid, moving_grid),
                   float(solution.confidence[0]))]
    if alternatives is not None:
        candidates += [(physical_transform(alternatives.rotation[0, k],
                                           float(alternatives.scale[0, k]) if mode == "similarity" else None,
                                           alternatives.translation[0, k], fixed_grid, moving_grid),
                        float(alternatives.confidence[0, k]))
                       for k in range(alternatives.score.shape[1]) if alternatives.score[0, k] > float("-inf")]
    stored = len(candidates) if refine and refinement.stored_start else None  # the stored pose's index
    if stored is not None:  # its confidence is measured only if it wins (with a model, two UNet passes)
        candidates.append((similarity_transform(np.eye(4), np.asarray(fixed_grid.centre), rigid=mode == "rigid"),
                           None))

    metric: dict[str, float | None] = {"stored": None, "dpc": None, "refined": None}
    chosen, candidate_metrics = 0, []
    final, refined = candidates[0][0], False
    if refine:
        start = time.perf_counter()
        report("refining", 0.4)
        # Without a user mask, sample the metric on the fixed foreground (a few mm wider): background air otherwise
        # dominates the joint histogram.
        sampled = fixed_mask_image if fixed_mask_image is not None else sitk.BinaryDilate(
            fixed_prepared.foreground, [refinement.mask_margin_voxels] * 3)
        masks = (sampled, moving_mask_image)
        # The metric's histogram spans each image's range: 8 hot voxels at 300 times the maximum squeezed the anatomy
        # into its first bin and took a right pose 247 mm off.
        fixed_values, moving_values = clip_outliers(fixed_image), clip_outliers(moving_image)
        metric["stored"] = mattes_metric(fixed_values, moving_values, sitk.Transform(3, sitk.sitkIdentity), masks,
                                         refinement)
        pyramid = image_pyramid(fixed_values, moving_values, refinement)
        chosen, candidate, candidate_metrics = refine_candidates(
            pyramid, [transform for transform, _ in candidates], masks, refinement,
            lambda fraction: report("refining", 0.4 + 0.5 * fraction))
        final = candidates[chosen][0]
        metric["dpc"] = mattes_metric(fixed_values, moving_values, final, masks, refinement)
        if metric["dpc"] is not None and candidate is not None:
            metric["refined"] = mattes_metric(fixed_values, moving_values, candidate, masks, refinement)
            # The local optimiser only ever starts from a global estimate; keep it only if it improved the metric.
            if metric["refined"] is not None and metric["refined"] <= metric["dpc"]:
                final, refined = candidate, True
        timings["refine"] = time.perf_counter() - start

    overlap = field_of_view_overlap(fixed_prepared.foreground, moving_image, final)
    resampled = None
    if resample:
        start = time.perf_counter()
        report("resampling", 0.9)
        resampled = resample_moving(fixed_image, moving_image, final)
        timings["resample"] = time.perf_counter() - start
    confidence = candidates[chosen][1]
    if chosen == stored:
        try:
            confidence = stored_pose_confidence(fixed_tensor, moving_tensor, network, solver)
        except InputError as error:
            raise InputError(f"{model}: {error}") from None
    if not math.isfinite(confidence):
        raise _non_finite(model if network is not None else None)
    report("done", 1.0)
    return RegistrationResult(
        fixed_to_moving=final, moving_to_fixed=final.GetInverse(), dpc_transform=candidates[chosen][0],
        confidence=confidence, candidate=chosen,
        start="stored pose" if chosen == stored else "phase correlation", candidate_metrics=candidate_metrics,
        mode=mode, bandwidth=bandwidth, fixed_grid=fixed_grid, moving_grid=moving_grid,
        modalities=(fixed_prepared.modality, moving_prepared.modality), metric=metric,
        refined=refined, overlap=overlap, timings=timings, device=str(torch_device),
        model="learning-free" if network is None else os.fspath(model), fixed_image=fixed_image,
        moving_image=moving_image, resampled=resampled)


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
    truncated towards zero: that biased an int16 CT by up to 0.9 HU), outside filled with its minimum."""
    background = float(sitk.GetArrayViewFromImage(moving).min())
    pixel = moving.GetPixelID()
    if pixel in (sitk.sitkFloat32, sitk.sitkFloat64):
        return sitk.Resample(moving, fixed, fixed_to_moving, sitk.sitkLinear, background, pixel)
    resampled = sitk.Resample(moving, fixed, fixed_to_moving, sitk.sitkLinear, background, sitk.sitkFloat64)
    return sitk.Cast(sitk.Round(resampled), pixel)  # within the input's range: linear interpolation never leaves it


def _registration_method(fixed: sitk.Image, masks: tuple[sitk.Image | None, sitk.Image | None],
                         settings: Refinement) -> sitk.ImageRegistrationMethod:
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
    statistics = sitk.LabelShapeStatisticsImageFilter()
    statistics.Execute(sitk.Cast(mask > 0, sitk.sitkUInt8))
    if not statistics.HasLabel(1):
        return image
    start, size = np.split(np.asarray(statistics.GetBoundingBox(1)), 2)
    corners = [mask.TransformContinuousIndexToPhysicalPoint((start + (size - 1) * np.asarray(corner) + 0.5 * (
        2 * np.asarray(corner) - 1)).tolist()) for corner in np.ndindex(2, 2, 2)]
    indices = np.array([image.TransformPhysicalPointToContinuousIndex(point) for point in corners])
    low = np.clip(np.floor(indices.min(0)).astype(int), 0, np.asarray(image.GetSize()) - 1)
    high = np.clip(np.ceil(indices.max(0)).astype(int), 0, np.asarray(image.GetSize()) - 1)
    return sitk.RegionOfInterest(image, (high - low + 1).tolist(), low.tolist())


def _float32(image: sitk.Image) -> sitk.Image:
    """``image`` as float32, the pixel type the registration method wants; no copy when it is one already."""
    return image if image.GetPixelID() == sitk.sitkFloat32 else sitk.Cast(image, sitk.sitkFloat32)


def mattes_metric(fixed: sitk.Image, moving: sitk.Image, fixed_to_moving: sitk.Transform,
                  masks: tuple[sitk.Image | None, sitk.Image | None],
                  settings: Refinement = Refinement(), *, crop: bool = True) -> float | None:
    """Mattes mutual information of the pair under ``fixed_to_moving`` at full resolution (lower is better); ``None``
    where the transform maps no sampled fixed point into the moving image (no overlap, e.g. two unrelated scanner
    frames taken as they are stored).

    SimpleITK's ``MetricEvaluate`` visits every fixed voxel whatever the sampling settings (measured: the same value
    and time with RANDOM, REGULAR and NONE; 0.7 s on a 1 mm head), so every voxel of the fixed mask counts, and the
    fixed image is cropped to the mask's box first (``crop``; ``False`` where the caller has cropped it already): the
    same value, in less time.
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


MIN_LEVEL_VOXELS = 4
"""The refinement's pyramid shrinks an axis no further than to this many voxels."""


def level_factors(size: Sequence[int], factor: int) -> list[int]:
    """Per-axis shrink factors of a pyramid level of ``factor`` for an image of ``size`` voxels: an axis keeps at
    least :data:`MIN_LEVEL_VOXELS` voxels (thinner, ITK's metric fails on the level's images)."""
    return [max(1, min(factor, length // MIN_LEVEL_VOXELS)) for length in size]


def first_step_mm(settings: Refinement, spacing: Sequence[float]) -> float:
    """The regular-step gradient descent's first step (mm) at the coarsest level of fixed voxel ``spacing`` (mm):
    ``settings.max_step_mm``, or half the finest of ``spacing`` where that is ``None``, so that the step follows the
    image's scale (a mouse at 0.1 mm and a head at 2 mm alike)."""
    return settings.max_step_mm if settings.max_step_mm is not None else 0.5 * float(min(spacing))


def image_pyramid(fixed: sitk.Image, moving: sitk.Image, settings: Refinement = Refinement()
                  ) -> list[tuple[sitk.Image, sitk.Image]]:
    """Both images per refinement level, coarse to fine: float32, smoothed (``settings.smoothing_mm``, physical
    sigma) and shrunk (``settings.shrink_factors``).

    Computed once and shared by every start: SimpleITK's registration method rebuilds its pyramid on each run, which
    on a 1 mm head costs about ten times the coarse level's own optimisation.
    """
    levels = []
    for factor, sigma in zip(settings.shrink_factors, settings.smoothing_mm, strict=True):
        pair = []
        for image in (fixed, moving):
            image = sitk.Cast(image, sitk.sitkFloat32)
            if sigma > 0:
                image = sitk.SmoothingRecursiveGaussian(image, sigma)
            factors = level_factors(image.GetSize(), factor)
            pair.append(sitk.Shrink(image, factors) if max(factors) > 1 else image)
        levels.append((pair[0], pair[1]))
    return levels


def refine_candidates(pyramid: list[tuple[sitk.Image, sitk.Image]], candidates: list[sitk.Transform],
                      masks: tuple[sitk.Image | None, sitk.Image | None], settings: Refinement = Refinement(),
                      progress: Callable[[float], None] | None = None
                      ) -> tuple[int, sitk.Transform | None, list[float | None]]:
    """The local search from several global candidates, by successive halving over the pyramid.

    Every candidate that overlaps runs the coarsest level; after each level only the ``settings.survivors`` best (by
    the metric on that level's images) go on. Phase correlation ranks a pose and its half-turn twin almost alike
    across modalities, and mutual information at the unrefined poses hardly differs either; one coarse level from
    each tells them apart (MNI head T1 to its pseudo-CT: about -0.66 from the right candidate, -0.09 from the twins).

    Args:
        pyramid: :func:`image_pyramid` of the pair.
        candidates: the starts, fixed to moving: the solver's global estimates, its own choice first, and the stored
            pose last when it is one (:attr:`Refinement.stored_start`).

    Returns:
        ``(index, transform, metrics)``: the winner's index in ``candidates``, its refined transform (``None`` when no
        candidate overlaps the fixed mask) and every candidate's metric after the coarsest level (``None`` without
        overlap).
    """
    # The images are pre-shrunk; each level's first step shrinks with them (Refinement.max_step_mm), as ITK's
    # multi-resolution examples (MultiResImageRegistration1) shrink the optimiser's step between levels.
    coarsest = first_step_mm(settings, pyramid[0][0].GetSpacing())
    level_settings = [replace(settings, shrink_factors=(1,), smoothing_mm=(0.0,),
                              max_step_mm=coarsest * factor / settings.shrink_factors[0])
                      for factor in settings.shrink_factors]
    # Each level's fixed image cropped to the fixed mask's box once, for every metric evaluation on that level.
    cropped = [fixed if masks[0] is None else _crop_to_mask(fixed, masks[0]) for fixed, _ in pyramid]
    coarse_moving = pyramid[0][1]
    survivors = [(index, candidate) for index, candidate in enumerate(candidates)
                 if mattes_metric(cropped[0], coarse_moving, candidate, masks, level_settings[0],
                                  crop=False) is not None]
    metrics: list[float | None] = [None] * len(candidates)
    for level, (fixed, moving) in enumerate(pyramid):
        if level > 0:
            survivors = survivors[:settings.survivors[min(level, len(settings.survivors)) - 1]]
        scored = []
        for done, (index, transform) in enumerate(survivors, start=1):
            try:
                transform = refine_transform(fixed, moving, transform, masks, level_settings[level])
                value = mattes_metric(cropped[level], moving, transform, masks, level_settings[level],
                                      crop=False) if len(survivors) > 1 or level == 0 else None
            except RuntimeError as error:  # the search drifted off the moving image: this start is lost
                if not _lost_overlap(error):
                    raise
                value = None
            scored.append((math.inf if value is None else value, index, transform))
            if level == 0:
                metrics[index] = value
            if progress is not None:
                progress((level + done / len(survivors)) / len(pyramid))
        survivors = [(index, transform) for _, index, transform in _merge_same_poses(
            sorted(scored, key=lambda item: item[0]), cropped[level])]
    if not survivors:
        return 0, None, metrics
    return survivors[0][0], survivors[0][1], metrics


def _merge_same_poses(scored: list[tuple[float, int, sitk.Transform]], fixed: sitk.Image
                      ) -> list[tuple[float, int, sitk.Transform]]:
    """``scored`` (metric, start index, refined transform; best metric first) with the starts that reached one pose
    (within a voxel of ``fixed``, on average over its corners) merged: the best metric and its transform, under the
    lowest start index. Which start found an optimum is the solver's ranking's call, the stored pose last: without
    this, the stored pose won ties by sampling noise (an MRI-DIR CT round trip: both -1.33), and the report named the
    identity as the start, with its own low confidence. The transform stays the best one: a voxel is 8 mm at the
    coarsest level, and two starts that close can still end apart in metric (an MNI pseudo-CT pose: -0.46 and
    -0.69 there, 0.99 mm off when the lower index's transform went on, 0.04 mm with the better one)."""
    ends = np.asarray(fixed.GetSize()) - 1
    corners = [fixed.TransformContinuousIndexToPhysicalPoint((ends * np.asarray(corner)).tolist())
               for corner in np.ndindex(2, 2, 2)]
    tolerance = max(fixed.GetSpacing())
    merged: list[tuple[float, int, sitk.Transform]] = []
    for value, index, transform in scored:
        same = next((place for place, (_, _, other) in enumerate(merged) if math.isfinite(value)
                     and target_registration_error(transform, other, corners) < tolerance), None)
        if same is None:
            merged.append((value, index, transform))
        elif index < merged[same][1]:
            merged[same] = (merged[same][0], index, merged[same][2])
    return merged


def refine_transform(fixed: sitk.Image, moving: sitk.Image, initial: sitk.Transform,
                     masks: tuple[sitk.Image | None, sitk.Image | None], settings: Refinement = Refinement(),
                     progress: Callable[[float], None] | None = None) -> sitk.Transform:
    """Multi-resolution Mattes mutual-information registration started from ``initial``, in one SimpleITK run: every
    level's first step is the coarsest level's (:func:`first_step_mm`; :func:`refine_candidates` shrinks it level by
    level).

    The optimiser moves a residual transform ``D`` near the identity and the result is ``initial o D``: a versor
    parameterises rotations badly near 180 degrees (its scalar part vanishes), where a global estimate often lies.

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
