"""Step 1 of DPC: the translation-invariant magnitude spectrum of an apodised volume."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dpcn_med.geometry import grid_centre


def spherical_window(sizes: tuple[int, ...], taper: float, *, device: torch.device | None = None,
                     dtype: torch.dtype | None = None) -> Tensor:
    """Radial window: one inside, a raised-cosine taper over the outer ``taper`` fraction, zero past the inscribed ball.

    Args:
        sizes: grid shape in torch order, ``(D, H, W)`` or ``(H, W)``.
        taper: fraction of the radius ``min(sizes) / 2 - 1`` over which the window falls from 1 to 0.

    Returns:
        ``sizes``-shaped window, centred at the grid centre.
    """
    radius = min(sizes) / 2 - 1
    squared = sum(  # broadcast sum of per-axis squares: much faster than a norm over a trailing axis of 3
        (((torch.arange(n, device=device, dtype=dtype) - grid_centre(n)) / radius) ** 2).reshape(
            [-1 if a == axis else 1 for a in range(len(sizes))])
        for axis, n in enumerate(sizes))
    distance = squared.sqrt()
    inner = 1.0 - taper
    ramp = ((distance - inner) / max(taper, 1e-12)).clamp(0.0, 1.0)
    return 0.5 * (1.0 + torch.cos(math.pi * ramp))


def apodize(volume: Tensor, dim: int, taper: float) -> Tensor:
    """Remove the window-weighted mean, then multiply by :func:`spherical_window`.

    Without the window the box edges put an axis-aligned cross into ``|FFT|`` that does not rotate with the object
    and pulls the rotation estimate towards the identity; without the mean removal a constant volume would leave the
    window's own spectrum, which correlates perfectly with itself.

    Args:
        volume: ``(batch, *S)`` real, ``S`` the last ``dim`` axes.
        dim: 2 or 3.
        taper: see :func:`spherical_window`.

    Returns:
        ``(batch, *S)``; exactly zero for a constant volume.
    """
    window = spherical_window(tuple(volume.shape[-dim:]), taper, device=volume.device, dtype=volume.dtype)
    axes = tuple(range(-dim, 0))
    mean = (volume * window).sum(axes, keepdim=True) / window.sum()
    centred = volume - mean
    # A constant volume leaves only rounding noise, which whitening would amplify into a perfect self-match: zero it.
    level = volume.abs().amax(axes, keepdim=True)
    constant = centred.abs().amax(axes, keepdim=True) <= 16 * torch.finfo(volume.dtype).eps * level
    return torch.where(constant, torch.zeros_like(centred), centred) * window


def magnitude_spectrum(volume: Tensor, dim: int, taper: float) -> Tensor:
    """``|FFT|`` of the apodised volume, ``fftshift``-ed so that the zero frequency sits at the grid centre.

    Args:
        volume: ``(batch, *S)`` real.
        dim: 2 or 3.
        taper: see :func:`spherical_window`.

    Returns:
        ``(batch, *S)`` non-negative, invariant to translations of the content (up to the window).

    Notes:
        If ``g1(p) = g2(mu R p + t)`` then ``|G1(k)| = mu^-d |G2(R k / mu)|`` (frequency ``k`` in cycles per grid, from
        the centre): translation is gone, rotation and scale remain.
    """
    axes = tuple(range(-dim, 0))
    spectrum = torch.fft.fftn(apodize(volume, dim, taper), dim=axes)
    return torch.fft.fftshift(spectrum.abs(), dim=axes)
