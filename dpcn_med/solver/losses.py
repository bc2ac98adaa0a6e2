"""DPCN++ training losses (DESIGN 2.7): per stage, an L1 on the expectation and a KL divergence on the distribution."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dpcn_med.arguments import check_flag, check_real, shown
from dpcn_med.errors import InputError
from dpcn_med.geometry import geodesic_distance, grid_centre, half_turns
from dpcn_med.solver.so3 import euler_grid, grid_rotations
from dpcn_med.solver.solve3d import SolveResult
from dpcn_med.solver.translation import TranslationEstimate

_WEIGHTS = ("rotation_kl", "rotation_l1", "translation_kl", "translation_l1", "scale_kl", "scale_l1",
            "candidate_ranking")

MIN_SIGMA = 1e-6
"""Least target width (radians or cells), far below a grid cell, where the target is one cell already (why this
value: docs/design_notes/solver.md)."""


@dataclass(frozen=True)
class LossWeights:
    """Weights of the training terms; the six of the paper default to its ``{1, 3, 3, 1, 1, 3}``.

    Attributes:
        rotation_kl, rotation_l1, translation_kl, translation_l1, scale_kl, scale_l1: the weights.
        candidate_ranking: weight of a learned model's candidate ranking loss
            (:func:`dpcn_med.models.pose_loss`; the solver's own loss has no such term). 0 leaves it out.
        rotation_sigma: width in radians of the Gaussian target on SO(3).
        rotation_twins: take the least of the rotation KLs to the true rotation and to each of its six half-turn
            twins (the candidates the solver tries beside each peak), so that the KL does not penalise the twin that
            a symmetric anatomy makes as likely; the candidate choice then tells them apart.
        shift_sigma: width in grid cells of the Gaussian targets of the translation and scale stages.
        candidate_degrees: the ranking loss's target is the candidate nearest the truth when it lies within this many
            degrees of it; pairs with none that near are left out of that term.
    """

    rotation_kl: float = 1.0
    rotation_l1: float = 3.0
    translation_kl: float = 3.0
    translation_l1: float = 1.0
    scale_kl: float = 1.0
    scale_l1: float = 3.0
    candidate_ranking: float = 0.0
    rotation_sigma: float = math.radians(5.0)
    rotation_twins: bool = False
    shift_sigma: float = 1.0
    candidate_degrees: float = 15.0

    def __post_init__(self) -> None:
        """Check that the weights are finite and >= 0 and the widths finite and >= :data:`MIN_SIGMA`; store numpy
        scalars as Python floats.

        Raises:
            InputError: a value of the wrong type or out of range.
        """
        for name in _WEIGHTS:
            object.__setattr__(self, name, check_real(name, getattr(self, name), minimum=0.0))
        for name in ("rotation_sigma", "shift_sigma"):
            object.__setattr__(self, name, check_real(name, getattr(self, name), minimum=MIN_SIGMA))
        check_flag("rotation_twins", self.rotation_twins)
        object.__setattr__(self, "candidate_degrees", check_real("candidate_degrees", self.candidate_degrees,
                                                                 minimum=0.0, maximum=180.0, above=True))


def _kl_from_log_target(log_target: Tensor, log_prob: Tensor) -> Tensor:
    """``KL(q || p)`` over all but the batch axis, from unnormalised ``log q`` and normalised ``log p``.

    Returns:
        ``(batch,)``.
    """
    flat_target = log_target.flatten(1)
    log_q = flat_target - torch.logsumexp(flat_target, -1, keepdim=True)
    return (log_q.exp() * (log_q - log_prob.flatten(1))).sum(-1)


@functools.lru_cache(maxsize=2)
def _euler_grid_rotations(bandwidth: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    """Rotation of every Euler grid cell: ``(2B, 2B, 2B, 3, 3)``, cached (its size: docs/design_notes/solver.md)."""
    ticks = torch.arange(2 * bandwidth, device=device, dtype=dtype)
    return grid_rotations(bandwidth, torch.stack(torch.meshgrid(ticks, ticks, ticks, indexing="ij"), -1))


def twins(rotation: Tensor) -> Tensor:
    """``(batch, 3, 3)`` -> ``(batch, 7, 3, 3)``: each rotation, then composed with the half-turns about the fixed
    grid's axes (on the right) and the moving grid's (on the left): the twins the solver tries beside each peak."""
    turns = half_turns(device=rotation.device, dtype=rotation.dtype)
    return torch.cat([rotation[:, None] @ turns, turns[1:] @ rotation[:, None]], 1)


def rotation_kl(log_prob: Tensor, target: Tensor, sigma: float, *, with_twins: bool = False) -> Tensor:
    """KL divergence from a Gaussian on SO(3) around the true rotation to the Euler-grid distribution.

    Args:
        log_prob: ``(batch, 2B, 2B, 2B)`` Haar-weighted log-softmax ``[alpha, beta, gamma]``
            (``SolveResult.rotation_log_prob``).
        target: ``(batch, 3, 3)`` true rotation.
        sigma: radians.
        with_twins: the least of the KL divergences to a Gaussian at ``target`` and at each of its :func:`twins`:
            the distribution may put its mass on any one of them (not a mixture, which would ask it to cover all
            seven: why: docs/design_notes/solver.md).

    Returns:
        ``(batch,)``. The target is ``exp(-angle(R_cell, target)^2 / 2 sigma^2) sin(beta)``, Haar-weighted like ``p``.
    """
    bandwidth = log_prob.shape[-1] // 2
    cells = _euler_grid_rotations(bandwidth, log_prob.device, log_prob.dtype)
    centres = twins(target.to(log_prob.dtype)) if with_twins else target.to(log_prob.dtype)[:, None]
    _, beta, _ = euler_grid(bandwidth, device=log_prob.device, dtype=log_prob.dtype)
    log_sin = torch.log(torch.sin(beta))[None, None, :, None]
    # One target at a time: broadcast over the batch, the products were (batch, 2B, 2B, 2B, 3, 3) temporaries,
    # 2.4 GB each at B = 64 and batch 32 (the angle is a constant of the loss: nothing is kept for backward).
    return torch.stack([torch.stack([
        _kl_from_log_target(-geodesic_distance(cells, rotation[None, None, None])[None] ** 2 / (2 * sigma ** 2)
                            + log_sin, log_prob[item:item + 1])[0]
        for rotation in centre]).amin(0) for item, centre in enumerate(centres)])


def shift_kl(log_prob: Tensor, target: Tensor, sigma: float, *, periodic: tuple[bool, ...] | None = None) -> Tensor:
    """KL divergence from a Gaussian around the true shift to a Cartesian soft-arg-max distribution.

    Args:
        log_prob: ``(batch, *S)`` log-softmax over shifts, zero shift at index ``size // 2`` (``SoftPeak.log_prob``).
        target: ``(batch, d)`` true shift in cells, order ``(x, y[, z])``.
        sigma: cells.
        periodic: per axis (torch order), whether distances wrap; default all.

    Returns:
        ``(batch,)``.
    """
    sizes = log_prob.shape[1:]
    dim = len(sizes)
    periodic = periodic or (True,) * dim
    squared = 0.0
    for axis, n in enumerate(sizes):
        cell = torch.arange(n, device=log_prob.device, dtype=log_prob.dtype) - grid_centre(n)
        delta = cell[None] - target[:, dim - 1 - axis, None].to(log_prob.dtype)  # (batch, n)
        if periodic[axis]:
            delta = torch.remainder(delta + n / 2, n) - n / 2
        squared = squared + (delta ** 2).reshape(-1, *[n if a == axis else 1 for a in range(dim)])
    return _kl_from_log_target(-squared / (2 * sigma ** 2), log_prob)


@dataclass
class PoseTarget:
    """Ground truth of a pair: ``fixed(p) = moving(scale * rotation @ p + translation)``.

    Attributes:
        rotation: ``(batch, 3, 3)``.
        scale: ``(batch,)``, positive.
        translation: ``(batch, 3)`` voxels ``(x, y, z)``.
    """

    rotation: Tensor
    scale: Tensor
    translation: Tensor

    def __post_init__(self) -> None:
        """Check the shapes; on the CPU also that the values are finite and the scales positive. Values on another
        device are not read (no synchronisation at every training step).

        Raises:
            InputError: a value that is not a tensor, a shape that is not as above, or a bad value on the CPU.
        """
        for name, tail in {"rotation": (3, 3), "scale": (), "translation": (3,)}.items():
            value = getattr(self, name)
            expected = f"a tensor of shape {('batch', *tail)}".replace("'", "")
            if not isinstance(value, Tensor):
                raise InputError(f"target {name} is {shown(value)}; expected {expected}")
            if tuple(value.shape[1:]) != tail or value.dim() != 1 + len(tail):
                raise InputError(f"target {name} has shape {tuple(value.shape)}; expected {expected}")
            if value.shape[0] == 0:
                raise InputError(f"target {name} holds no poses (shape {tuple(value.shape)}); expected at least one")
            if value.shape[0] != self.rotation.shape[0]:
                raise InputError(f"target {name} has shape {tuple(value.shape)}; expected a batch of "
                                 f"{self.rotation.shape[0]}, as the rotation {tuple(self.rotation.shape)}")
            if value.device.type == "cpu" and not torch.isfinite(value).all():
                raise InputError(f"target {name} holds NaN or Inf values")
        if self.scale.device.type == "cpu" and not (self.scale > 0).all():
            index = int((self.scale <= 0).nonzero()[0])
            raise InputError(f"target scale[{index}] is {self.scale[index].item()!r}; expected a scale > 0")


def pose_loss(result: SolveResult, target: PoseTarget, weights: LossWeights | None = None, *,
              translation: TranslationEstimate | None = None, compensation: Tensor | None = None
              ) -> dict[str, Tensor]:
    """The six DPCN++ terms and their weighted sum for a batch solved with ``refine=False``.

    Args:
        result: from :func:`dpcn_med.solver.solve` (soft arg-max, so the L1 terms carry gradients).
        target: the true pose.
        weights: term weights and target widths.
        translation: a translation stage measured outside ``result`` (the learned model runs it on its own
            features); defaults to ``result.translation_estimate``.
        compensation: ``(batch, 3, 3)`` the ``scale * rotation`` that compensated the moving volume before that
            stage; defaults to ``result``'s estimate.

    Returns:
        ``{"rotation_kl", "rotation_l1", "translation_kl", "translation_l1", "scale_kl", "scale_l1", "total"}``, each
        a scalar (batch mean). The rotation L1 is the geodesic angle (wrap-safe); the scale terms compare ``log``
        scales (zero in rigid mode); the translation terms compare the stage's own shift with ``A^-1 t``, ``A`` the
        estimated ``scale * rotation`` (detached) that compensated the moving volume before the stage: the shift
        that brings the true ``t`` back, in the frame the stage actually measured in (``(scale R)^-1 t`` once the
        rotation and scale are right).
    """
    weights = weights or LossWeights()
    terms = {
        "rotation_kl": rotation_kl(result.rotation_log_prob, target.rotation, weights.rotation_sigma,
                                   with_twins=weights.rotation_twins),
        "rotation_l1": geodesic_distance(result.rotation, target.rotation.to(result.rotation.dtype)),
    }
    linear = (result.scale[:, None, None] * result.rotation if compensation is None else compensation).detach()
    # solve_ex: solve's check for singular input is a host sync on CUDA at every training step.
    true_shift = torch.linalg.solve_ex(linear, target.translation[..., None].to(linear.dtype)).result[..., 0]
    estimate = result.translation_estimate if translation is None else translation
    terms["translation_kl"] = shift_kl(estimate.peak.log_prob, true_shift, weights.shift_sigma)
    terms["translation_l1"] = (estimate.shift - true_shift).abs().sum(-1)
    if result.scale_estimate is not None:
        stage = result.scale_estimate
        true_lag = -torch.log(target.scale.to(result.scale.dtype)) / stage.bin
        terms["scale_kl"] = shift_kl(stage.peak.log_prob, true_lag[:, None], weights.shift_sigma, periodic=(False,))
        terms["scale_l1"] = (torch.log(result.scale) - torch.log(target.scale.to(result.scale.dtype))).abs()
    else:
        zero = result.scale.new_zeros(result.scale.shape)
        terms["scale_kl"], terms["scale_l1"] = zero, zero
    terms = {name: value.mean() for name, value in terms.items()}
    terms["total"] = sum(getattr(weights, name) * value for name, value in terms.items())
    return terms
