"""Known poses for synthetic pairs."""

from __future__ import annotations

import math

import pytest
import torch

from dpcn_med.errors import InputError
from dpcn_med.geometry import grid_centre, rotation_angle, rotation_z, warp
from dpcn_med.synth import Pose, random_poses


class TestPose:
    def test_moving_from_satisfies_the_solver_contract(self):
        # fixed(p) = moving(A p + t): warping the moving grid back by the pose reproduces the fixed one.
        fixed = torch.zeros(1, 1, 24, 24, 24, dtype=torch.float64)
        c = grid_centre(24)
        fixed[0, 0, c - 3:c + 1, c - 2:c + 5, c - 1:c + 3] = 1.0
        pose = Pose(rotation_z(torch.tensor(math.pi / 2, dtype=torch.float64)), 1.0,
                    torch.tensor([2.0, -1.0, 1.0], dtype=torch.float64))
        moving = pose.moving_from(fixed)
        back = warp(moving, pose.rotation[None], pose.translation[None])
        torch.testing.assert_close(back, fixed, atol=1e-9, rtol=0)

    def test_moving_from_follows_the_volume_dtype(self):
        pose = random_poses(1, 16, seed=1)[0]
        single = Pose(pose.rotation.float(), pose.scale, pose.translation.float())
        fixed = torch.rand(1, 1, 16, 16, 16, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
        moving = single.moving_from(fixed)
        assert moving.dtype == torch.float64
        # The float32 pose, widened, is the pose used.
        widened = Pose(single.rotation.double(), single.scale, single.translation.double())
        torch.testing.assert_close(moving, widened.moving_from(fixed), rtol=0, atol=0)

    def test_moving_from_follows_the_volume_device(self):
        # Host poses with a volume elsewhere (CUDA in benchmarks/solver_speed.py; 'meta' here) failed in grid_sample.
        fixed = torch.zeros(2, 1, 16, 16, 16, dtype=torch.float64, device="meta")
        moving = random_poses(1, 16, seed=1)[0].moving_from(fixed)
        assert moving.device.type == "meta" and moving.dtype == torch.float64 and moving.shape == fixed.shape

    def test_errors_of_an_exact_and_of_a_wrong_estimate(self):
        pose = random_poses(1, 64, seed=0)[0]
        assert pose.errors(pose.rotation, pose.scale, pose.translation) == pytest.approx((0.0, 0.0, 0.0), abs=1e-6)
        turned = pose.rotation @ rotation_z(torch.tensor(0.1, dtype=torch.float64))
        rotation_error, translation_error, scale_error = pose.errors(turned, pose.scale * 1.1,
                                                                     pose.translation + 3.0)
        assert rotation_error == pytest.approx(math.degrees(0.1))
        assert translation_error == pytest.approx(3.0 * math.sqrt(3))
        assert scale_error == pytest.approx(0.1)


class TestRandomPoses:
    def test_reproducible_and_within_range(self):
        first, second = random_poses(20, 64, seed=3), random_poses(20, 64, seed=3)
        for a, b in zip(first, second):
            torch.testing.assert_close(a.rotation, b.rotation)
        assert all(0.8 <= p.scale <= 1.2 for p in first)
        assert all(p.translation.norm() <= 0.2 * 64 for p in first)
        assert max(rotation_angle(p.rotation).item() for p in first) > math.radians(120)

    def test_two_dimensional_and_rigid(self):
        poses = random_poses(5, 256, seed=4, dim=2, similarity=False, max_shift=50.0)
        assert all(p.rotation.shape == (2, 2) and p.scale == 1.0 for p in poses)
        assert all(p.translation.norm() <= 50.0 for p in poses)

    @pytest.mark.parametrize("options,message", [
        ({"count": -3}, "^count is -3; expected an integer >= 0$"),
        ({"size": 0}, "^size is 0; expected an integer >= 1$"),
        ({"dim": 4}, "^dim is 4; expected an integer >= 2 and <= 3$"),
        ({"similarity": "yes"}, r"^similarity is 'yes' \(str\); expected True or False$"),
        ({"max_shift": math.nan}, "^max_shift is nan; expected a finite number >= 0$"),
        ({"max_shift": -1.0}, "^max_shift is -1.0; expected a finite number >= 0$"),
        ({"scale_range": (-1.0, -0.5)}, r"^scale_range is \(-1.0, -0.5\); expected \(low, high\) with 0 < low"),
        ({"scale_range": (1.2, 0.8)}, r"^scale_range is \(1.2, 0.8\); expected \(low, high\) with 0 < low <= high$"),
        ({"scale_range": (0.8, math.inf)}, r"^scale_range\[1\] is inf; expected a finite number$"),
        ({"seed": -1}, r"^seed is -1; expected an integer >= 0 and <= 9223372036854775807$"),
        ({"seed": 1.5}, r"^seed is 1.5 \(float\); expected an integer >= 0"),
    ])
    def test_invalid_arguments(self, options, message):
        arguments = {"count": 2, "size": 32, "seed": 0} | options
        with pytest.raises(InputError, match=message):
            random_poses(**arguments)
