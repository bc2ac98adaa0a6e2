"""Step 3b: Wigner small-d tables, against the matrix exponential of the angular momentum."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.special
import torch

from dpcn_med.solver.sphere import even_degrees
from dpcn_med.solver.wigner import correlation_table, legendre, wigner_d


def _j_y(degree: int) -> np.ndarray:
    """Angular momentum ``J_y`` in the basis ``|l, m>``, ``m = -l..l``."""
    orders = np.arange(-degree, degree + 1)
    raising = np.zeros((2 * degree + 1,) * 2)
    for i, order in enumerate(orders[:-1]):
        raising[i + 1, i] = np.sqrt(degree * (degree + 1) - order * (order + 1))
    return (raising - raising.T) / 2j


class TestWignerD:
    def test_equals_exp_of_minus_i_beta_j_y(self):
        betas = torch.tensor([0.05, 0.9, 2.2, 3.1], dtype=torch.float64)
        degrees = (0, 1, 2, 5, 12)
        table = wigner_d(degrees, betas).numpy()
        top = max(degrees)
        for i, degree in enumerate(degrees):
            for k, beta in enumerate(betas.tolist()):
                reference = scipy.linalg.expm(-1j * beta * _j_y(degree))
                block = table[i, k, top - degree:top + degree + 1, top - degree:top + degree + 1]
                np.testing.assert_allclose(block, reference.real, atol=1e-12)
                assert np.abs(reference.imag).max() < 1e-12

    def test_unitary_to_1e10_up_to_degree_63(self):
        betas = torch.linspace(0.01, 3.13, 9, dtype=torch.float64)
        degrees = (31, 48, 63)
        table = wigner_d(degrees, betas)
        top = max(degrees)
        for i, degree in enumerate(degrees):
            block = table[i, :, top - degree:top + degree + 1, top - degree:top + degree + 1]
            identity = torch.eye(2 * degree + 1, dtype=torch.float64)
            assert (block @ block.transpose(-1, -2) - identity).abs().max() < 1e-10

    def test_beta_symmetry_used_by_the_half_table(self):
        beta = torch.tensor([0.4], dtype=torch.float64)
        degrees = (2, 6, 10)
        low, high = wigner_d(degrees, beta)[:, 0], wigner_d(degrees, torch.pi - beta)[:, 0]
        top = max(degrees)
        orders = torch.arange(-top, top + 1, dtype=torch.float64)
        for i, degree in enumerate(degrees):
            sign = (-1.0) ** (degree + orders)[:, None]
            torch.testing.assert_close(high[i], sign * low[i].flip(-1), atol=1e-12, rtol=0)


class TestLegendre:
    def test_equals_scipy_sph_legendre_p_up_to_degree_127(self):
        betas = torch.tensor([0.003, 0.4, 1.5707, 2.9, 3.1385], dtype=torch.float64)
        degrees = (0, 1, 2, 7, 30, 64, 127)
        table = legendre(degrees, betas).numpy()
        top = max(degrees)
        for i, degree in enumerate(degrees):
            orders = np.arange(-top, top + 1)
            reference = scipy.special.sph_legendre_p(degree, orders[:, None], betas.numpy()[None, :])[0]
            reference[np.abs(orders) > degree] = 0.0
            np.testing.assert_allclose(table[i], reference, atol=1e-11, err_msg=f"degree {degree}")

    def test_columns_of_the_recurrence_are_those_of_the_full_table(self):
        betas = torch.tensor([0.7, 2.0], dtype=torch.float64)
        degrees = (3, 8)
        full = wigner_d(degrees, betas)[..., 8]  # n = 0 of the full (m, n) matrices: (L, K, 2M + 1)
        scale = torch.sqrt((2 * torch.tensor(degrees, dtype=torch.float64) + 1) / (4 * torch.pi))
        torch.testing.assert_close(legendre(degrees, betas), (full * scale[:, None, None]).transpose(1, 2),
                                   atol=1e-14, rtol=0)


class TestCorrelationTable:
    @pytest.mark.parametrize("bandwidth", [5, 8])
    def test_holds_even_degrees_non_negative_n_and_the_first_half_of_the_betas(self, bandwidth):
        table = correlation_table(bandwidth, torch.device("cpu"), torch.float64)
        degrees = even_degrees(bandwidth)
        top = max(degrees)
        index = torch.arange(bandwidth, dtype=torch.float64)
        reference = wigner_d(degrees, torch.pi * (2 * index + 1) / (4 * bandwidth))[..., top:]
        assert table.shape == ((2 * top + 1) * (top + 1), bandwidth, len(degrees))
        torch.testing.assert_close(table, reference.permute(2, 3, 1, 0).reshape(table.shape))

    def test_cached(self):
        assert correlation_table(6, torch.device("cpu"), torch.float32) is correlation_table(
            6, torch.device("cpu"), torch.float32)
