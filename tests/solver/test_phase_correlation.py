"""N-D phase correlation, its soft arg-max and the upsampled-DFT peak refinement."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dpcn_med.solver.phase_correlation import phase_correlation, refine_peak, soft_argmax, unravel


def _smooth_noise(shape: tuple[int, ...], seed: int, dtype: torch.dtype) -> torch.Tensor:
    """Band-limited random signal ``(1, *shape)``: a low-pass of white noise, done in Fourier space."""
    noise = torch.randn(1, *shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    axes = tuple(range(1, len(shape) + 1))
    frequency = sum(torch.fft.fftfreq(n, dtype=torch.float64).reshape([-1 if a == i else 1 for a in range(len(shape))])
                    ** 2 for i, n in enumerate(shape))
    return torch.fft.ifftn(torch.fft.fftn(noise, dim=axes) * torch.exp(-frequency * 10), dim=axes).real.to(dtype)


def _fourier_shift(signal: torch.Tensor, shift_xyz: list[float]) -> torch.Tensor:
    """``out(p) = signal(p + shift)`` by a Fourier phase ramp (exact for band-limited periodic signals)."""
    dim = len(shift_xyz)
    axes = tuple(range(-dim, 0))
    ramp = 0.0
    for axis in range(dim):
        n = signal.shape[-dim + axis]
        k = torch.fft.fftfreq(n, dtype=torch.float64).reshape([-1 if a == axis else 1 for a in range(dim)])
        ramp = ramp + k * shift_xyz[dim - 1 - axis]
    return torch.fft.ifftn(torch.fft.fftn(signal, dim=axes) * torch.exp(2j * math.pi * ramp), dim=axes).real.to(
        signal.dtype)


class TestPhaseCorrelation:
    @pytest.mark.parametrize("shape,shift", [((64,), [5.0]), ((32, 48), [-7.0, 3.0]), ((16, 20, 24), [2.0, -3.0, 4.0])])
    def test_integer_shift_gives_a_unit_peak_at_the_shift(self, shape, shift, dtype, device):
        moving = _smooth_noise(shape, 0, dtype)
        fixed = _fourier_shift(moving, shift)  # fixed(p) = moving(p + shift)
        surface, _ = phase_correlation(fixed.to(device), moving.to(device), len(shape))
        assert surface.device.type == device.type
        peak = soft_argmax(surface, 0.01, len(shape))
        torch.testing.assert_close(peak.index[0].cpu(), torch.tensor(shift, dtype=dtype))
        assert surface.max().item() > 0.99

    def test_flat_input_gives_zeros_not_nan(self):
        surface, spectrum = phase_correlation(torch.zeros(1, 8, 8), torch.ones(1, 8, 8), 2)
        assert torch.isfinite(surface).all() and torch.isfinite(spectrum).all()
        assert surface.abs().max() < 1e-6


class TestRefinePeak:
    @pytest.mark.parametrize("shape,true", [((50,), [3.4375]), ((40, 36), [2.3125, -4.6875]),
                                            ((20, 18, 24), [1.25, -2.5625, 3.875])])
    def test_recovers_a_sub_pixel_shift(self, shape, true, dtype):
        moving = _smooth_noise(shape, 1, dtype)
        fixed = _fourier_shift(moving, true)
        surface, spectrum = phase_correlation(fixed, moving, len(shape))
        coarse = soft_argmax(surface, 0.01, len(shape))
        refined, height = refine_peak(spectrum, coarse.index, shape, upsample=16)
        # Within one refinement step: a fractional Fourier shift is not exact at the Nyquist frequency of an even axis.
        torch.testing.assert_close(refined[0], torch.tensor(true, dtype=dtype), atol=1 / 16 + 1e-6, rtol=0)
        assert height.item() > 0.9


class TestSoftArgmax:
    def test_wraps_around_a_periodic_axis(self):
        surface = torch.full((1, 16), -1.0, dtype=torch.float64)
        surface[0, 0], surface[0, 15] = 1.0, 1.0  # a peak split across the wrap, at shift -8 / +7
        peak = soft_argmax(surface, 0.05, 1)
        assert peak.shift[0, 0].item() == pytest.approx(-8.5, abs=1e-6) or \
            peak.shift[0, 0].item() == pytest.approx(7.5, abs=1e-6)

    def test_non_periodic_axis_drops_cells_past_the_end(self):
        surface = torch.full((1, 9), -1.0, dtype=torch.float64)
        surface[0, 0] = 1.0
        peak = soft_argmax(surface, 0.05, 1, periodic=(False,))
        assert peak.shift[0, 0].item() == pytest.approx(-4.0, abs=1e-6)

    def test_mass_is_high_for_a_sharp_peak_and_low_for_a_flat_surface(self):
        sharp = torch.zeros(1, 32, 32)
        sharp[0, 10, 20] = 1.0
        assert soft_argmax(sharp, 0.01, 2).mass.item() > 0.99
        assert soft_argmax(torch.zeros(1, 32, 32), 0.01, 2).mass.item() == pytest.approx(9 / 1024, rel=1e-4)

    def test_flat_surface_ties_go_to_the_zero_shift(self):
        peak = soft_argmax(torch.zeros(1, 10, 12), 0.01, 2)
        torch.testing.assert_close(peak.index, torch.zeros(1, 2))

    def test_gradcheck_wrt_surface_and_temperature(self):
        surface = torch.randn(1, 7, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
        surface[0, 3, 2] += 3.0
        temperature = torch.tensor(0.7, dtype=torch.float64, requires_grad=True)
        surface.requires_grad_()
        assert torch.autograd.gradcheck(
            lambda s, t: (soft_argmax(s, t, 2).shift, soft_argmax(s, t, 2).mass), (surface, temperature))


@pytest.mark.parametrize("sizes", [(7,), (5, 3), (4, 6, 9)])
def test_unravel_matches_numpy(sizes):
    flat = torch.randint(0, math.prod(sizes), (3, 11), generator=torch.Generator().manual_seed(len(sizes)))
    expected = np.stack(np.unravel_index(flat.numpy(), sizes), -1)
    assert unravel(flat, sizes).shape == (3, 11, len(sizes))
    np.testing.assert_array_equal(unravel(flat, sizes).numpy(), expected)
