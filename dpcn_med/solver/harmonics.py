"""Spherical harmonic transform on the SOFT grid (step 3 of DPC, first half).

Convention: ``Y_l^m(theta, phi)`` orthonormal with the Condon-Shortley phase, equal to
``scipy.special.sph_harm_y(l, m, theta, phi)``. Coefficients are stored densely as ``(batch, L, 2M + 1)`` for a list of
``L`` degrees, order ``m = -M..M`` at index ``m + M`` (``M`` the largest degree), zero where ``|m| > l``.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from dpcn_med.solver.sphere import quadrature_weights, sphere_angles
from dpcn_med.solver.wigner import legendre


@functools.lru_cache(maxsize=16)
def legendre_table(bandwidth: int, degrees: tuple[int, ...], device: torch.device, dtype: torch.dtype) -> Tensor:
    """Normalised associated Legendre functions on the grid: ``Y_l^m(theta_j, 0)``
    (:func:`dpcn_med.solver.wigner.legendre`).

    Args:
        bandwidth: ``B``; the grid has ``2B`` colatitudes.
        degrees: the ``L`` degrees ``l`` to tabulate.
        device: where the table lives; cached per ``(bandwidth, degrees, device, dtype)``.
        dtype: real dtype of the table.

    Returns:
        ``(L, 2M + 1, 2B)`` real, ``M = max(degrees)``, zero where ``|m| > l``.
    """
    theta, _ = sphere_angles(bandwidth, dtype=torch.float64)
    return legendre(degrees, theta).to(device=device, dtype=dtype)


def order_columns(top: int, columns: int, device: torch.device) -> Tensor:
    """Column of each order ``m = -top..top`` in a length-``columns`` FFT over ``phi``."""
    return torch.remainder(torch.arange(-top, top + 1, device=device), columns)


def sht(sphere: Tensor, degrees: tuple[int, ...]) -> Tensor:
    """Forward spherical harmonic transform by SOFT/Driscoll-Healy quadrature.

    Args:
        sphere: ``(batch, 2B, 2B)`` real values on the SOFT grid, ``[theta, phi]``.
        degrees: the degrees to compute, all below the bandwidth ``B``.

    Returns:
        ``(batch, L, 2M + 1)`` complex coefficients ``S_l^m = integral s conj(Y_l^m)``, exact for functions of
        band-limit ``B``.

    Notes:
        ``S_l^m = (2 pi / 2B) sum_j w_j Y_l^m(theta_j, 0) sum_k s(theta_j, phi_k) exp(-i m phi_k)``: an FFT over
        ``phi``, then a weighted sum over ``theta``.
    """
    bandwidth = sphere.shape[-1] // 2
    if max(degrees) >= bandwidth:
        raise ValueError(f"degrees up to {max(degrees)} need a bandwidth above it; the sphere has B = {bandwidth}")
    real = sphere.dtype
    table = legendre_table(bandwidth, tuple(degrees), sphere.device, real)
    weights = quadrature_weights(bandwidth, device=sphere.device, dtype=real) * (math.pi / bandwidth)
    fourier = torch.fft.fft(sphere, dim=-1)[..., order_columns(max(degrees), sphere.shape[-1], sphere.device)]
    weighted = torch.view_as_real(fourier * weights[:, None])  # (batch, 2B, 2M + 1, 2)
    coeffs = torch.einsum("lmj,bjmc->blmc", table, weighted)
    return torch.view_as_complex(coeffs.contiguous())


def isht(coeffs: Tensor, degrees: tuple[int, ...], bandwidth: int) -> Tensor:
    """Inverse transform: ``s(theta_j, phi_k) = sum_l sum_m S_l^m Y_l^m(theta_j, phi_k)``, real part.

    Args:
        coeffs: ``(batch, L, 2M + 1)`` complex, as from :func:`sht`.
        degrees: the ``L`` degrees of ``coeffs``.
        bandwidth: ``B`` of the output grid.

    Returns:
        ``(batch, 2B, 2B)`` real values on the SOFT grid.
    """
    real = coeffs.real.dtype
    table = legendre_table(bandwidth, tuple(degrees), coeffs.device, real)
    per_order = torch.einsum("lmj,blmc->bjmc", table, torch.view_as_real(coeffs))
    columns = 2 * bandwidth
    spectrum = per_order.new_zeros(coeffs.shape[0], columns, columns, 2)
    spectrum = spectrum.index_add(2, order_columns(max(degrees), columns, coeffs.device), per_order)
    return torch.fft.ifft(torch.view_as_complex(spectrum), dim=-1, norm="forward").real
