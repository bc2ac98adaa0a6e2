"""Cartesian phase correlation in any number of dimensions, with a soft arg-max and a sub-grid peak refinement.

Used three times by the solver: 3-D translation, 1-D log-radius (scale) and 2-D log-polar (rotation and scale in 2-D).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from dpcn_med.geometry import grid_centre, squared_distance_from_centre

# Whitening divides by |X| + WHITENING_FLOOR * mean |X|: frequencies with (almost) no energy in either signal carry
# no phase worth amplifying, and an all-zero spectrum becomes zeros instead of NaN.
WHITENING_FLOOR = 1e-6


def cross_power_spectrum(fixed: Tensor, moving: Tensor, dim: int, *, whiten: bool = True) -> Tensor:
    """One-sided cross-power spectrum ``RFFT(moving) * conj(RFFT(fixed))`` over the last ``dim`` axes.

    Args:
        fixed: ``(..., *S)`` real signals.
        moving: ``(..., *S)`` real signals, broadcastable against ``fixed`` (e.g. one fixed signal for K moving
            ones), same device and dtype.
        dim: number of trailing axes ``S`` to transform.
        whiten: divide by the magnitudes (phase correlation) rather than keep them (cross-correlation).

    Returns:
        ``(batch, *S')`` complex spectrum, ``S'`` = ``S`` with the last axis ``n // 2 + 1`` (real signals have Hermitian
        spectra, so half is enough and costs half), zero frequency first. Whitened, a flat input gives zeros, not NaN.
    """
    axes = tuple(range(-dim, 0))
    spectrum = torch.fft.rfftn(moving, dim=axes) * torch.fft.rfftn(fixed, dim=axes).conj()
    if not whiten:
        return spectrum
    magnitude = spectrum.abs()
    floor = WHITENING_FLOOR * magnitude.mean(axes, keepdim=True) + torch.finfo(magnitude.dtype).tiny
    return spectrum / (magnitude + floor)


def correlation_surface(spectrum: Tensor, sizes: tuple[int, ...]) -> Tensor:
    """Correlation surface of a one-sided cross-power spectrum: ``(batch, *S')`` complex -> ``(batch, *sizes)`` real.

    Shifted so that index ``size // 2`` along each axis is a zero shift; for a whitened spectrum of a pure translation
    the surface is a unit peak at the shift ``d`` with ``fixed(p) = moving(p + d)``.
    """
    axes = tuple(range(-len(sizes), 0))
    return torch.fft.fftshift(torch.fft.irfftn(spectrum, s=sizes, dim=axes), dim=axes)


def phase_correlation(fixed: Tensor, moving: Tensor, dim: int, *, whiten: bool = True) -> tuple[Tensor, Tensor]:
    """Phase correlation of two signals over their last ``dim`` axes.

    Args:
        fixed: ``(batch, *S)`` real signals.
        moving: ``(batch, *S)`` real signals.
        dim: number of trailing axes.
        whiten: phase correlation (True) or plain circular cross-correlation (False).

    Returns:
        ``(surface, spectrum)``: the real ``(batch, *S)`` surface of :func:`correlation_surface` and the complex
        spectrum of :func:`cross_power_spectrum`, which :func:`refine_peak` reuses.

    Notes:
        If ``fixed(p) = moving(p + d)``, then ``FFT(moving)(k) = exp(-2 pi i k.d / N) FFT(fixed)(k)``, the whitened
        cross-power spectrum is ``exp(-2 pi i k.d / N)`` and its inverse transform (``exp(+2 pi i k.p / N)``) is a unit
        impulse at ``p = d``.

    References:
        Kuglin and Hines, "The phase correlation image alignment method", 1975.
    """
    spectrum = cross_power_spectrum(fixed, moving, dim, whiten=whiten)
    return correlation_surface(spectrum, tuple(fixed.shape[-dim:])), spectrum


@dataclass
class SoftPeak:
    """A soft arg-max of a surface.

    Attributes:
        shift: ``(batch, d)`` expected shift, order ``(x, y[, z])`` (the last axis of the surface first), in grid cells
            from the centre index ``size // 2``.
        index: ``(batch, d)`` arg-max, same order and units (integers).
        mass: ``(batch,)`` softmax mass inside the window around the arg-max, in ``[0, 1]``: a confidence.
        log_prob: ``(batch, *S)`` global log-softmax of ``surface / temperature``, for the KL losses.
    """

    shift: Tensor
    index: Tensor
    mass: Tensor
    log_prob: Tensor


def unravel(flat: Tensor, sizes: tuple[int, ...]) -> Tensor:
    """``(...,)`` flat indices into a C-ordered array of ``sizes`` -> ``(..., d)`` indices, torch order.

    Like ``torch.unravel_index``, by integer division (why not it: docs/design_notes/solver.md).
    """
    indices = []
    for size in reversed(sizes):
        indices.append(torch.remainder(flat, size))
        flat = torch.div(flat, size, rounding_mode="floor")
    return torch.stack(indices[::-1], -1)


def _tie_break(sizes: tuple[int, ...], like: Tensor) -> Tensor:
    """A penalty of at most one machine epsilon growing with the distance from the centre cell: ``sizes``-shaped.

    Subtracted before an arg-max so that ties (a flat surface, from an empty or constant input) go to the centre, the
    zero shift, instead of the first cell; any real peak differs by far more.
    """
    squared = squared_distance_from_centre(sizes, device=like.device, dtype=like.dtype)
    return torch.finfo(like.dtype).eps * squared / squared.max().clamp_min(1.0)


def _window_offsets(dim: int, half_width: int, device: torch.device) -> Tensor:
    """All integer offsets of a ``(2w+1)^d`` window: ``((2w+1)^d, d)`` in torch axis order."""
    ticks = torch.arange(-half_width, half_width + 1, device=device)
    return torch.stack(torch.meshgrid(*([ticks] * dim), indexing="ij"), -1).reshape(-1, dim)


def window_softmax(log_prob: Tensor, cells: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """A normalised distribution restricted to windows of cells: their total mass and the renormalised weights.

    Args:
        log_prob: ``(batch, C)`` flattened log-probabilities (summing to one per item).
        cells: ``(batch, *K, W)`` flat indices into ``C``: ``K`` windows of ``W`` cells per item.
        valid: ``(batch, *K, W)``; cells outside the domain (past a non-periodic edge) are left out.

    Returns:
        ``(mass, weights)``: ``(batch, *K)`` in ``[0, 1]`` and ``(batch, *K, W)`` summing to one.
    """
    window = log_prob.gather(1, cells.flatten(1)).reshape(cells.shape).masked_fill(~valid, float("-inf"))
    return torch.logsumexp(window, -1).exp().clamp(0.0, 1.0), torch.softmax(window, -1)


def soft_argmax(surface: Tensor, temperature: Tensor | float, dim: int, *, half_width: int = 1,
                periodic: tuple[bool, ...] | None = None) -> SoftPeak:
    """Soft arg-max of a correlation surface: softmax with a temperature in a window around the arg-max.

    Args:
        surface: ``(batch, *S)`` real surface, zero shift at index ``size // 2`` (see :func:`correlation_surface`).
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
    peak = unravel(flat_index, tuple(sizes)).unbind(-1)  # d tensors (batch,), torch order
    offsets = _window_offsets(dim, half_width, surface.device)  # (W, d)
    valid = torch.ones(batch, offsets.shape[0], dtype=torch.bool, device=surface.device)
    flat_cells = torch.zeros_like(valid, dtype=torch.long)
    for axis, n in enumerate(sizes):  # Python scalars throughout: no host-to-device copies on CUDA
        cell = peak[axis][:, None] + offsets[:, axis]  # (batch, W)
        if periodic[axis]:
            cell = torch.remainder(cell, n)
        else:
            valid &= (cell >= 0) & (cell < n)
        flat_cells = flat_cells + cell.clamp(0, n - 1) * math.prod(sizes[axis + 1:])
    mass, weights = window_softmax(log_prob.flatten(1), flat_cells, valid)
    index = torch.stack([peak[axis] - grid_centre(n) for axis, n in enumerate(sizes)], -1).to(surface.dtype)
    expected = index + weights @ offsets.to(surface.dtype)
    return SoftPeak(shift=expected.flip(-1), index=index.flip(-1), mass=mass, log_prob=log_prob.reshape(batch, *sizes))


def refine_peak(spectrum: Tensor, shift: Tensor, sizes: tuple[int, ...], *, upsample: int = 16,
                half_width: float = 1.0) -> tuple[Tensor, Tensor]:
    """Sub-grid peak of a correlation by a local upsampled DFT around an initial shift.

    Evaluates ``c(x) = N^-d sum_k spectrum(k) exp(2 pi i k.x / N)`` on a grid of step ``1 / upsample`` within
    ``half_width`` cells of ``shift`` (separable matrix products, so the cost is about ``upsample * N^d``, not the
    ``upsample^d N^d`` of zero-padding) and returns its arg-max.

    Args:
        spectrum: ``(batch, *S')`` one-sided complex cross-power spectrum, as from :func:`cross_power_spectrum`.
        shift: ``(batch, d)`` initial shift in cells, order ``(x, y[, z])``.
        sizes: ``S``, the shape of the real signals (the last axis is not recoverable from ``S'``).
        upsample: refinement factor.
        half_width: half-size of the searched region in cells.

    Returns:
        ``(shift, height)``: refined ``(batch, d)`` shift, same order, and ``(batch,)`` correlation value there.

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
        where = shift[:, dim - 1 - axis, None] + steps  # (batch, U)
        positions.append(where)
        if axis == dim - 1:  # the one-sided axis: count each conjugate pair twice, then keep the real part
            frequencies = torch.arange(n // 2 + 1, device=spectrum.device, dtype=shift.dtype)
            pairs = torch.where((frequencies == 0) | (frequencies == n / 2), 1.0, 2.0)
        else:
            frequencies = torch.fft.fftfreq(n, d=1.0 / n, device=spectrum.device, dtype=shift.dtype)
            pairs = torch.ones_like(frequencies)
        kernel = pairs * torch.exp(2j * math.pi * where[..., None] * frequencies / n) / n  # (batch, U, n')
        values = torch.movedim(torch.einsum("bun,bn...->bu...", kernel.to(spectrum.dtype),
                                            torch.movedim(values, axis + 1, 1)), 1, axis + 1)
    real = values.real
    count = steps.numel()
    best = (real - _tie_break((count,) * dim, real)).flatten(1).argmax(-1)
    index = unravel(best, (count,) * dim)  # (batch, d) torch order
    refined = torch.stack([positions[axis].gather(1, index[:, axis, None])[:, 0] for axis in range(dim)], -1)
    return refined.flip(-1), real.flatten(1).gather(1, best[:, None])[:, 0]
