"""Known poses for synthetic pairs."""

from __future__ import annotations

import math

import pytest
import torch

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
