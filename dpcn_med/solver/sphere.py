"""Step 2 of DPC: radial aggregation of a magnitude spectrum onto the SOFT sphere grid (scale invariance).

The grid is SOFT's variant of Driscoll-Healy (ducc0's "F1"): ``theta_j = pi (2j + 1) / (4B)``,
``phi_k = 2 pi k / (2B)``, ``j, k < 2B``; it excludes the poles, and the quadrature weights below belong to it.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from dpcn_med.geometry import sample

# log |G| is floored at LOG_FLOOR * mean |G|: the log of the spectrum's near-empty corners would otherwise be noise
# with an unbounded negative range.
LOG_FLOOR = 1e-3


def even_degrees(bandwidth: int) -> tuple[int, ...]:
    """Degrees the rotation stage uses: even ``l`` from 2 to ``B - 1``.

    ``|FFT|`` is even, so its sphere carries only even degrees; degree 0 is the mean, which dominates the correlation
    and carries no rotation.
    """
    return tuple(range(2, bandwidth, 2))


def soft_colatitude(index: Tensor, bandwidth: int) -> Tensor:
    """``pi (2j + 1) / 4B``: the SOFT colatitudes ``theta_j``, which are also the Euler grid's betas (any ``j``, even
    fractional)."""
    return math.pi * (2 * index + 1) / (4 * bandwidth)


def sphere_angles(bandwidth: int, *, device: torch.device | None = None, dtype: torch.dtype | None = None
                  ) -> tuple[Tensor, Tensor]:
    """``(theta, phi)`` of the SOFT grid, each ``(2B,)`` radians."""
    index = torch.arange(2 * bandwidth, device=device, dtype=dtype)
    return soft_colatitude(index, bandwidth), 2 * math.pi * index / (2 * bandwidth)


def sphere_mean_weights(weights: Tensor, columns: int) -> Tensor:
    """Per-cell weights ``(2B, 1)`` of the mean over the sphere: ``sum(values * w)`` is the average of ``values``."""
    return weights[:, None] / (weights.sum() * columns)


def floored_log(values: Tensor, magnitude: Tensor) -> Tensor:
    """``log`` of magnitudes ``values (batch, ...)`` sampled from ``magnitude (batch, ...)``, floored
    (:data:`LOG_FLOOR`)."""
    floor = LOG_FLOOR * magnitude.flatten(1).mean(-1) + torch.finfo(magnitude.dtype).tiny
    return torch.log(values + floor.reshape(-1, *([1] * (values.dim() - 1))))


def sphere_directions(bandwidth: int, *, device: torch.device | None = None, dtype: torch.dtype | None = None
                      ) -> Tensor:
    """Unit vectors ``(x, y, z)`` of the grid: ``(2B, 2B, 3)`` indexed ``[theta, phi]``."""
    theta, phi = sphere_angles(bandwidth, device=device, dtype=dtype)
    theta, phi = theta[:, None], phi[None, :]
    return torch.stack(torch.broadcast_tensors(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()), -1)


def quadrature_weights(bandwidth: int, *, device: torch.device | None = None, dtype: torch.dtype = torch.float64
                       ) -> Tensor:
    """SOFT quadrature weights in ``theta``: ``(2B,)``, summing to 2 (the integral of ``sin theta``).

    ``w_j = (2 / B) sin(theta_j) sum_{k < B} sin((2k + 1) theta_j) / (2k + 1)`` (Kostelec and Rockmore 2008, eq. 2.13;
    exact for band-limit ``B`` together with the ``2 pi / 2B`` step in ``phi``).
    """
    theta, _ = sphere_angles(bandwidth, device=device, dtype=torch.float64)
    odd = 2 * torch.arange(bandwidth, device=device, dtype=torch.float64) + 1
    weights = (2.0 / bandwidth) * theta.sin() * ((odd * theta[:, None]).sin() / odd).sum(-1)
    return weights.to(dtype)


def log_radii(size: int, band: tuple[float, float], count: int, *, device: torch.device | None = None,
              dtype: torch.dtype | None = None) -> Tensor:
    """``count`` radii evenly spaced in ``log r`` over ``band`` (fractions of the Nyquist radius ``size / 2``).

    Returns:
        ``(R,)`` radii in frequency cells.
    """
    nyquist = size / 2
    return torch.linspace(math.log(band[0] * nyquist), math.log(band[1] * nyquist), count, device=device,
                          dtype=dtype).exp()


def log_radius_step(band: tuple[float, float], count: int) -> float:
    """The ``log r`` spacing of :func:`log_radii` (computed on the host: no device synchronisation)."""
    return math.log(band[1] / band[0]) / (count - 1)


def radial_profiles(magnitude: Tensor, directions: Tensor, radii: Tensor, *, log_magnitude: bool = True) -> Tensor:
    """Magnitude spectrum sampled along rays: ``f(|G|(r u))`` for every direction ``u`` and radius ``r``.

    Args:
        magnitude: ``(batch, N, N, N)`` ``fftshift``-ed magnitude spectrum.
        directions: ``(batch, *S, 3)`` unit vectors ``(x, y, z)``.
        radii: ``(R,)`` radii in frequency cells (cycles per grid), as from :func:`log_radii`.
        log_magnitude: return ``log |G|`` (floored at a small fraction of the mean) rather than ``|G|``.

    Returns:
        ``(batch, *S, R)``, trilinear interpolation.
    """
    points = directions[..., None, :] * radii[:, None]  # (batch, *S, R, 3)
    values = sample(magnitude[:, None], points)[:, 0]
    if not log_magnitude:
        return values
    return floored_log(values, magnitude)


def to_sphere(magnitude: Tensor, directions: Tensor, radii: Tensor, *, log_magnitude: bool = True) -> Tensor:
    """Radial aggregation of a magnitude spectrum onto directions: ``s(u) = mean_r f(|G|(r u))``.

    Args:
        magnitude: ``(batch, N, N, N)`` ``fftshift``-ed magnitude spectrum.
        directions: ``(batch, *S, 3)`` unit vectors (for instance :func:`sphere_directions`, or rotated ones).
        radii: ``(R,)`` log-spaced radii: the band-pass.
        log_magnitude: aggregate ``log |G|`` (True) or ``|G|``.

    Returns:
        ``(batch, *S)`` values on the sphere.

    Notes:
        With ``|G1(k)| = mu^-3 |G2(R k / mu)|``, ``log |G1|`` along ``u`` is ``log |G2|`` along ``R u`` shifted by
        ``log mu`` in ``log r`` and offset by ``-3 log mu``; averaging over log-spaced radii therefore makes
        ``s1(u) = s2(R u)`` up to a constant and the ends of the band, which normalisation removes.
    """
    return radial_profiles(magnitude, directions, radii, log_magnitude=log_magnitude).mean(-1)


def normalize_sphere(sphere: Tensor, weights: Tensor) -> Tensor:
    """Zero weighted mean, unit weighted norm: ``(batch, 2B, 2B)`` -> same. A constant sphere becomes zeros, not NaN.

    Args:
        sphere: ``(batch, 2B, 2B)`` values on the grid, ``[theta, phi]``.
        weights: ``(2B,)`` :func:`quadrature_weights`.
    """
    w = sphere_mean_weights(weights, sphere.shape[-1])
    centred = sphere - (sphere * w).sum((-2, -1), keepdim=True)
    root_w = w.sqrt()  # norms through vector_norm: its gradient at zero is 0, sqrt's is NaN
    norm = torch.linalg.vector_norm(centred * root_w, dim=(-2, -1), keepdim=True)
    # What centring leaves of a constant sphere is rounding, a few eps of its values: a floor of sqrt(eps) times
    # the sphere's own size maps it to ~sqrt(eps), not to unit-norm noise. A real sphere's centred norm is far
    # above the floor, and the correlation's own normalisation cancels the scale either way.
    floor = torch.finfo(sphere.dtype).eps ** 0.5 * torch.linalg.vector_norm(sphere * root_w, dim=(-2, -1),
                                                                             keepdim=True)
    return centred / (norm + floor + torch.finfo(sphere.dtype).tiny)


def sample_sphere(sphere: Tensor, directions: Tensor) -> Tensor:
    """Bilinear interpolation of grid values at arbitrary directions.

    Args:
        sphere: ``(batch, 2b, 2b)`` values on the SOFT grid of bandwidth ``b``, ``[theta, phi]``.
        directions: ``(batch, *S, 3)`` unit vectors ``(x, y, z)`` (not renormalised).

    Returns:
        ``(batch, *S)``.

    Notes:
        ``phi`` wraps; beyond the first and last ``theta`` rows the grid continues over the pole, where the row is
        the same row shifted by half a turn in ``phi``, so the padding below makes the interpolation seamless.
    """
    rows, cols = sphere.shape[-2:]
    half = cols // 2
    north = sphere[:, :1].roll(half, dims=-1)
    south = sphere[:, -1:].roll(half, dims=-1)
    padded = torch.cat([north, sphere, south], dim=1)
    padded = torch.cat([padded[..., -1:], padded, padded[..., :1]], dim=-1)  # (batch, 2b + 2, 2b + 2)
    x, y, z = directions.unbind(-1)
    theta = torch.acos(z.clamp(-1.0, 1.0))
    phi = torch.remainder(torch.atan2(y, x), 2 * math.pi)
    row = theta * rows / math.pi - 0.5 + 1.0  # +1 for the padding row
    col = phi * cols / (2 * math.pi) + 1.0
    grid = torch.stack([2 * col / (cols + 1) - 1, 2 * row / (rows + 1) - 1], -1)
    batch, sample_shape = directions.shape[0], directions.shape[1:-1]
    values = F.grid_sample(padded[:, None], grid.reshape(batch, -1, 1, 2), mode="bilinear",
                           padding_mode="border", align_corners=True)
    return values.reshape(batch, *sample_shape)
