"""Simulated modalities with exact ground truth: random contrast, bias field, blur, thick slices and noise.

Every function maps a batch of volumes ``(B, 1, D, H, W)`` (torch order z, y, x; intensities in ``[0, 1]``, 0 the
background) to a batch of the same shape, device and dtype, and never moves anything: two draws from one volume are two
modalities in one frame, so a pair built from them keeps the exact ground truth of its pose. Each random function
takes a ``torch.Generator`` on any device (draws are moved to the data's device): the same seed gives the same output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from dpcn_med.arguments import check_flag, check_integer, check_pair, check_real
from dpcn_med.synth._common import check_volumes, integers, normal, uniform

MAX_BIAS_STRENGTH = 80.0
"""Largest bias strength: the field's extremes ``exp(+-80)`` stay normal float32 numbers (``exp(89)`` overflows, and
the background's ``0 * inf`` is NaN)."""


MAX_KNOTS = 64
"""Most control points of an intensity map: more is noise on the intensities, and ``B x knots`` draws."""

MAX_BIAS_ORDER = 10
"""Highest degree of a bias field: a coil's field is smooth, and ``(order + 1)^3`` coefficients are drawn."""

MAX_SIGMA = 8.0
"""Largest blur sigma, voxels: the kernel reaches ``3 sigma`` (time grows with it; docs/design_notes/synth.md)."""

MAX_NOISE_STD = 1.0
"""Largest noise standard deviation: on intensities in ``[0, 1]`` more is pure noise (docs/design_notes/synth.md)."""


@dataclass(frozen=True)
class ContrastConfig:
    """Ranges of a random modality (:func:`random_modality`); the defaults of every function in this module.

    Attributes:
        knots: control points of the random intensity map, equally spaced over ``[0, 1]``; 2 to :data:`MAX_KNOTS`.
        monotonic: increasing intensity maps only (same contrast family) instead of any map (bone bright on one,
            dark on the other).
        bias_strength: largest ``|log|`` of the multiplicative bias field, at most :data:`MAX_BIAS_STRENGTH`.
        bias_order: highest total degree of the field's Legendre polynomials, 1 to :data:`MAX_BIAS_ORDER`.
        sigma_range: Gaussian blur, voxels, at most :data:`MAX_SIGMA`.
        factor_range: slice thickness, in voxels, of the resolution loss along one axis (1 = none).
        noise_std_range: standard deviation of the additive noise (intensities in ``[0, 1]``), at most
            :data:`MAX_NOISE_STD`.
        rician: magnitude (Rician) noise as in MR, instead of Gaussian.
    """

    knots: int = 6
    monotonic: bool = False
    bias_strength: float = 0.3
    bias_order: int = 3
    sigma_range: tuple[float, float] = (0.0, 1.5)
    factor_range: tuple[float, float] = (1.0, 3.0)
    noise_std_range: tuple[float, float] = (0.0, 0.05)
    rician: bool = True

    def __post_init__(self) -> None:
        """Refuse what would make NaN or blank volumes, naming the field.

        Raises:
            InputError: a value out of its range.
        """
        check_integer("knots", self.knots, minimum=2, maximum=MAX_KNOTS)
        check_flag("monotonic", self.monotonic)
        check_real("bias_strength", self.bias_strength, minimum=0.0, maximum=MAX_BIAS_STRENGTH)
        check_integer("bias_order", self.bias_order, minimum=1, maximum=MAX_BIAS_ORDER)
        check_pair("sigma_range", self.sigma_range, minimum=0.0, maximum=MAX_SIGMA, equal=True)
        check_pair("factor_range", self.factor_range, minimum=1.0, equal=True)
        check_pair("noise_std_range", self.noise_std_range, minimum=0.0, maximum=MAX_NOISE_STD, equal=True)
        check_flag("rician", self.rician)


def _per_sample(values: Tensor) -> Tensor:
    """``(B,)`` -> ``(B, 1, 1, 1, 1)``, to broadcast over a batch of volumes."""
    return values.reshape(-1, 1, 1, 1, 1)


def random_intensity_map(volume: Tensor, generator: torch.Generator, *, knots: int = ContrastConfig.knots,
                         monotonic: bool = ContrastConfig.monotonic) -> Tensor:
    """A random piecewise-linear map of ``[0, 1]`` onto itself, one per volume; the background stays 0.

    The map passes through ``knots`` control points equally spaced in the input, with outputs uniform in ``[0, 1]``
    scaled so that the brightest is 1. Non-monotonic maps reorder tissues, as CT and MR do (bone bright on one, dark on
    the other).

    Args:
        volume: ``(B, 1, D, H, W)`` intensities in ``[0, 1]`` (values outside are clipped), exactly 0 in the background.
        generator: source of randomness.
        knots: number of control points, 2 to :data:`MAX_KNOTS`.
        monotonic: sort the control points' outputs, so the map is increasing.

    Returns:
        ``(B, 1, D, H, W)`` in ``[0, 1]``, 0 exactly where ``volume`` is 0.
    """
    check_volumes("volume", volume)
    return _intensity_map(volume, generator, check_integer("knots", knots, minimum=2, maximum=MAX_KNOTS),
                          check_flag("monotonic", monotonic))


def _intensity_map(volume: Tensor, generator: torch.Generator, knots: int, monotonic: bool) -> Tensor:
    """:func:`random_intensity_map` of checked arguments."""
    outputs = uniform(generator, (volume.shape[0], knots), 0.0, 1.0, like=volume)
    if monotonic:
        outputs = outputs.sort(-1).values
    outputs = outputs / outputs.amax(-1, keepdim=True)
    position = volume.flatten(1).clamp(0.0, 1.0) * (knots - 1)
    left = position.floor().clamp(max=knots - 2)
    weight = position - left
    index = left.long()
    mapped = torch.gather(outputs, 1, index) * (1 - weight) + torch.gather(outputs, 1, index + 1) * weight
    return torch.where(volume.flatten(1) == 0, 0.0, mapped).view_as(volume)


def _legendre(ticks: Tensor, order: int) -> Tensor:
    """Legendre polynomials ``P_0 .. P_order`` at ``ticks`` ``(n,)`` -> ``(order + 1, n)`` (Bonnet's recursion)."""
    rows = [torch.ones_like(ticks), ticks]
    for degree in range(1, order):
        rows.append(((2 * degree + 1) * ticks * rows[-1] - degree * rows[-2]) / (degree + 1))
    return torch.stack(rows[:order + 1])


def bias_field(volume: Tensor, generator: torch.Generator, *, strength: float = ContrastConfig.bias_strength,
               order: int = ContrastConfig.bias_order) -> Tensor:
    """Multiply each volume by a smooth random field, as MR coil sensitivity does.

    The field is ``exp(s * q / max |q|)``: ``q`` a random combination (coefficients uniform in ``[-1, 1]``) of the
    products ``P_i(z) P_j(y) P_k(x)`` of Legendre polynomials on ``[-1, 1]`` with ``0 < i + j + k <= order`` (MONAI's
    ``RandBiasField`` model), ``s`` uniform in ``[0, strength]``. So it lies in ``[exp(-strength), exp(strength)]``.

    Args:
        volume: ``(B, 1, D, H, W)``.
        generator: source of randomness.
        strength: largest ``|log|`` of the field, in ``[0, MAX_BIAS_STRENGTH]``.
        order: highest total degree, 1 to :data:`MAX_BIAS_ORDER`.

    Returns:
        ``(B, 1, D, H, W)`` ``volume * field``: the background stays 0, the foreground may exceed 1.
    """
    # Written out rather than MONAI's RandBiasField: that one draws from numpy, one volume at a time, on the host.
    check_volumes("volume", volume)
    return _bias(volume, generator, check_real("strength", strength, minimum=0.0, maximum=MAX_BIAS_STRENGTH),
                 check_integer("order", order, minimum=1, maximum=MAX_BIAS_ORDER))


def _bias(volume: Tensor, generator: torch.Generator, strength: float, order: int) -> Tensor:
    """:func:`bias_field` of checked arguments."""
    batch = volume.shape[0]
    size = order + 1
    degree = torch.arange(size, device=volume.device)
    within = (degree[:, None, None] + degree[None, :, None] + degree[None, None, :]) <= order
    within[0, 0, 0] = False  # a constant gain is not a bias
    coefficients = uniform(generator, (batch, size, size, size), -1.0, 1.0, like=volume) * within
    axes = [_legendre(torch.linspace(-1.0, 1.0, n, device=volume.device, dtype=volume.dtype), order)
            for n in volume.shape[2:]]
    log_field = torch.einsum("bijk,iz,jy,kx->bzyx", coefficients, *axes)
    peak = log_field.flatten(1).abs().amax(-1).clamp_min(torch.finfo(volume.dtype).tiny)
    amplitude = uniform(generator, (batch,), 0.0, strength, like=volume)
    return volume * torch.exp((amplitude / peak).reshape(-1, 1, 1, 1) * log_field)[:, None]


def _gaussian_blur(volume: Tensor, sigma: Tensor) -> Tensor:
    """Separable Gaussian blur with one ``sigma`` (voxels) per volume: ``(B, 1, D, H, W)``, ``(B,)``; zero padding."""
    # One grouped convolution blurs every volume with its own kernel: MONAI's GaussianFilter takes one sigma per call.
    batch = volume.shape[0]
    radius = max(1, math.ceil(3.0 * float(sigma.max())))
    ticks = torch.arange(-radius, radius + 1, device=volume.device, dtype=volume.dtype)
    # A vanishing sigma gives a unit impulse, the identity.
    kernel = torch.exp(-0.5 * (ticks / sigma.clamp_min(1e-3)[:, None]) ** 2)
    kernel = kernel / kernel.sum(-1, keepdim=True)
    out = volume.reshape(1, batch, *volume.shape[2:])
    for axis in range(3):
        shape, padding = [1, 1, 1], [0, 0, 0]
        shape[axis], padding[axis] = 2 * radius + 1, radius
        out = F.conv3d(out, kernel.reshape(batch, 1, *shape), padding=padding, groups=batch)
    return out.reshape(volume.shape)


def blur(volume: Tensor, generator: torch.Generator, *,
         sigma_range: tuple[float, float] = ContrastConfig.sigma_range) -> Tensor:
    """Gaussian blur (a scanner's point-spread function) with a random sigma per volume.

    Args:
        volume: ``(B, 1, D, H, W)``.
        generator: source of randomness.
        sigma_range: sigma in voxels, uniform in this interval inside ``[0, MAX_SIGMA]``.

    Returns:
        ``(B, 1, D, H, W)``; zero padding, so the background far from the foreground stays 0.
    """
    check_volumes("volume", volume)
    check_pair("sigma_range", sigma_range, minimum=0.0, maximum=MAX_SIGMA, equal=True)
    return _blur(volume, generator, sigma_range)


def _blur(volume: Tensor, generator: torch.Generator, sigma_range: tuple[float, float]) -> Tensor:
    """:func:`blur` of checked arguments."""
    return _gaussian_blur(volume, uniform(generator, (volume.shape[0],), *sigma_range, like=volume))


def resolution_loss(volume: Tensor, generator: torch.Generator, *,
                    factor_range: tuple[float, float] = ContrastConfig.factor_range) -> Tensor:
    """Thick slices: average along one random axis into slices a random factor thicker, then interpolate back.

    Args:
        volume: ``(B, 1, D, H, W)``.
        generator: source of randomness.
        factor_range: slice thickness in voxels, uniform in this interval (lower bound at least 1).

    Returns:
        ``(B, 1, D, H, W)``; unchanged along the two other axes.
    """
    check_volumes("volume", volume)
    check_pair("factor_range", factor_range, minimum=1.0, equal=True)
    return _thick_slices(volume, generator, factor_range)


def _thick_slices(volume: Tensor, generator: torch.Generator, factor_range: tuple[float, float]) -> Tensor:
    """:func:`resolution_loss` of checked arguments."""
    batch = volume.shape[0]
    factors = uniform(generator, (batch,), *factor_range, like=volume).tolist()
    axes = integers(generator, 3, batch)
    # One volume at a time: the thick grid's shape depends on the volume's axis and factor.
    thick = []
    for one, factor, axis in zip(volume.split(1), factors, axes):
        sizes = list(one.shape[2:])
        coarse = sizes.copy()
        coarse[axis] = max(1, round(sizes[axis] / factor))
        slices = F.interpolate(one, size=coarse, mode="area")
        thick.append(F.interpolate(slices, size=sizes, mode="trilinear", align_corners=False))
    return torch.cat(thick)


def noise(volume: Tensor, generator: torch.Generator, *,
          std_range: tuple[float, float] = ContrastConfig.noise_std_range,
          rician: bool = ContrastConfig.rician) -> Tensor:
    """Additive white noise with a random standard deviation per volume.

    Rician noise is the magnitude of a complex signal with Gaussian noise on both channels,
    ``sqrt((v + n_1)^2 + n_2^2)``, as in MR magnitude images: positive, and the background becomes Rayleigh noise.

    Args:
        volume: ``(B, 1, D, H, W)``.
        generator: source of randomness.
        std_range: standard deviation of each Gaussian channel, uniform in this interval inside
            ``[0, MAX_NOISE_STD]``.
        rician: Rician (True) or Gaussian noise.

    Returns:
        ``(B, 1, D, H, W)``, not clipped.
    """
    # Written out rather than MONAI's RandGaussianNoise / RandRicianNoise: those draw from numpy on the host.
    check_volumes("volume", volume)
    check_pair("std_range", std_range, minimum=0.0, maximum=MAX_NOISE_STD, equal=True)
    return _noise(volume, generator, std_range, check_flag("rician", rician))


def _noise(volume: Tensor, generator: torch.Generator, std_range: tuple[float, float], rician: bool) -> Tensor:
    """:func:`noise` of checked arguments."""
    std = _per_sample(uniform(generator, (volume.shape[0],), *std_range, like=volume))
    real = volume + std * normal(generator, tuple(volume.shape), like=volume)
    if not rician:
        return real
    return torch.hypot(real, std * normal(generator, tuple(volume.shape), like=volume))


def random_modality(volume: Tensor, generator: torch.Generator, config: ContrastConfig = ContrastConfig()) -> Tensor:
    """A random simulated modality of the same anatomy, in the same frame.

    The chain :func:`random_intensity_map`, :func:`bias_field`, rescale so the brightest voxel is 1, :func:`blur`,
    :func:`resolution_loss`, :func:`noise`, clip to ``[0, 1]``. The background is 0 until the noise (with Rician noise
    it becomes Rayleigh noise, as in an MR magnitude image).

    Args:
        volume: ``(B, 1, D, H, W)`` intensities in ``[0, 1]``, 0 in the background.
        generator: source of randomness.
        config: the ranges of every step.

    Returns:
        ``(B, 1, D, H, W)`` in ``[0, 1]``, same device and dtype.
    """
    # The volume is checked once, the config on its making: each step's own check of a finite input (a host sync on
    # CUDA) repeated five times a call, ten a pair.
    check_volumes("volume", volume)
    mapped = _intensity_map(volume, generator, config.knots, config.monotonic)
    biased = _bias(mapped, generator, config.bias_strength, config.bias_order)
    peak = biased.flatten(1).amax(-1).clamp_min(torch.finfo(volume.dtype).tiny)
    blurred = _blur(biased / _per_sample(peak), generator, config.sigma_range)
    thick = _thick_slices(blurred, generator, config.factor_range)
    return _noise(thick, generator, config.noise_std_range, config.rician).clamp(0.0, 1.0)
