"""Step 4 of DPC: scale by a 1-D correlation over log-radius of the rotation-compensated magnitude spectra."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dpcn_med.solver.phase_correlation import SoftPeak, correlation_surface, refine_peak, soft_argmax
from dpcn_med.solver.sphere import (
    log_radii,
    log_radius_step,
    quadrature_weights,
    radial_profiles,
    sphere_directions,
)


@dataclass
class ScaleEstimate:
    """Result of :func:`log_polar_scale`.

    Attributes:
        scale: ``(batch, K)`` ``mu`` of ``fixed(p) ~ moving(mu R p + t)`` for each of ``K`` rotations.
        peak: the soft arg-max over log-radius lags, batch ``B * K`` (in bins; ``log mu = -shift * bin``).
        bin: ``log r`` step of one lag, so the KL loss can place the ground truth on the lag grid.
        height: ``(batch, K)`` normalised correlation at the chosen lag, in ``[-1, 1]``.
    """

    scale: Tensor
    peak: SoftPeak
    bin: float
    height: Tensor


def detrend(profiles: Tensor) -> Tensor:
    """Remove each profile's least-squares line over its last axis: ``(..., R)`` -> same.

    Spectra fall off roughly as a power of the radius, a line in ``log r``; left in, that ramp dominates the
    correlation and its peak stays at zero lag whatever the scale.
    """
    count = profiles.shape[-1]
    x = torch.linspace(-1.0, 1.0, count, device=profiles.device, dtype=profiles.dtype)
    centred = profiles - profiles.mean(-1, keepdim=True)
    slope = (centred * x).sum(-1, keepdim=True) / (x * x).sum()
    return centred - slope * x


def log_polar_scale(fixed_magnitude: Tensor, moving_magnitude: Tensor, rotation: Tensor, band: tuple[float, float],
                    samples: int, temperature: Tensor | float, *, directions_bandwidth: int, max_scale: float,
                    refine: bool, upsample: int) -> ScaleEstimate:
    """Scale between two magnitude spectra, given the rotation.

    Log-magnitude profiles along directions ``u`` of the fixed spectrum and ``R u`` of the moving one are detrended,
    tapered, zero-padded and cross-correlated over ``log r``; the correlations of all directions are summed
    (quadrature-weighted) before the arg-max, so every direction votes for one shift.

    Args:
        fixed_magnitude: ``(batch, N, N, N)`` ``fftshift``-ed magnitude spectrum of the fixed volume.
        moving_magnitude: ``(batch, N, N, N)`` same for the moving volume.
        rotation: ``(batch, K, 3, 3)`` candidate rotations of ``fixed(p) ~ moving(mu R p + t)``.
        band: radii of the profiles, fractions of the Nyquist radius.
        samples: log-spaced samples per profile.
        temperature: softmax temperature over lags.
        directions_bandwidth: the profiles use the SOFT grid of this bandwidth (``4 b^2`` directions).
        max_scale: only scales in ``[1 / max_scale, max_scale]`` are considered.
        refine: arg-max plus an upsampled-DFT refinement (True) or the differentiable soft arg-max (False).
        upsample: refinement factor.

    Returns:
        A :class:`ScaleEstimate`.

    Notes:
        ``log |G_fixed|(e^rho u) = log |G_moving|(e^(rho - log mu) R u) - 3 log mu``: after detrending, the fixed
        profile is the moving one shifted by ``log mu``.
    """
    batch, count = rotation.shape[:2]
    directions = sphere_directions(directions_bandwidth, device=rotation.device, dtype=rotation.dtype)
    moving_dirs = torch.einsum("bkij,...j->bk...i", rotation, directions)  # (batch, K, 2b, 2b, 3)
    radii = log_radii(fixed_magnitude.shape[-1], band, samples, device=rotation.device, dtype=rotation.dtype)
    taper = torch.hann_window(samples, periodic=False, device=radii.device, dtype=radii.dtype)
    fixed = detrend(radial_profiles(fixed_magnitude, directions.expand(batch, *directions.shape), radii)) * taper
    moving = detrend(radial_profiles(moving_magnitude, moving_dirs, radii)) * taper
    fixed_spec = torch.fft.rfft(fixed, n=2 * samples, dim=-1)[:, None]  # (batch, 1, 2b, 2b, R + 1)
    moving_spec = torch.fft.rfft(moving, n=2 * samples, dim=-1)  # (batch, K, 2b, 2b, R + 1)
    weights = quadrature_weights(directions_bandwidth, device=radii.device, dtype=radii.dtype)[:, None]
    spectrum = (moving_spec * fixed_spec.conj() * weights[..., None]).sum((2, 3)).flatten(0, 1)  # (batch K, R + 1)
    # norms through vector_norm: its gradient at zero (an empty volume's profiles) is 0, sqrt's is NaN
    root_w = weights.sqrt()[..., None]
    norms = (torch.linalg.vector_norm(fixed * root_w, dim=(-3, -2, -1))[:, None]
             * torch.linalg.vector_norm(moving * root_w, dim=(-3, -2, -1)))  # (batch, K)
    spectrum = spectrum / (norms.flatten() + torch.finfo(norms.dtype).eps)[:, None]
    sizes = (2 * samples,)
    step = log_radius_step(band, samples)
    reach = min(samples - 1, math.ceil(math.log(max_scale) / step))  # lags of plausible scales only
    surface = correlation_surface(spectrum, sizes)[:, samples - reach:samples + reach + 1]
    peak = soft_argmax(surface, temperature, dim=1, periodic=(False,))
    if refine:
        shift, height = refine_peak(spectrum, peak.index, sizes, upsample=upsample)
    else:
        shift, height = peak.shift, surface.max(-1).values
    # The window ends at whole lags and the sub-grid peak may lie past its last one: 1.2 gave up to 1.30.
    scale = torch.exp(-shift[:, 0] * step).clamp(1 / max_scale, max_scale)
    return ScaleEstimate(scale=scale.reshape(batch, count), peak=peak, bin=step, height=height.reshape(batch, count))
