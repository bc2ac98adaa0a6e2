"""Dense cross-modal pretraining of the rotation-stage networks, without the solver.

For a synthetic pair ``fixed(p) ~ moving(A p + t)`` (two simulated modalities of one head, the moving one turned over
SO(3) on its own), each side's rotation-stage UNet maps its volume to a feature grid; the moving side's features are
warped back into the fixed frame with the true pose, both are band-passed to the frequencies the solver's sphere
reads, and the loss is one minus their normalised cross-correlation (NCC) inside the eroded overlap of the two
foregrounds; optionally plus a pose contrast (:func:`pose_contrast`): the NCC at the true pose must stand out from
the NCC at decoy poses. At the end of pretraining each pretrained extractor takes a gain that makes its UNet term
outweigh the raw volume, which is modality-specific (:func:`set_pretrained_gains`).

Why each choice, and what each measured: docs/learning.md ("Dense pretraining of the rotation features") and
../shared/LEARNING.md ("Pitfalls for a dense cross-modal objective").

Convention:
    Grids ``(B, 1, N, N, N)`` in the solver's order (z, y, x) and the pose convention of :mod:`dpcn_med.geometry`
    (``warp(volume, A, t)(p) = volume(A p + t)``, ``p`` voxels ``(x, y, z)`` from the grid centre).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from dpcn_med.arguments import check_integer, check_pair, check_real
from dpcn_med.geometry import axis_angle_to_matrix, half_turns, warp
from dpcn_med.solver import PoseTarget

PRETRAINED_EXTRACTORS = ("rotation_fixed", "rotation_moving")
"""The extractors pretraining trains (a model with shared weights has one)."""


def pretrained_extractors(model: torch.nn.Module) -> dict[str, torch.nn.Module]:
    """``model``'s distinct :data:`PRETRAINED_EXTRACTORS` by name: one entry when the two share their weights."""
    distinct: dict[int, tuple[str, torch.nn.Module]] = {}
    for name in PRETRAINED_EXTRACTORS:
        distinct.setdefault(id(getattr(model, name)), (name, getattr(model, name)))
    return dict(distinct.values())
EPSILON = 1e-6
"""Added to the NCC's variances: a feature grid constant over the overlap correlates with nothing."""


@dataclass(frozen=True)
class PretrainConfig:
    """Settings of dense pretraining, the ``pretrain:`` section of a training config.

    Attributes:
        steps: the first this many optimiser steps train the rotation-stage UNets with :func:`dense_loss` instead of
            the pose loss (0: no pretraining).
        band: the band-pass, as fractions ``(low, high)`` of the Nyquist radius.
        erosion_voxels: the overlap of the two foregrounds is eroded by this many voxels before the NCC.
        feature_gain: at the end of pretraining each pretrained extractor's gain is set so that its UNet term has
            this many times the foreground standard deviation of the raw volume (:func:`set_pretrained_gains`).
        contrast_weight: weight of the contrast term (:func:`pose_contrast`): the similarity at the true pose must
            stand out from the similarities at its six half-turn twins and its near misses (0: the NCC term alone).
        contrast_temperature: the softmax temperature of that term, in units of NCC.
        near_degrees: the near misses are the true pose turned by this angle about each grid axis, both ways (six
            more poses; 0: none).
        decoys: how many of those poses each step draws at random for the contrast (0: all; each costs a warp of
            the moving features).

    Raises:
        InputError: a value out of its range (the message names it).
    """

    steps: int = 0
    band: tuple[float, float] = (0.1, 0.6)
    erosion_voxels: int = 3
    feature_gain: float = 4.0
    contrast_weight: float = 0.0
    contrast_temperature: float = 0.1
    near_degrees: float = 0.0
    decoys: int = 0

    def __post_init__(self) -> None:
        check_integer("steps", self.steps, minimum=0)
        check_pair("band", self.band, minimum=0.0, maximum=math.sqrt(3),
                   note=" (fractions of the Nyquist radius; the grid's corners are at sqrt(3))")
        check_integer("erosion_voxels", self.erosion_voxels, minimum=0)
        check_real("feature_gain", self.feature_gain, minimum=0.0, above=True)
        check_real("contrast_weight", self.contrast_weight, minimum=0.0)
        check_real("contrast_temperature", self.contrast_temperature, minimum=0.0, above=True)
        check_real("near_degrees", self.near_degrees, minimum=0.0, maximum=90.0)
        check_integer("decoys", self.decoys, minimum=0)


def band_pass(volume: Tensor, band: tuple[float, float]) -> Tensor:
    """``volume`` ``(B, C, N, N, N)`` with only the frequencies whose radius, as a fraction of the Nyquist radius
    (0.5 cycles per voxel), lies in ``band`` (an ideal radial filter, the solver's own spectral band: torch and MONAI
    have no radial band-pass)."""
    size = volume.shape[-3:]
    axes = [torch.fft.fftfreq(n, device=volume.device) for n in size[:-1]] + [
        torch.fft.rfftfreq(size[-1], device=volume.device)]
    grid = torch.meshgrid(*axes, indexing="ij")
    radius = torch.sqrt(sum(axis ** 2 for axis in grid)) / 0.5
    keep = ((radius >= band[0]) & (radius <= band[1])).to(volume.dtype)
    spectrum = torch.fft.rfftn(volume, dim=(-3, -2, -1))
    return torch.fft.irfftn(spectrum * keep, s=size, dim=(-3, -2, -1))


def masked_ncc(first: Tensor, second: Tensor, mask: Tensor) -> Tensor:
    """``(B,)`` normalised cross-correlation of ``first`` and ``second`` ``(B, C, ...)`` over the voxels (and
    channels) where ``mask`` ``(B, 1, ...)`` is 1; 0 where either is constant there or the mask is empty."""
    mask = mask.expand_as(first).flatten(1)
    first, second = first.flatten(1), second.flatten(1)
    count = mask.sum(1).clamp_min(1)

    def centred(values: Tensor) -> Tensor:
        return (values - (values * mask).sum(1, keepdim=True) / count[:, None]) * mask

    a, b = centred(first), centred(second)
    return (a * b).sum(1) / torch.sqrt((a * a).sum(1) * (b * b).sum(1) + EPSILON)


def _erode(mask: Tensor, voxels: int) -> Tensor:
    """A binary ``(B, 1, N, N, N)`` mask eroded by a cube of ``2 * voxels + 1``."""
    if voxels == 0:
        return mask
    return -F.max_pool3d(-mask, 2 * voxels + 1, stride=1, padding=voxels)


def dense_similarity(fixed_features: Tensor, moving_features: Tensor, fixed: Tensor, moving: Tensor,
                     target: PoseTarget, config: PretrainConfig = PretrainConfig()) -> Tensor:
    """``(B,)`` band-passed NCC of the two sides' features in the fixed frame.

    Args:
        fixed_features, moving_features: ``(B, C, N, N, N)`` features of ``fixed`` and ``moving``.
        fixed, moving: ``(B, 1, N, N, N)`` the volumes, 0 outside their foreground (their masks).
        target: the pose with ``fixed(p) ~ moving(scale * rotation @ p + translation)``.
    """
    linear = (target.scale[:, None, None] * target.rotation).to(moving_features.dtype)
    return _similarity(band_pass(fixed_features, config.band), moving_features, fixed, moving, linear,
                       target.translation.to(moving_features.dtype), config)


def _similarity(fixed_band: Tensor, moving_features: Tensor, fixed: Tensor, moving: Tensor, linear: Tensor,
                shift: Tensor, config: PretrainConfig) -> Tensor:
    """``(B,)`` NCC of the band-passed fixed features ``fixed_band`` and the moving features warped back by
    ``linear`` ``(B, 3, 3)`` and ``shift`` ``(B, 3)``, inside the eroded overlap of the two foregrounds."""
    warped = warp(moving_features, linear, shift)
    foreground = (fixed > 0).to(fixed_band.dtype) * (warp((moving > 0).to(moving.dtype), linear, shift) > 0.5
                                                     ).to(fixed_band.dtype)
    return masked_ncc(fixed_band, band_pass(warped, config.band), _erode(foreground, config.erosion_voxels))


def decoy_poses(linear: Tensor, near_degrees: float = 0.0) -> list[Tensor]:
    """The poses :func:`pose_contrast` tells the true ``linear`` ``(B, 3, 3)`` from: its six half-turn twins (composed
    with a half-turn about a fixed-grid or a moving-grid axis: the candidates the solver tries beside each rotation
    peak) and, when ``near_degrees`` > 0, six near misses (turned by that angle about each fixed-grid axis, both
    ways)."""
    turns = half_turns(linear.device, linear.dtype)
    poses = [linear @ turn for turn in turns[1:]] + [turn @ linear for turn in turns[1:]]
    if near_degrees > 0:
        vectors = math.radians(near_degrees) * torch.cat([torch.eye(3), -torch.eye(3)]).to(linear)
        poses += [linear @ turn for turn in axis_angle_to_matrix(vectors)]
    return poses


def _pose_similarities(fixed_features: Tensor, moving_features: Tensor, fixed: Tensor, moving: Tensor,
                       target: PoseTarget, config: PretrainConfig, generator: torch.Generator | None) -> Tensor:
    """``(B, 1 + D)``: :func:`dense_similarity` at the true pose, then at ``D`` of its :func:`decoy_poses`
    (``config.decoys`` of them drawn with ``generator``, the same for the whole batch, when that is not 0)."""
    linear = (target.scale[:, None, None] * target.rotation).to(moving_features.dtype)
    fixed_band = band_pass(fixed_features, config.band)
    shift = target.translation.to(moving_features.dtype)
    decoys = decoy_poses(linear, config.near_degrees)
    if 0 < config.decoys < len(decoys):
        drawn = torch.randperm(len(decoys), generator=generator, device="cpu" if generator is None else
                               generator.device)[:config.decoys]
        decoys = [decoys[int(index)] for index in drawn]
    return torch.stack([_similarity(fixed_band, moving_features, fixed, moving, pose, shift, config)
                        for pose in [linear, *decoys]], 1)


def _contrast(similarities: Tensor, config: PretrainConfig) -> Tensor:
    return -torch.log_softmax(similarities / config.contrast_temperature, 1)[:, 0]


def pose_contrast(fixed_features: Tensor, moving_features: Tensor, fixed: Tensor, moving: Tensor,
                  target: PoseTarget, config: PretrainConfig = PretrainConfig(),
                  generator: torch.Generator | None = None) -> Tensor:
    """``(B,)`` cross-entropy of the true pose among it and its :func:`decoy_poses` (``config.decoys`` of them drawn
    with ``generator``, the same for the whole batch, when that is not 0), by their :func:`dense_similarity` over
    ``config.contrast_temperature``: features that agree as well at a twin or a few degrees off score no better than
    chance."""
    return _contrast(_pose_similarities(fixed_features, moving_features, fixed, moving, target, config, generator),
                     config)


def dense_loss(model: torch.nn.Module, fixed: Tensor, moving: Tensor, target: PoseTarget,
               config: PretrainConfig = PretrainConfig(), *, amp: bool = False,
               generator: torch.Generator | None = None) -> dict[str, Tensor]:
    """The pretraining terms of a batch, on the UNet outputs of ``model``'s rotation-stage extractors (without their
    raw-volume term): ``"dense_ncc"`` (batch mean of :func:`dense_similarity`), ``"pose_contrast"`` (batch mean of
    :func:`pose_contrast`; zero when ``config.contrast_weight`` is) and ``"total"``: one minus the first plus
    ``config.contrast_weight`` times the second. ``amp``: the UNets (only) run under bfloat16 autocast, as in
    :meth:`dpcn_med.models.DPCN.forward`; ``generator`` draws the contrast's decoys."""
    with torch.autocast(fixed.device.type, dtype=torch.bfloat16, enabled=amp):
        fixed_features, moving_features = model.rotation_fixed.unet(fixed), model.rotation_moving.unet(moving)
    fixed_features, moving_features = fixed_features.to(fixed.dtype), moving_features.to(moving.dtype)
    if config.contrast_weight > 0:  # the truth's similarity is the first of the contrast's: one warp, not two
        similarities = _pose_similarities(fixed_features, moving_features, fixed, moving, target, config, generator)
        similarity, contrast = similarities[:, 0].mean(), _contrast(similarities, config).mean()
    else:
        similarity = dense_similarity(fixed_features, moving_features, fixed, moving, target, config).mean()
        contrast = torch.zeros((), device=fixed.device)
    return {"total": 1 - similarity + config.contrast_weight * contrast, "dense_ncc": similarity,
            "pose_contrast": contrast}


@torch.no_grad()
def set_pretrained_gains(model: torch.nn.Module, fixed: Tensor, moving: Tensor, config: PretrainConfig
                         ) -> dict[str, float]:
    """Set the gain of each rotation-stage extractor to ``config.feature_gain`` times the ratio of the raw volume's
    foreground standard deviation to its UNet output's, over the batch ``fixed`` / ``moving``; the gains set, by
    extractor."""
    gains = {}
    for name, volume in zip(PRETRAINED_EXTRACTORS, (fixed, moving)):
        extractor = getattr(model, name)
        inside = volume > 0
        output = extractor.unet(volume)
        ratio = volume[inside].std() / output[inside].std().clamp_min(EPSILON)
        extractor.gain.fill_(config.feature_gain * float(ratio))
        gains[name] = extractor.gain.item()
    return gains
