"""Training pairs with exact ground truth: two simulated modalities of one volume, a random pose, a partial overlap."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from dpcn_med.arguments import check_flag, check_integer, check_pair, check_real
from dpcn_med.errors import InputError
from dpcn_med.geometry import random_rotation, warp
from dpcn_med.solver import PoseTarget
from dpcn_med.synth._common import check_volumes, host_generator, integers, normal, uniform
from dpcn_med.synth.anatomy import AnatomyConfig, deformed_anatomy
from dpcn_med.synth.contrast import ContrastConfig, random_modality
from dpcn_med.synth.ultrasound import UltrasoundConfig, simulated_ultrasound

PAIR_MODALITIES = ("random", "identity", "ultrasound")
"""How a side of a pair is simulated: :func:`~dpcn_med.synth.contrast.random_modality`, the volume itself, or
:func:`~dpcn_med.synth.ultrasound.simulated_ultrasound` of the volume taken as a CT."""

_MODES = ("similarity", "rigid")


def _check_modality(name: str, modality: str) -> str:
    if modality not in PAIR_MODALITIES:
        raise InputError(f"{name} {modality!r} is not supported; use one of {', '.join(PAIR_MODALITIES)}")
    return modality


@dataclass(frozen=True)
class PairConfig:
    """How :func:`synthetic_pairs` draws poses, crops and modalities; the defaults follow DESIGN section 5.

    Attributes:
        mode: ``"similarity"`` (scale uniform in ``scale_range``) or ``"rigid"`` (scale 1).
        max_shift_fraction: translation length uniform up to this fraction of the grid side ``N``, direction uniform.
        scale_range: interval of the scale in similarity mode.
        overlap_range: fraction of the foreground the fixed volume keeps after its slab crop, uniform in this
            interval inside ``(0, 1]`` (1 = no crop).
        crop_probability: chance that a fixed volume is cropped at all.
        fixed_modality, moving_modality: one of :data:`PAIR_MODALITIES` for each side.
        fixed_contrast, moving_contrast: ranges of the random modality of each side.
        ultrasound: field of view and acoustics of a simulated ultrasound side.
        anatomy: the random deformation of each base volume before both sides are made (off by default).

    Raises:
        InputError: an unknown mode or modality, or a range outside its domain.
    """

    mode: str = "similarity"
    max_shift_fraction: float = 0.2
    scale_range: tuple[float, float] = (0.8, 1.2)
    overlap_range: tuple[float, float] = (0.6, 1.0)
    crop_probability: float = 0.5
    fixed_modality: str = "random"
    moving_modality: str = "random"
    fixed_contrast: ContrastConfig = field(default_factory=ContrastConfig)
    moving_contrast: ContrastConfig = field(default_factory=ContrastConfig)
    ultrasound: UltrasoundConfig = field(default_factory=UltrasoundConfig)
    anatomy: AnatomyConfig = field(default_factory=AnatomyConfig)

    def __post_init__(self) -> None:
        if self.mode not in _MODES:
            raise InputError(f"mode {self.mode!r} is not supported; use one of {', '.join(_MODES)}")
        _check_modality("fixed_modality", self.fixed_modality)
        _check_modality("moving_modality", self.moving_modality)
        check_pair("overlap_range", self.overlap_range, minimum=0.0, maximum=1.0, above=True, equal=True,
                   note=" (the fraction of the foreground the fixed volume keeps)")
        check_pair("scale_range", self.scale_range, minimum=0.0, above=True, equal=True)
        check_real("crop_probability", self.crop_probability, minimum=0.0, maximum=1.0, note=" (a probability)")
        check_real("max_shift_fraction", self.max_shift_fraction, minimum=0.0, maximum=0.5,
                   note=" (a fraction of N: a shift past half the grid is a wrap-around to phase correlation, and "
                   "moves the object off the grid)")


def _random_poses(batch: int, size: int, generator: torch.Generator, config: PairConfig, like: Tensor) -> PoseTarget:
    """Rotation uniform over SO(3), shift uniform in direction and length, scale uniform (1 when rigid)."""
    rotation = random_rotation(batch, host_generator(generator), dtype=like.dtype).to(like.device)
    scale = (uniform(generator, (batch,), *config.scale_range, like=like) if config.mode == "similarity"
             else like.new_ones(batch))
    direction = normal(generator, (batch, 3), like=like)
    length = uniform(generator, (batch,), 0.0, config.max_shift_fraction * size, like=like)
    return PoseTarget(rotation, scale, direction / direction.norm(dim=-1, keepdim=True) * length[:, None])


def slab_mask(foreground: Tensor, fraction: float, axis: int, from_end: bool) -> Tensor:
    """1 on a slab along ``axis`` that keeps ``fraction`` of ``foreground``, 0 beyond it.

    The slab starts at one end of the axis (the last when ``from_end``) and ends at the first slice where the kept
    foreground reaches ``fraction`` (the crop of :func:`synthetic_pairs`, and of
    :class:`dpcn_med.train.folders.FolderPairs`).

    Args:
        foreground: ``(D, H, W)`` bool.
        fraction: in ``(0, 1]``.
        axis: torch axis, 0 (z), 1 (y) or 2 (x).
        from_end: start at the high-index end.

    Returns:
        ``(D, H, W)`` float32 mask, broadcast along the other two axes.

    Raises:
        InputError: ``fraction`` outside ``(0, 1]``, ``axis`` not 0, 1 or 2, or ``from_end`` not a bool.
    """
    check_real("fraction", fraction, minimum=0.0, maximum=1.0, above=True)
    axis = check_integer("axis", axis, minimum=0, maximum=2)
    check_flag("from_end", from_end)
    profile = foreground.float().sum([a for a in range(3) if a != axis])
    if from_end:
        profile = profile.flip(0)
    kept = profile.cumsum(0) / profile.sum().clamp_min(1.0)
    end = int(torch.searchsorted(kept, torch.tensor([fraction], dtype=kept.dtype, device=kept.device))) + 1
    inside = torch.zeros_like(profile)
    inside[:end] = 1.0
    if from_end:
        inside = inside.flip(0)
    return inside.reshape([-1 if a == axis else 1 for a in range(3)]).expand(foreground.shape)


def _slab_masks(volumes: Tensor, generator: torch.Generator, config: PairConfig) -> Tensor:
    """Per volume, 1 on a slab along a random axis that keeps a random fraction of the foreground, 0 beyond it.

    The slab starts at one end of the axis (chosen at random) and ends at the first slice where the kept foreground
    reaches the drawn overlap; volumes not drawn for cropping keep everything.
    """
    batch = volumes.shape[0]
    cropped = uniform(generator, (batch,), 0.0, 1.0, like=volumes) < config.crop_probability
    overlap = uniform(generator, (batch,), *config.overlap_range, like=volumes)
    axes, from_end = integers(generator, 3, batch), integers(generator, 2, batch)
    masks = torch.ones_like(volumes)
    for index in torch.nonzero(cropped).flatten().tolist():
        masks[index, 0] = slab_mask(volumes[index, 0] > 0, float(overlap[index]), int(axes[index]),
                                    bool(from_end[index]))
    return masks


def _simulate(volumes: Tensor, generator: torch.Generator, modality: str, contrast: ContrastConfig,
              config: PairConfig) -> Tensor:
    if modality == "identity":
        return volumes
    if modality == "ultrasound":
        return simulated_ultrasound(volumes, generator, config=config.ultrasound)[0]
    return random_modality(volumes, generator, contrast)


def synthetic_pairs(volumes: Tensor, generator: torch.Generator, config: PairConfig = PairConfig(), *,
                    fixed_modality: str | None = None, moving_modality: str | None = None
                    ) -> tuple[Tensor, Tensor, PoseTarget]:
    """Fixed and moving volumes of the same anatomy in two simulated modalities, with their exact pose.

    Each base volume is first deformed into a head of its own (:func:`~dpcn_med.synth.anatomy.deformed_anatomy`,
    with ``config.anatomy``; off by default), shared by both sides. The fixed volume is a modality of ``volumes``
    (slab-cropped with probability ``config.crop_probability``); the moving one is another modality of ``volumes``
    moved by a random similarity ``A p + t``, ``A = scale * rotation``:
    ``moving = warp(modality(volumes), A^-1, -A^-1 t)`` (as :meth:`dpcn_med.synth.Pose.moving_from`, batched), so
    ``fixed(p) ~ moving(A p + t)`` wherever both have content. Content moved off the grid is lost.

    Args:
        volumes: ``(B, 1, N, N, N)`` base volumes, intensities in ``[0, 1]``, 0 in the background (e.g. from
            :func:`dpcn_med.preprocess.solver_grid`).
        generator: source of randomness (any device; draws are moved to ``volumes``' device).
        config: poses, crops and modalities.
        fixed_modality, moving_modality: override ``config``'s choice, one of :data:`PAIR_MODALITIES`.

    Returns:
        ``(fixed, moving, target)``: two ``(B, 1, N, N, N)`` batches with ``volumes``' device and dtype, and the
        :class:`~dpcn_med.solver.PoseTarget` (rotation ``(B, 3, 3)``, scale ``(B,)``, translation ``(B, 3)`` voxels
        ``(x, y, z)``) in the same device and dtype.

    Raises:
        InputError: ``volumes`` is not a floating cubic batch, or a modality is unknown.

    Convention:
        The solver's contract ``fixed(p) ~ moving(scale * rotation @ p + translation)``, ``p`` voxels ``(x, y, z)``
        from the grid centre, pull resampling: :mod:`dpcn_med.geometry`.
    """
    size = check_volumes("volumes", volumes, cubic=True)
    fixed_modality = _check_modality("fixed_modality", fixed_modality or config.fixed_modality)
    moving_modality = _check_modality("moving_modality", moving_modality or config.moving_modality)
    volumes = deformed_anatomy(volumes, generator, config.anatomy)
    target = _random_poses(volumes.shape[0], size, generator, config, volumes)
    fixed = _simulate(volumes, generator, fixed_modality, config.fixed_contrast, config)
    fixed = fixed * _slab_masks(volumes, generator, config)
    moving = _simulate(volumes, generator, moving_modality, config.moving_contrast, config)
    inverse = torch.linalg.inv_ex(target.scale[:, None, None] * target.rotation).inverse  # inv: a host sync on CUDA
    moving = warp(moving, inverse, -(inverse @ target.translation[..., None])[..., 0])
    return fixed, moving, target
