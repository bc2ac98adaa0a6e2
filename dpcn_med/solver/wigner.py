"""Wigner small-d functions by the Kostelec-Rockmore three-term recurrence in the degree, and the associated
Legendre functions of the spherical harmonic transform, which are their column ``n = 0``.

Convention: ``d^l_mn(beta) = <l m| exp(-i beta J_y) |l n>``, so that ``D^l_mn(R) = exp(-i m alpha) d^l_mn(beta)
exp(-i n gamma)`` for ``R = Rz(alpha) Ry(beta) Rz(gamma)``. Tables are computed in float64 on the target device, cast
at the end, cached per ``(bandwidth, device, dtype)`` and never stored on disk (why a module of our own:
docs/design_notes/solver.md).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator

import torch
from torch import Tensor

from dpcn_med.solver.sphere import even_degrees, soft_colatitude


def _orders(top: int, columns: tuple[int, ...] | None, device: torch.device) -> tuple[Tensor, Tensor]:
    """``(m, n)`` float64 grids: rows ``m = -top..top``, ``(2 top + 1, 1)``; columns ``n`` (default ``-top..top``),
    ``(1, N)``."""
    orders = torch.arange(-top, top + 1, device=device, dtype=torch.float64)
    n = orders if columns is None else torch.tensor(columns, device=device, dtype=torch.float64)
    return orders[:, None], n[None, :]


def _seeds(top: int, betas: Tensor, columns: tuple[int, ...] | None = None) -> Tensor:
    """``d^l0_mn(beta)`` at ``l0 = max(|m|, |n|)``, the first degree where each ``(m, n)`` exists.

    Closed forms from Wigner's formula, evaluated in log space so that powers of ``sin(beta / 2)`` underflow to zero
    instead of overflowing the binomial factor. Returns ``(K, 2 top + 1, N)`` float64, the columns of
    :func:`_orders`.
    """
    m, n = _orders(top, columns, betas.device)
    l0 = torch.maximum(m.abs(), n.abs())
    row_is_edge = m.abs() >= n.abs()  # cases m = +-l0, else n = +-l0
    other = torch.where(row_is_edge, n, m)
    edge_positive = torch.where(row_is_edge, m, n) > 0
    log_binomial = 0.5 * (torch.lgamma(2 * l0 + 1) - torch.lgamma(l0 + other + 1) - torch.lgamma(l0 - other + 1))
    cos_power = torch.where(edge_positive, l0 + other, l0 - other)
    sin_power = torch.where(edge_positive, l0 - other, l0 + other)
    # Signs: m = l0 gives (-1)^(l0 - n); n = -l0 gives (-1)^(l0 + m); m = -l0 and n = l0 give +1.
    sign_exponent = torch.where(row_is_edge & edge_positive, l0 - n, torch.zeros_like(l0))
    sign_exponent = torch.where(~row_is_edge & ~edge_positive, l0 + m, sign_exponent)
    sign = 1.0 - 2.0 * torch.remainder(sign_exponent, 2)
    half = betas.to(torch.float64)[:, None, None] / 2
    log_value = log_binomial + cos_power * torch.log(torch.cos(half)) + sin_power * torch.log(torch.sin(half))
    return sign * torch.exp(log_value)


def _recurrence(top: int, betas: Tensor, columns: tuple[int, ...] | None = None) -> Iterator[tuple[int, Tensor]]:
    """Yield ``(l, d^l)`` for ``l = 0..top``, each ``(K, 2 top + 1, N)`` float64 (zero where ``|m|, |n| > l``), rows
    ``m = -top..top`` and columns ``n`` in ``columns`` (default ``-top..top``, ``N = 2 top + 1``).

    ``d^(J+1) = a_J (cos beta - m n / (J (J + 1))) d^J - b_J d^(J-1)`` with
    ``a_J = (J + 1)(2J + 1) / sqrt(((J + 1)^2 - m^2)((J + 1)^2 - n^2))`` and
    ``b_J = (J + 1) sqrt((J^2 - m^2)(J^2 - n^2)) / (J sqrt(((J + 1)^2 - m^2)((J + 1)^2 - n^2)))``.

    References:
        Kostelec and Rockmore, "FFTs on the rotation group", J. Fourier Anal. Appl. 2008, eq. 4.5.
    """
    m, n = _orders(top, columns, betas.device)
    l0 = torch.maximum(m.abs(), n.abs())
    seeds = _seeds(top, betas, columns)
    cos_beta = torch.cos(betas.to(torch.float64))[:, None, None]
    previous = torch.zeros_like(seeds)
    current = torch.zeros_like(seeds)
    for degree in range(top + 1):
        j = float(degree - 1)
        if degree == 0:
            following = torch.zeros_like(seeds)
        else:
            grown = l0 <= j  # entries that already exist at degree J = degree - 1
            denominator = torch.sqrt(((j + 1) ** 2 - m ** 2).clamp_min(1) * ((j + 1) ** 2 - n ** 2).clamp_min(1))
            a = (j + 1) * (2 * j + 1) / denominator
            b = (j + 1) * torch.sqrt(((j ** 2 - m ** 2) * (j ** 2 - n ** 2)).clamp_min(0)) / (max(j, 1.0) * denominator)
            mixing = m * n / max(j * (j + 1), 1.0)
            following = torch.where(grown, a * (cos_beta - mixing) * current - b * previous, 0.0)
        following = torch.where(l0 == degree, seeds, following)
        previous, current = current, following
        yield degree, current


def _wanted(degrees: tuple[int, ...], betas: Tensor, columns: tuple[int, ...] | None = None
            ) -> Iterator[tuple[int, int, Tensor]]:
    """``(i, l, d^l)`` for each wanted degree ``l = degrees[i]``, in increasing ``l``: :func:`_recurrence` run up to
    the largest, with its ``columns``."""
    wanted = {degree: index for index, degree in enumerate(degrees)}
    for degree, values in _recurrence(max(degrees), betas, columns):
        if degree in wanted:
            yield wanted[degree], degree, values


def wigner_d(degrees: tuple[int, ...], betas: Tensor) -> Tensor:
    """Wigner small-d matrices.

    Args:
        degrees: the ``L`` degrees wanted.
        betas: ``(K,)`` angles in radians, strictly inside ``(0, pi)``.

    Returns:
        ``(L, K, 2M + 1, 2M + 1)`` float64, ``M = max(degrees)``, entry ``[i, k, m + M, n + M] = d^l_mn(beta_k)`` for
        ``l = degrees[i]``; zero where ``|m|`` or ``|n|`` exceeds ``l``.
    """
    size = 2 * max(degrees) + 1
    table = torch.zeros(len(degrees), betas.shape[0], size, size, device=betas.device, dtype=torch.float64)
    for index, _, values in _wanted(degrees, betas):
        table[index] = values
    return table


def legendre(degrees: tuple[int, ...], betas: Tensor) -> Tensor:
    """Orthonormal associated Legendre functions with the Condon-Shortley phase: ``Y_l^m(beta, 0)``, equal to
    ``scipy.special.sph_legendre_p(l, m, beta)``, from ``Y_l^m(beta, 0) = sqrt((2l + 1) / (4 pi)) d^l_m0(beta)``.

    Why not scipy: importing ``scipy.special`` costs more than the table at the solver's bandwidths, and the
    recurrence is already here (docs/design_notes/solver.md, ``dpcn_med.solver.wigner.legendre``).

    Args:
        degrees: the ``L`` degrees wanted.
        betas: ``(K,)`` colatitudes in radians, strictly inside ``(0, pi)``.

    Returns:
        ``(L, 2M + 1, K)`` float64, ``M = max(degrees)``, entry ``[i, m + M, k]`` for ``l = degrees[i]``; zero where
        ``|m| > l``.
    """
    table = torch.zeros(len(degrees), 2 * max(degrees) + 1, betas.shape[0], device=betas.device, dtype=torch.float64)
    for index, degree, values in _wanted(degrees, betas, columns=(0,)):
        table[index] = values[..., 0].T * math.sqrt((2 * degree + 1) / (4 * math.pi))
    return table


@functools.lru_cache(maxsize=4)
def correlation_table(bandwidth: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    """The SO(3) correlation's table: ``d^l_mn(beta_k)`` for even degrees, ``n >= 0`` and the first half of the betas.

    The correlation of two real spheres has a Hermitian spectrum in ``(m, n)``, so orders ``n >= 0`` suffice; and
    ``d^l_mn(pi - beta) = (-1)^(l + m) d^l_m,-n(beta)`` gives the betas past ``pi / 2``. Together they cut the table
    to a quarter of the full one.

    Args:
        bandwidth: ``B``; betas ``beta_k = pi (2k + 1) / (4B)``, ``k < B``.
        device: where the table lives.
        dtype: its real dtype.

    Returns:
        ``((2M + 1)(M + 1), B, L)``, rows ``(m, n)`` for ``m = -M..M``, ``n = 0..M`` (``M`` the largest even degree
        below ``B``), laid out for a batched matrix product over ``(m, n)``: about ``B^4`` entries (sizes:
        docs/design_notes/solver.md); the cache holds up to four tables.
    """
    degrees = even_degrees(bandwidth)
    top = max(degrees)
    rows, cols = 2 * top + 1, top + 1
    betas = soft_colatitude(torch.arange(bandwidth, device=device, dtype=torch.float64), bandwidth)
    table = torch.empty(rows * cols, bandwidth, len(degrees), device=device, dtype=dtype)
    for index, _, values in _wanted(degrees, betas, columns=tuple(range(cols))):  # n >= 0 only: half the work
        table[:, :, index] = values.permute(1, 2, 0).reshape(rows * cols, bandwidth).to(dtype)
    return table
