"""Step 7: the six DPCN++ loss terms, and that they train features end to end through the solver."""

from __future__ import annotations

import math

import pytest
import torch

from dpcn_med.geometry import axis_angle_to_matrix, random_rotation
from dpcn_med.solver import PoseTarget, StageTemperatures, Temperatures, pose_loss, solve
from dpcn_med.solver.losses import rotation_kl, shift_kl
from dpcn_med.solver.so3 import grid_rotations, so3_log_prob
from dpcn_med.synth import random_poses
from tests.conftest import volume_grid


class TestShiftKL:
    def test_zero_for_the_matching_gaussian_and_positive_otherwise(self):
        sizes = (9, 10)
        target = torch.tensor([[1.0, -2.0]], dtype=torch.float64)
        y, x = torch.meshgrid(torch.arange(9.0) - 4, torch.arange(10.0) - 5, indexing="ij")
        logits = -((x - 1.0) ** 2 + (y + 2.0) ** 2) / 2
        log_prob = (logits - torch.logsumexp(logits.flatten(), 0))[None].double()
        straight = (False, False)
        assert shift_kl(log_prob, target, 1.0, periodic=straight).item() == pytest.approx(0.0, abs=1e-6)
        assert shift_kl(log_prob, target + 2.0, 1.0, periodic=straight).item() > 0.5
        assert log_prob.shape[1:] == sizes

    def test_distances_wrap_on_periodic_axes(self):
        logits = torch.full((1, 16), -30.0, dtype=torch.float64)
        logits[0, 0] = 0.0  # all mass at shift -8, next to +7 across the wrap
        log_prob = logits - torch.logsumexp(logits, -1, keepdim=True)
        near = shift_kl(log_prob, torch.tensor([[7.0]], dtype=torch.float64), 1.0)
        far = shift_kl(log_prob, torch.tensor([[0.0]], dtype=torch.float64), 1.0)
        assert near.item() < far.item()
        assert shift_kl(log_prob, torch.tensor([[7.0]], dtype=torch.float64), 1.0, periodic=(False,)).item() > \
            near.item()


class TestRotationKL:
    def test_lower_at_the_true_rotation(self):
        bandwidth = 6
        truth = random_rotation(1, torch.Generator().manual_seed(30))
        index = torch.stack(torch.meshgrid(*[torch.arange(12)] * 3, indexing="ij"), -1).double()
        from dpcn_med.geometry import geodesic_distance
        correlation = torch.cos(geodesic_distance(grid_rotations(bandwidth, index), truth[0]))[None]
        log_prob = so3_log_prob(correlation, 0.05)
        wrong = truth @ axis_angle_to_matrix(torch.tensor([0.0, math.pi / 2, 0.0], dtype=torch.float64))
        right_kl = rotation_kl(log_prob, truth, math.radians(15.0))
        assert right_kl.item() < 0.5 * rotation_kl(log_prob, wrong, math.radians(15.0)).item()


class TestPoseLoss:
    def test_terms_are_finite_and_the_total_uses_the_paper_weights(self):
        size = 16
        fixed = volume_grid("mni", size, torch.float64)
        pose = random_poses(1, size, seed=31)[0]
        result = solve(fixed, pose.moving_from(fixed), refine=False)
        target = PoseTarget(pose.rotation[None], torch.tensor([pose.scale], dtype=torch.float64),
                            pose.translation[None])
        terms = pose_loss(result, target)
        assert set(terms) == {"rotation_kl", "rotation_l1", "translation_kl", "translation_l1", "scale_kl",
                              "scale_l1", "total"}
        assert all(torch.isfinite(value) for value in terms.values())
        paper = {"rotation_kl": 1, "rotation_l1": 3, "translation_kl": 3, "translation_l1": 1, "scale_kl": 1,
                 "scale_l1": 3}
        torch.testing.assert_close(terms["total"], sum(weight * terms[name] for name, weight in paper.items()))

    def test_every_term_is_smallest_at_the_true_pose(self):
        size = 32
        fixed = volume_grid("mni", size, torch.float64)
        pose = random_poses(1, size, seed=35)[0]
        result = solve(fixed, pose.moving_from(fixed), refine=False)

        def terms_for(rotation, scale, translation):
            return pose_loss(result, PoseTarget(rotation[None], torch.tensor([scale], dtype=torch.float64),
                                                translation[None]))

        true = terms_for(pose.rotation, pose.scale, pose.translation)
        turned = pose.rotation @ axis_angle_to_matrix(torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64))
        wrong = {"rotation": terms_for(turned, pose.scale, pose.translation),
                 "scale": terms_for(pose.rotation, pose.scale * 1.1, pose.translation),
                 "translation": terms_for(pose.rotation, pose.scale, pose.translation + 3.0)}
        for stage, terms in wrong.items():
            for kind in ("kl", "l1"):
                name = f"{stage}_{kind}"
                assert true[name].item() < terms[name].item(), name

    def test_rigid_mode_has_zero_scale_terms(self):
        fixed = volume_grid("mni", 16, torch.float64)
        pose = random_poses(1, 16, seed=32, similarity=False)[0]
        result = solve(fixed, pose.moving_from(fixed), "rigid", refine=False)
        terms = pose_loss(result, PoseTarget(pose.rotation[None], torch.ones(1, dtype=torch.float64),
                                             pose.translation[None]))
        assert terms["scale_kl"].item() == 0.0 and terms["scale_l1"].item() == 0.0


class TestTemperatures:
    def test_positive_initialised_and_learnable(self):
        module = Temperatures(StageTemperatures(rotation=0.03, scale=0.5, translation=2.0))
        values = module()
        assert values.rotation.item() == pytest.approx(0.03, rel=1e-5)
        assert values.translation.item() == pytest.approx(2.0, rel=1e-5)
        (values.rotation + values.scale + values.translation).backward()
        assert all(parameter.grad is not None for parameter in module.parameters())
        with torch.no_grad():
            for parameter in module.parameters():
                parameter.fill_(-50.0)
        assert (torch.stack([module().rotation, module().scale]) > 0).all()


class TestEndToEndTraining:
    def test_pose_loss_decreases_when_features_and_temperatures_are_trained(self):
        torch.manual_seed(33)
        size = 16
        fixed = volume_grid("mni", size)
        poses = random_poses(2, size, seed=34)
        moving = torch.cat([pose.moving_from(fixed) for pose in poses])
        fixed = fixed.expand(2, -1, -1, -1, -1)
        target = PoseTarget(torch.stack([p.rotation for p in poses]).float(),
                            torch.tensor([p.scale for p in poses]), torch.stack([p.translation for p in poses]).float())
        features = torch.nn.Conv3d(1, 1, 3, padding=1)
        temperatures = Temperatures()
        optimiser = torch.optim.Adam([*features.parameters(), *temperatures.parameters()], lr=3e-2)
        losses = []
        for _ in range(12):
            result = solve(features(fixed), features(moving), refine=False, temperatures=temperatures())
            loss = pose_loss(result, target)["total"]
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            losses.append(loss.item())
        assert sum(losses[-3:]) / 3 < 0.9 * sum(losses[:3]) / 3
