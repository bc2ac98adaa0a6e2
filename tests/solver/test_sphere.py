"""Step 2: the SOFT sphere grid, its quadrature, radial aggregation and interpolation."""

from __future__ import annotations

import math

import pytest
import torch

from dpcn_med.geometry import random_rotation, warp
from dpcn_med.solver.spectrum import magnitude_spectrum
from dpcn_med.solver.sphere import (
    log_radii,
    normalize_sphere,
    quadrature_weights,
    sample_sphere,
    sphere_angles,
    sphere_directions,
    to_sphere,
)
from tests.conftest import volume_grid


class TestGrid:
    def test_soft_grid_excludes_the_poles(self):
        theta, phi = sphere_angles(4, dtype=torch.float64)
        torch.testing.assert_close(theta[0], torch.tensor(math.pi / 16, dtype=torch.float64))
        torch.testing.assert_close(phi[1], torch.tensor(math.pi / 4, dtype=torch.float64))

    def test_directions_are_unit_vectors(self):
        torch.testing.assert_close(sphere_directions(8, dtype=torch.float64).norm(dim=-1),
                                   torch.ones(16, 16, dtype=torch.float64))


class TestQuadratureWeights:
    def test_sum_to_two(self):
        assert quadrature_weights(16, dtype=torch.float64).sum().item() == pytest.approx(2.0, abs=1e-12)

    def test_integrate_polynomials_in_cos_theta_exactly(self):
        bandwidth = 8
        theta, _ = sphere_angles(bandwidth, dtype=torch.float64)
        weights = quadrature_weights(bandwidth, dtype=torch.float64)
        for power in range(0, 2 * bandwidth - 1):
            exact = 0.0 if power % 2 else 2.0 / (power + 1)
            assert (weights * theta.cos() ** power).sum().item() == pytest.approx(exact, abs=1e-12)


class TestSampleSphere:
    def test_exact_on_grid_points(self):
        sphere = torch.randn(1, 16, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        directions = sphere_directions(8, dtype=torch.float64)[None]
        torch.testing.assert_close(sample_sphere(sphere, directions), sphere)

    def test_smooth_function_is_interpolated_across_the_pole_and_the_phi_seam(self):
        directions = sphere_directions(32, dtype=torch.float64)
        values = (directions @ torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64))[None]
        queries = torch.tensor([[[0.0, 0.0, 1.0], [1.0, -1e-3, 0.0], [0.1, 0.1, -0.99]]], dtype=torch.float64)
        queries = queries / queries.norm(dim=-1, keepdim=True)
        expected = queries[0] @ torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
        torch.testing.assert_close(sample_sphere(values, queries)[0], expected, atol=5e-3, rtol=0)


class TestToSphere:
    def test_rotating_the_volume_rotates_the_sphere(self):
        volume = volume_grid("mni", 64, torch.float64)
        rotation = random_rotation(1, torch.Generator().manual_seed(1))
        moving = warp(volume, rotation.transpose(-1, -2))  # moving(q) = volume(R^T q): fixed(p) = moving(R p)
        radii = log_radii(64, (0.05, 0.6), 24, dtype=torch.float64)
        weights = quadrature_weights(16, dtype=torch.float64)
        directions = sphere_directions(16, dtype=torch.float64)
        fixed_sphere = normalize_sphere(to_sphere(magnitude_spectrum(volume[:, 0], 3, 0.25), directions[None], radii),
                                        weights)
        # s_fixed(u) = s_moving(R u): sample the moving spectrum along the rotated directions.
        rotated = torch.einsum("ij,...j->...i", rotation[0], directions)
        moving_sphere = normalize_sphere(to_sphere(magnitude_spectrum(moving[:, 0], 3, 0.25), rotated[None], radii),
                                         weights)
        correlation = (fixed_sphere * moving_sphere * weights[:, None]).sum() / (weights.sum() * 32)
        assert correlation.item() > 0.95

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    @pytest.mark.parametrize("bandwidth", [4, 8, 16, 32])
    @pytest.mark.parametrize("value", [1.0, 3.0, -87.3365])  # -87.3: an empty volume's floored log in float32
    def test_constant_sphere_normalises_to_zero(self, dtype, bandwidth, value):
        """Rounding left by the centring was scaled to unit norm: up to 0.99 at B = 32, where 0 was promised."""
        weights = quadrature_weights(bandwidth, dtype=dtype)
        constant = torch.full((1, 2 * bandwidth, 2 * bandwidth), value, dtype=dtype)
        assert normalize_sphere(constant, weights).abs().max() < 10 * torch.finfo(dtype).eps ** 0.5
