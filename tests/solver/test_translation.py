"""Step 5: translation by phase correlation."""

from __future__ import annotations

import torch

from dpcn_med.geometry import warp
from dpcn_med.solver.translation import phase_translation
from tests.conftest import volume_grid


class TestPhaseTranslation:
    def test_recovers_a_sub_voxel_shift_of_anatomy(self, dtype):
        fixed = volume_grid("mni", 32, dtype)
        true = torch.tensor([[2.25, -3.5, 1.75]], dtype=dtype)
        # moving(q) = fixed(q - t), so fixed(p) = moving(p + t)
        moving = warp(fixed, torch.eye(3, dtype=dtype)[None], -true)
        estimate = phase_translation(fixed[:, 0], moving[:, 0], 0.01, dim=3, taper=0.25, refine=True, upsample=16)
        torch.testing.assert_close(estimate.shift, true, atol=0.15, rtol=0)
        assert estimate.peak.mass.item() > 0.9

    def test_gradcheck_of_the_soft_estimate(self):
        generator = torch.Generator().manual_seed(2)
        fixed = torch.nn.functional.avg_pool3d(torch.randn(1, 1, 12, 12, 12, generator=generator,
                                                           dtype=torch.float64), 3, 1, 1)[:, 0]
        moving = fixed.roll((1, -2), (-1, -2))
        temperature = torch.tensor(0.05, dtype=torch.float64, requires_grad=True)

        def shift(f, m, t):
            estimate = phase_translation(f, m, t, dim=3, taper=0.25, refine=False, upsample=16)
            return estimate.shift, estimate.peak.mass

        assert torch.autograd.gradcheck(shift, (fixed.requires_grad_(), moving.requires_grad_(), temperature),
                                        fast_mode=True)
