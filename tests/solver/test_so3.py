"""Step 3b: SO(3) correlation, peaks, soft arg-max and continuous refinement."""

from __future__ import annotations

import math

import pytest
import torch

from dpcn_med.geometry import (
    axis_angle_to_matrix,
    euler_zyz_to_matrix,
    geodesic_distance,
    matrix_to_euler_zyz,
    random_rotation,
)
from dpcn_med.solver.harmonics import isht, sht
from dpcn_med.solver.so3 import (
    deduplicate,
    euler_grid,
    grid_rotations,
    refine_rotation,
    so3_correlation,
    so3_log_prob,
    so3_peaks,
    soft_argmax_so3,
    sphere_correlation,
)
from dpcn_med.solver.sphere import even_degrees, quadrature_weights, sphere_directions
from dpcn_med.solver.wigner import wigner_d
from tests.conftest import TOLERANCE
from tests.solver.test_harmonics import _random_real_coefficients


def _rotate_coefficients(coeffs: torch.Tensor, degrees: tuple[int, ...], rotation: torch.Tensor) -> torch.Tensor:
    """Coefficients of ``L_R f``, ``(L_R f)(x) = f(R^T x)``: ``sum_n D^l_mn(R) S_l^n``.

    ``D^l_mn = exp(-i m alpha) d^l_mn(beta) exp(-i n gamma)``, the convention of :mod:`dpcn_med.solver.wigner`.
    """
    alpha, beta, gamma = matrix_to_euler_zyz(rotation).tolist()
    top = max(degrees)
    orders = torch.arange(-top, top + 1, dtype=torch.float64)
    d = wigner_d(degrees, torch.tensor([beta], dtype=torch.float64))[:, 0].to(torch.complex128)
    big_d = torch.exp(-1j * orders[:, None] * alpha) * d * torch.exp(-1j * orders[None, :] * gamma)
    return torch.einsum("lmn,bln->blm", big_d, coeffs)


def _analytic_pair(bandwidth: int, rotation: torch.Tensor, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Band-limited real spheres ``(fixed, moving)`` with ``moving = L_R fixed``, on the SOFT grid."""
    degrees = even_degrees(bandwidth)
    coeffs = _random_real_coefficients(degrees, seed)
    return isht(coeffs, degrees, bandwidth), isht(_rotate_coefficients(coeffs, degrees, rotation), degrees, bandwidth)


class TestSO3Correlation:
    def test_equals_the_direct_sum_over_all_betas_and_orders(self, device, dtype):
        bandwidth = 6
        degrees = even_degrees(bandwidth)
        generator = torch.Generator().manual_seed(0)
        spheres = torch.randn(2, 3, 2 * bandwidth, 2 * bandwidth, generator=generator, dtype=torch.float64)
        first, second = sht(spheres[0], degrees), sht(spheres[1], degrees)  # a batch of 3
        _, betas, _ = euler_grid(bandwidth, dtype=torch.float64)
        d = wigner_d(degrees, betas)  # (L, 2B, M, N)
        spectrum = torch.einsum("lkmn,blm,bln->bkmn", d.to(torch.complex128), first, second.conj())
        top = max(degrees)
        padded = torch.zeros(3, 2 * bandwidth, 2 * bandwidth, 2 * bandwidth, dtype=torch.complex128)
        orders = torch.remainder(torch.arange(-top, top + 1), 2 * bandwidth)
        padded[:, :, orders[:, None], orders[None, :]] = spectrum
        direct = torch.fft.ifft2(padded, norm="forward").real.permute(0, 2, 1, 3)
        direct = direct / (first.abs().square().sum((1, 2)).sqrt() * second.abs().square().sum((1, 2)).sqrt())[
            :, None, None, None]
        complex_dtype = torch.complex64 if dtype == torch.float32 else torch.complex128
        ours = so3_correlation(first.to(device, complex_dtype), second.to(device, complex_dtype), bandwidth)
        assert ours.device.type == device.type and ours.dtype == dtype
        torch.testing.assert_close(ours.cpu().double(), direct, atol=TOLERANCE[dtype], rtol=0)

    @pytest.mark.parametrize("seed", range(4))
    def test_peaks_at_the_rotation_of_an_analytic_band_limited_sphere(self, seed):
        bandwidth = 16
        rotation = random_rotation(1, torch.Generator().manual_seed(seed))[0]
        fixed, moving = _analytic_pair(bandwidth, rotation, seed)
        degrees = even_degrees(bandwidth)
        correlation = so3_correlation(sht(moving, degrees), sht(fixed, degrees), bandwidth)
        peaks = so3_peaks(correlation, 4)
        cells = grid_rotations(bandwidth, peaks[0].double())
        # The function has only even degrees, so R and R composed with some half-turn tie; one peak must be R.
        best = geodesic_distance(cells, rotation).min()
        assert math.degrees(best.item()) < 360 / (2 * bandwidth)  # within one grid cell

    @pytest.mark.parametrize("seed", range(4))
    def test_refinement_recovers_the_rotation_within_a_degree(self, seed):
        bandwidth = 16
        rotation = random_rotation(1, torch.Generator().manual_seed(10 + seed))[0]
        fixed, moving = _analytic_pair(bandwidth, rotation, seed)
        degrees = even_degrees(bandwidth)
        correlation = so3_correlation(sht(moving, degrees), sht(fixed, degrees), bandwidth)
        start, _ = soft_argmax_so3(correlation, so3_peaks(correlation, 4), 0.01)
        weights = quadrature_weights(bandwidth, dtype=torch.float64)
        directions = sphere_directions(bandwidth, dtype=torch.float64)
        fine = isht(sht(fixed, degrees), degrees, 2 * bandwidth)
        refined, score = refine_rotation(moving, fine, weights, directions, start, step=math.pi / bandwidth,
                                         iterations=8)
        errors = geodesic_distance(refined[0], rotation)
        assert math.degrees(errors.min().item()) < 1.0
        assert score[0, errors.argmin()].item() > 0.98

    def test_gradcheck_wrt_both_spheres(self):
        bandwidth = 6
        degrees = even_degrees(bandwidth)
        generator = torch.Generator().manual_seed(1)
        fixed = torch.randn(1, 12, 12, generator=generator, dtype=torch.float64, requires_grad=True)
        moving = torch.randn(1, 12, 12, generator=generator, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(
            lambda f, m: so3_correlation(sht(m, degrees), sht(f, degrees), bandwidth), (fixed, moving))


def _bump(bandwidth: int, centre: torch.Tensor, width: float) -> torch.Tensor:
    """A correlation grid ``exp(-angle(R, centre)^2 / width^2)``: ``(1, 2B, 2B, 2B)``."""
    index = torch.stack(torch.meshgrid(*[torch.arange(2 * bandwidth)] * 3, indexing="ij"), -1).double()
    angle = geodesic_distance(grid_rotations(bandwidth, index), centre)
    return torch.exp(-(angle / width) ** 2)[None]


class TestSoftArgmaxSO3:
    @pytest.mark.parametrize("angles", [(0.02, 1.3, 6.27), (2.0, 0.05, 1.0), (4.0, 3.1, 0.5)],
                             ids=["alpha-gamma wrap", "north pole", "south pole"])
    def test_expectation_respects_periodicity_and_the_poles(self, angles):
        bandwidth = 16
        centre = euler_zyz_to_matrix(torch.tensor(angles, dtype=torch.float64))
        correlation = _bump(bandwidth, centre, math.radians(10.0))
        rotation, mass = soft_argmax_so3(correlation, so3_peaks(correlation, 1), 0.05)
        # Never worse than the arg-max cell, and well inside it.
        argmax_cell = grid_rotations(bandwidth, so3_peaks(correlation, 1)[0, 0].double())
        error = geodesic_distance(rotation[0, 0], centre).item()
        assert error <= geodesic_distance(argmax_cell, centre).item() + 1e-5
        assert math.degrees(error) < 0.3 * 360 / (2 * bandwidth)  # under a third of a grid cell
        assert 0.0 < mass.item() <= 1.0

    def test_gradcheck_wrt_correlation_and_temperature(self):
        bandwidth = 4
        centre = euler_zyz_to_matrix(torch.tensor([1.0, 1.2, 2.0], dtype=torch.float64))
        correlation = (_bump(bandwidth, centre, 0.5) + 0.01 * torch.randn(
            1, 8, 8, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64)).requires_grad_()
        temperature = torch.tensor(0.1, dtype=torch.float64, requires_grad=True)
        peaks = so3_peaks(correlation.detach(), 2)
        assert torch.autograd.gradcheck(lambda c, t: soft_argmax_so3(c, peaks, t), (correlation, temperature))

    def test_log_prob_is_normalised_and_haar_weighted(self):
        correlation = torch.zeros(1, 8, 8, 8, dtype=torch.float64)
        probability = so3_log_prob(correlation, 0.1).exp()
        assert probability.sum().item() == pytest.approx(1.0)
        _, beta, _ = euler_grid(4, dtype=torch.float64)
        per_beta = probability.sum((0, 1, 3))
        torch.testing.assert_close(per_beta / per_beta.sum(), beta.sin() / beta.sin().sum())


class TestPeaks:
    def test_finds_two_peaks_including_one_across_the_wrap(self):
        correlation = torch.zeros(1, 8, 8, 8)
        correlation[0, 0, 3, 7] = 2.0
        correlation[0, 7, 3, 0] = 1.5  # neighbours of the first across both wraps, but lower
        correlation[0, 4, 5, 2] = 1.0
        peaks = so3_peaks(correlation, 2)
        assert peaks[0].tolist() == [[0, 3, 7], [4, 5, 2]]


class TestSphereCorrelation:
    def test_matches_the_grid_correlation_at_grid_rotations(self):
        bandwidth = 8
        degrees = even_degrees(bandwidth)
        fixed = isht(_random_real_coefficients(degrees, 4), degrees, bandwidth)
        moving = isht(_random_real_coefficients(degrees, 5), degrees, bandwidth)
        fixed_coeffs, moving_coeffs = sht(fixed, degrees), sht(moving, degrees)
        grid = so3_correlation(moving_coeffs, fixed_coeffs, bandwidth)
        cells = torch.randint(0, 2 * bandwidth, (5, 3), generator=torch.Generator().manual_seed(4))
        fine = isht(fixed_coeffs, degrees, 8 * bandwidth)  # finely sampled, so interpolation error is small
        values = sphere_correlation(moving, fine, quadrature_weights(bandwidth, dtype=torch.float64),
                                    sphere_directions(bandwidth, dtype=torch.float64),
                                    grid_rotations(bandwidth, cells.double())[None])
        # sphere_correlation is the mean over the sphere (integral / 4 pi); the grid is normalised by the norms.
        norms = moving_coeffs.abs().square().sum().sqrt() * fixed_coeffs.abs().square().sum().sqrt()
        expected = grid[0, cells[:, 0], cells[:, 1], cells[:, 2]] * norms / (4 * math.pi)
        torch.testing.assert_close(values[0], expected, atol=2e-3 * norms.item(), rtol=0)


class TestDeduplicate:
    def test_keeps_the_best_of_near_duplicates(self):
        base = random_rotation(2, torch.Generator().manual_seed(6))
        near = base[0] @ axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.radians(5.0)], dtype=torch.float64))
        rotation = torch.stack([base[0], near, base[1]])[None]
        keep = deduplicate(rotation, torch.tensor([[0.5, 0.9, 0.1]], dtype=torch.float64), math.radians(10.0))
        assert keep[0].tolist() == [False, True, True]
