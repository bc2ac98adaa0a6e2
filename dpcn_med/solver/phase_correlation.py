"""Cartesian phase correlation in any number of dimensions, with a soft arg-max and a sub-grid peak refinement.

Used three times by the solver: 3-D translation, 1-D log-radius (scale) and 2-D log-polar (rotation and scale in 2-D).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dpcn_med.geometry import grid_centre


def cross_power_spectrum(fixed: Tensor, moving: Tensor, dim: int, *, whiten: bool = True) -> Tensor:
    """One-sided cross-power spectrum ``RFFT(moving) * conj(RFFT(fixed))`` over the last ``dim`` axes.

    Args:
        fixed: ``(B, *S)`` real signals.
        moving: ``(B, *S)`` real signals, same shape, device and dtype.
        dim: number of trailing axes to transform.
        whiten: divide by the magnitudes (phase correlation) rather than keep them (cross-correlation).

    Returns:
        ``(B, *S')`` complex spectrum, ``S'`` = ``S`` with the last axis ``n // 2 + 1`` (real signals have Hermitian
        spectra, so half is enough and costs half), zero frequency first. Whitened, a flat input gives zeros, not NaN.
    """
    axes = tuple(range(-dim, 0))
    spectrum = torch.fft.rfftn(moving, dim=axes) * torch.fft.rfftn(fixed, dim=axes).conj()
    if not whiten:
        return spectrum
    magnitude = spectrum.abs()
    floor = 1e-6 * magnitude.flatten(1).mean(-1).reshape(-1, *([1] * dim)) + torch.finfo(magnitude.dtype).tiny
    return spectrum / (magnitude + floor)


def correlation_surface(spectrum: Tensor, sizes: tuple[int, ...]) -> Tensor:
    """Correlation surface of a one-sided cross-power spectrum: ``(B, *S')`` complex -> ``(B, *sizes)`` real.

    Shifted so that index ``size // 2`` along each axis is a zero shift; for a whitened spectrum of a pure translation
    the surface is a unit peak at the shift ``d`` with ``fixed(p) = moving(p + d)``.
    """
    axes = tuple(range(-len(sizes), 0))
    return torch.fft.fftshift(torch.fft.irfftn(spectrum, s=sizes, dim=axes), dim=axes)


def phase_correlation(fixed: Tensor, moving: Tensor, dim: int, *, whiten: bool = True) -> tuple[Tensor, Tensor]:
    """Phase correlation of two signals over their last ``dim`` axes.

    Args:
        fixed: ``(B, *S)`` real signals.
        moving: ``(B, *S)`` real signals.
        dim: number of trailing axes.
        whiten: phase correlation (True) or plain circular cross-correlation (False).

    Returns:
        ``(surface, spectrum)``: the real ``(B, *S)`` surface of :func:`correlation_surface` and the complex spectrum of
        :func:`cross_power_spectrum`, which :func:`refine_peak` reuses.

    Notes:
        If ``fixed(p) = moving(p + d)``, then ``FFT(moving)(k) = exp(2 pi i k.d / N) FFT(fixed)(k)``, the whitened
        cross-power spectrum is ``exp(2 pi i k.d / N)`` and its inverse transform is a unit impulse at ``d``.

    References:
        Kuglin and Hines, "The phase correlation image alignment method", 1975.
    """
    spectrum = cross_power_spectrum(fixed, moving, dim, whiten=whiten)
    return correlation_surface(spectrum, tuple(fixed.shape[-dim:])), spectrum


@dataclass
class SoftPeak:
    """A soft arg-max of a surface.

    Attributes:
        shift: ``(B, d)`` expected shift, order ``(x, y[, z])`` (the last axis of the surface first), in grid cells from
            the centre index ``size // 2``.
        index: ``(B, d)`` arg-max, same order and units (integers).
        mass: ``(B,)`` softmax mass inside the window around the arg-max, in ``[0, 1]``: a confidence.
        log_prob: ``(B, *S)`` global log-softmax of ``surface / temperature``, for the KL losses.
    """

    shift: Tensor
    index: Tensor
    mass: Tensor
    log_prob: Tensor


def _tie_break(sizes: tuple[int, ...], like: Tensor) -> Tensor:
    """A penalty of at most one machine epsilon growing with the distance from the centre cell: ``sizes``-shaped.

    Subtracted before an arg-max so that ties (a flat surface, from an empty or constant input) go to the centre, the
    zero shift, instead of the first cell; any real peak differs by far more.
    """
    squared = sum(((torch.arange(n, device=like.device, dtype=like.dtype) - grid_centre(n)) ** 2).reshape(
        [-1 if a == axis else 1 for a in range(len(sizes))]) for axis, n in enumerate(sizes))
    return torch.finfo(like.dtype).eps * squared / squared.max().clamp_min(1.0)


def _window_offsets(dim: int, half_width: int, device: torch.device) -> Tensor:
    """All integer offsets of a ``(2w+1)^d`` window: ``((2w+1)^d, d)`` in torch axis order."""
    ticks = torch.arange(-half_width, half_width + 1, device=device)
    return torch.stack(torch.meshgrid(*([ticks] * dim), indexing="ij"), -1).reshape(-1, dim)


def soft_argmax(surface: Tensor, temperature: Tensor | float, dim: int, *, half_width: int = 1,
                periodic: tuple[bool, ...] | None = None) -> SoftPeak:
    """Soft arg-max of a correlation surface: softmax with a temperature in a window around the arg-max.

    Args:
        surface: ``(B, *S)`` real surface, zero shift at index ``size // 2`` (see :func:`correlation_surface`).
        temperature: positive scalar (float or 0-d tensor, differentiable); lower is sharper.
        dim: number of trailing axes forming the surface.
        half_width: the window spans ``2 * half_width + 1`` cells per axis.
        periodic: per trailing axis (torch order), whether it wraps; default all periodic. Window cells past the end
            of a non-periodic axis are left out.

    Returns:
        A :class:`SoftPeak`. The expectation is taken in a window, not globally: a global expectation is pulled
        towards the centre by the background and is wrong across the wrap of a periodic axis.
    """
    sizes = surface.shape[-dim:]
    periodic = periodic or (True,) * dim
    batch = surface.shape[0]
    logits = surface / temperature
    log_prob = logits - torch.logsumexp(logits.flatten(1), dim=-1).reshape(-1, *([1] * dim))
    flat_index = (surface.detach() - _tie_break(tuple(sizes), surface)).flatten(1).argmax(-1)
    peak = torch.stack(torch.unravel_index(flat_index, tuple(sizes)), -1)  # (B, d) torch order
    offsets = _window_offsets(dim, half_width, surface.device)  # (W, d)
    cells = peak[:, None, :] + offsets[None]  # (B, W, d)
    valid = torch.ones(cells.shape[:2], dtype=torch.bool, device=surface.device)
    size_tensor = torch.tensor(sizes, device=surface.device)
    for axis in range(dim):
        if periodic[axis]:
            cells[..., axis] = torch.remainder(cells[..., axis], sizes[axis])
        else:
            valid &= (cells[..., axis] >= 0) & (cells[..., axis] < sizes[axis])
    cells = torch.minimum(cells.clamp_min(0), size_tensor - 1)
    strides = torch.tensor([math.prod(sizes[a + 1:]) for a in range(dim)], device=surface.device)
    window_logp = log_prob.flatten(1).gather(1, (cells * strides).sum(-1))
    window_logp = window_logp.masked_fill(~valid, float("-inf"))
    mass = torch.logsumexp(window_logp, dim=-1).exp().clamp(0.0, 1.0)
    weights = torch.softmax(window_logp, dim=-1)
    centre = torch.tensor([grid_centre(n) for n in sizes], device=surface.device)
    expected = (peak - centre).to(surface.dtype) + weights @ offsets.to(surface.dtype)
    return SoftPeak(shift=expected.flip(-1), index=(peak - centre).flip(-1).to(surface.dtype),
                    mass=mass, log_prob=log_prob.reshape(batch, *sizes))


def refine_peak(spectrum: Tensor, shift: Tensor, sizes: tuple[int, ...], *, upsample: int = 16,
                half_width: float = 1.0) -> tuple[Tensor, Tensor]:
    """Sub-grid peak of a correlation by a local upsampled DFT around an initial shift.

    Evaluates ``c(x) = N^-d sum_k spectrum(k) exp(2 pi i k.x / N)`` on a grid of step ``1 / upsample`` within
    ``half_width`` cells of ``shift`` (separable matrix products, so the cost is about ``upsample * N^d``, not the
    ``upsample^d N^d`` of zero-padding) and returns its arg-max.

    Args:
        spectrum: ``(B, *S')`` one-sided complex cross-power spectrum, as from :func:`cross_power_spectrum`.
        shift: ``(B, d)`` initial shift in cells, order ``(x, y[, z])``.
        sizes: ``S``, the shape of the real signals (the last axis is not recoverable from ``S'``).
        upsample: refinement factor.
        half_width: half-size of the searched region in cells.

    Returns:
        ``(shift, height)``: refined ``(B, d)`` shift, same order, and ``(B,)`` correlation value there.

    References:
        Guizar-Sicairos, Thurman and Fienup, "Efficient subpixel image registration algorithms", Opt. Lett. 2008.
    """
    dim = shift.shape[-1]
    steps = torch.arange(-half_width * upsample, half_width * upsample + 1, device=spectrum.device,
                         dtype=shift.dtype) / upsample
    values = spectrum
    positions = []
    for axis in range(dim):  # torch axis order; shift is (x, y, z) so axis a pairs with shift[..., dim - 1 - a]
        n = sizes[axis]
        where = shift[:, dim - 1 - axis, None] + steps  # (B, U)
        positions.append(where)
        if axis == dim - 1:  # the one-sided axis: count each conjugate pair twice, then keep the real part
            frequencies = torch.arange(n // 2 + 1, device=spectrum.device, dtype=shift.dtype)
            pairs = torch.where((frequencies == 0) | (frequencies == n / 2), 1.0, 2.0)
        else:
            frequencies = torch.fft.fftfreq(n, d=1.0 / n, device=spectrum.device, dtype=shift.dtype)
            pairs = torch.ones_like(frequencies)
        kernel = pairs * torch.exp(2j * math.pi * where[..., None] * frequencies / n) / n  # (B, U, n')
        values = torch.movedim(torch.einsum("bun,bn...->bu...", kernel.to(spectrum.dtype),
                                            torch.movedim(values, axis + 1, 1)), 1, axis + 1)
    real = values.real
    count = steps.numel()
    best = (real - _tie_break((count,) * dim, real)).flatten(1).argmax(-1)
    index = torch.stack(torch.unravel_index(best, (count,) * dim), -1)  # (B, d) torch order
    refined = torch.stack([positions[axis].gather(1, index[:, axis, None])[:, 0] for axis in range(dim)], -1)
    return refined.flip(-1), real.flatten(1).gather(1, best[:, None])[:, 0]
