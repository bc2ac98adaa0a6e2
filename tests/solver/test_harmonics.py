"""Step 3a: spherical harmonics and their transform on the SOFT grid."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.special
import torch

from dpcn_med.solver.harmonics import isht, legendre_table, sht
from dpcn_med.solver.sphere import even_degrees, sphere_angles


class TestLegendreTable:
    @pytest.mark.parametrize("bandwidth", [8, 64])
    def test_table_times_phase_equals_scipy_sph_harm_y(self, bandwidth):
        degrees = tuple(range(bandwidth))
        table = legendre_table(bandwidth, degrees, torch.device("cpu"), torch.float64).numpy()
        theta, phi = (a.numpy() for a in sphere_angles(bandwidth, dtype=torch.float64))
        top = bandwidth - 1
        for degree in (0, 1, bandwidth // 2, top):
            for order in (-degree, -1, 0, degree // 2, degree):
                if abs(order) > degree:
                    continue
                ours = table[degree, order + top][:, None] * np.exp(1j * order * phi)[None, :]
                reference = scipy.special.sph_harm_y(degree, order, theta[:, None], phi[None, :])
                np.testing.assert_allclose(ours, reference, atol=1e-12)

    def test_cached_per_bandwidth_device_and_dtype(self):
        first = legendre_table(8, (2, 4), torch.device("cpu"), torch.float32)
        assert legendre_table(8, (2, 4), torch.device("cpu"), torch.float32) is first
        assert legendre_table(8, (2, 4), torch.device("cpu"), torch.float64) is not first


def _random_real_coefficients(degrees: tuple[int, ...], seed: int) -> torch.Tensor:
    """Coefficients of a real function: ``S_l^-m = (-1)^m conj(S_l^m)``. ``(1, L, 2M + 1)`` complex128."""
    top = max(degrees)
    generator = torch.Generator().manual_seed(seed)
    coeffs = torch.zeros(1, len(degrees), 2 * top + 1, dtype=torch.complex128)
    for i, degree in enumerate(degrees):
        for order in range(0, degree + 1):
            value = torch.complex(*torch.randn(2, generator=generator, dtype=torch.float64))
            value = value.real.to(torch.complex128) if order == 0 else value
            coeffs[0, i, top + order] = value
            coeffs[0, i, top - order] = (-1) ** order * value.conj()
    return coeffs


class TestSHT:
    @pytest.mark.parametrize("bandwidth", [4, 16, 32])
    def test_round_trip_of_a_band_limited_function(self, bandwidth):
        degrees = tuple(range(bandwidth))
        coeffs = _random_real_coefficients(degrees, bandwidth)
        values = isht(coeffs, degrees, bandwidth)
        torch.testing.assert_close(sht(values, degrees), coeffs, atol=1e-10, rtol=0)

    def test_even_degrees_skip_zero_and_odd(self):
        assert even_degrees(9) == (2, 4, 6, 8)

    def test_rejects_degrees_at_or_above_the_bandwidth(self):
        with pytest.raises(ValueError, match="need a bandwidth above"):
            sht(torch.zeros(1, 8, 8), (2, 4))
