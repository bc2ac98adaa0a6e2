"""Step 4: scale from the log-radius correlation of rotation-compensated spectra."""

from __future__ import annotations

import pytest
import torch

from dpcn_med.geometry import random_rotation
from dpcn_med.solver.scale import detrend, log_polar_scale
from dpcn_med.solver.spectrum import magnitude_spectrum
from dpcn_med.synth import Pose
from tests.conftest import volume_grid


class TestDetrend:
    def test_removes_a_line_and_keeps_the_rest(self):
        x = torch.linspace(-1, 1, 50, dtype=torch.float64)
        wiggle = torch.sin(7 * x)
        wiggle = detrend(wiggle)
        torch.testing.assert_close(detrend(3.0 + 2.0 * x + wiggle), wiggle)


def _scale_of(fixed: torch.Tensor, moving: torch.Tensor, rotation: torch.Tensor, refine: bool = True,
              temperature: torch.Tensor | float = 0.02, max_scale: float = 2.0) -> torch.Tensor:
    estimate = log_polar_scale(magnitude_spectrum(fixed[:, 0], 3, 0.25), magnitude_spectrum(moving[:, 0], 3, 0.25),
                               rotation[None, None].to(fixed.dtype), (0.05, 0.8), 64, temperature,
                               directions_bandwidth=8, max_scale=max_scale, refine=refine, upsample=16)
    return estimate.scale[0, 0]


class TestLogPolarScale:
    @pytest.mark.parametrize("scale", [0.8, 0.93, 1.2])
    def test_recovers_the_scale_of_anatomy_given_the_rotation(self, scale):
        fixed = volume_grid("mni", 64, torch.float64)
        rotation = random_rotation(1, torch.Generator().manual_seed(7))[0]
        moving = Pose(rotation, scale, torch.tensor([2.0, -1.0, 3.0], dtype=torch.float64)).moving_from(fixed)
        assert _scale_of(fixed, moving, rotation).item() == pytest.approx(scale, rel=0.01)

    @pytest.mark.parametrize("scale", [0.7, 1.4])
    @pytest.mark.parametrize("refine", [True, False])
    def test_the_estimate_stays_within_max_scale(self, scale, refine):
        """The window ended at whole lags and the sub-grid peak went past it: 1.2 gave up to 1.30."""
        fixed = volume_grid("mni", 64, torch.float64)
        eye = torch.eye(3, dtype=torch.float64)
        moving = Pose(eye, scale, torch.zeros(3, dtype=torch.float64)).moving_from(fixed)
        estimate = _scale_of(fixed, moving, eye, refine=refine, max_scale=1.2).item()
        assert 1 / 1.2 <= estimate <= 1.2

    def test_soft_estimate_is_close_to_the_refined_one(self):
        fixed = volume_grid("mni", 64, torch.float64)
        moving = Pose(torch.eye(3, dtype=torch.float64), 1.1, torch.zeros(3, dtype=torch.float64)).moving_from(fixed)
        eye = torch.eye(3, dtype=torch.float64)
        assert _scale_of(fixed, moving, eye, refine=False).item() == pytest.approx(
            _scale_of(fixed, moving, eye).item(), rel=0.01)

    def test_gradcheck_wrt_volumes_and_temperature(self):
        generator = torch.Generator().manual_seed(8)
        fixed = torch.nn.functional.avg_pool3d(torch.randn(1, 1, 16, 16, 16, generator=generator,
                                                           dtype=torch.float64), 3, 1, 1)
        moving = (fixed.roll(1, -1) + 0.1 * fixed).requires_grad_()
        temperature = torch.tensor(0.05, dtype=torch.float64, requires_grad=True)
        eye = torch.eye(3, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda f, m, t: _scale_of(f, m, eye, refine=False, temperature=t),
                                        (fixed.requires_grad_(), moving, temperature), fast_mode=True)
