"""2-D: rotation (modulo half a turn) and scale from one log-polar phase correlation."""

from __future__ import annotations

import math

import pytest
import torch

from dpcn_med.geometry import rotation_2d
from dpcn_med.solver.log_polar import log_polar, log_polar_rotation_scale
from dpcn_med.solver.spectrum import magnitude_spectrum
from dpcn_med.solver.sphere import log_radii
from dpcn_med.synth import Pose
from tests.conftest import axial_slice


class TestLogPolar:
    def test_shape_and_a_radial_spectrum_is_constant_in_angle(self):
        x = torch.arange(64, dtype=torch.float64) - 32
        radial = torch.exp(-(x[None, :] ** 2 + x[:, None] ** 2) / 50.0)[None]
        values = log_polar(radial, 90, log_radii(64, (0.05, 0.5), 20, dtype=torch.float64))
        assert values.shape == (1, 90, 20)
        assert (values.std(dim=1) / values.abs().mean()).max() < 2e-2  # bilinear interpolation error only


class TestLogPolarRotationScale:
    @pytest.mark.parametrize("angle,scale", [(30.0, 1.15), (-75.0, 0.85), (160.0, 1.0)])
    def test_recovers_angle_modulo_half_a_turn_and_scale(self, angle, scale):
        fixed = axial_slice("mni", 256, torch.float64)
        rotation = rotation_2d(torch.tensor(math.radians(angle), dtype=torch.float64))
        moving = Pose(rotation, scale, torch.tensor([5.0, -3.0], dtype=torch.float64)).moving_from(fixed)
        estimate = log_polar_rotation_scale(
            magnitude_spectrum(fixed[:, 0], 2, 0.25), magnitude_spectrum(moving[:, 0], 2, 0.25),
            (0.03, 0.9), 256, 360, 0.01, refine=True, upsample=16)
        difference = (math.degrees(estimate.angle.item()) - angle + 90) % 180 - 90
        assert abs(difference) < 0.5
        assert estimate.scale.item() == pytest.approx(scale, rel=0.005)
