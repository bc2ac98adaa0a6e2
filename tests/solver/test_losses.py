"""Step 7: the six DPCN++ loss terms, and that they train features end to end through the solver."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dpcn_med.errors import InputError
from dpcn_med.geometry import axis_angle_to_matrix, geodesic_distance, half_turns, random_rotation
from dpcn_med.solver import LossWeights, PoseTarget, StageTemperatures, Temperatures, pose_loss, solve
from dpcn_med.solver.losses import rotation_kl, shift_kl, twins
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
        correlation = torch.cos(geodesic_distance(grid_rotations(bandwidth, index), truth[0]))[None]
        log_prob = so3_log_prob(correlation, 0.05)
        wrong = truth @ axis_angle_to_matrix(torch.tensor([0.0, math.pi / 2, 0.0], dtype=torch.float64))
        right_kl = rotation_kl(log_prob, truth, math.radians(15.0))
        assert right_kl.item() < 0.5 * rotation_kl(log_prob, wrong, math.radians(15.0)).item()


    def test_twin_aware_target_does_not_penalise_a_half_turn_twin(self):
        bandwidth = 6
        truth = random_rotation(1, torch.Generator().manual_seed(31))
        twin = truth @ half_turns(torch.device("cpu"), torch.float64)[2]  # a half-turn about the fixed grid's y
        index = torch.stack(torch.meshgrid(*[torch.arange(12)] * 3, indexing="ij"), -1).double()
        log_prob = so3_log_prob(torch.cos(geodesic_distance(grid_rotations(bandwidth, index), twin[0]))[None], 0.05)
        sigma = math.radians(15.0)
        plain = rotation_kl(log_prob, truth, sigma)
        aware = rotation_kl(log_prob, truth, sigma, with_twins=True)
        assert aware.item() < 0.25 * plain.item()
        # At the truth itself it is the plain KL: the distribution need not cover the twins too (a mixture target
        # asked for that, and a sharp peak at the truth cost 26 nats).
        at_truth = so3_log_prob(torch.cos(geodesic_distance(grid_rotations(bandwidth, index), truth[0]))[None], 0.05)
        torch.testing.assert_close(rotation_kl(at_truth, truth, sigma, with_twins=True),
                                   rotation_kl(at_truth, truth, sigma))
        torch.testing.assert_close(aware, rotation_kl(log_prob, twin, sigma))

    def test_twins_are_the_seven_half_turn_variants(self):
        truth = random_rotation(2, torch.Generator().manual_seed(32))
        variants = twins(truth)
        assert variants.shape == (2, 7, 3, 3)
        torch.testing.assert_close(variants[:, 0], truth)
        angles = torch.rad2deg(geodesic_distance(variants, truth[:, None]))
        torch.testing.assert_close(angles[:, 1:], torch.full((2, 6), 180.0, dtype=torch.float64), rtol=0, atol=1e-4)


class TestLossWeights:
    def test_defaults_and_numpy_values(self):
        assert LossWeights(scale_l1=np.float32(3.0), shift_sigma=np.int64(1)) == LossWeights()
        assert type(LossWeights(scale_l1=np.float32(3.0)).scale_l1) is float

    @pytest.mark.parametrize(("field", "value", "message"), [
        ("rotation_sigma", 0.0, r"rotation_sigma is 0\.0; expected a finite number >= 1e-06"),  # was a NaN rotation_kl
        ("shift_sigma", 0.0, r"shift_sigma is 0\.0; expected a finite number >= 1e-06"),  # was NaN shift terms
        ("rotation_sigma", -0.1, r"rotation_sigma is -0\.1; expected a finite number >= 1e-06"),
        ("shift_sigma", 1e-20, r"shift_sigma is 1e-20; expected a finite number >= 1e-06"),  # -inf everywhere: NaN
        ("rotation_l1", float("nan"), r"rotation_l1 is nan; expected a finite number >= 0"),  # was a NaN total
        ("rotation_kl", -5.0, r"rotation_kl is -5\.0; expected a finite number >= 0"),  # rewarded a worse match
        ("scale_kl", "1", r"scale_kl is '1' \(str\); expected a finite number >= 0"),
        ("candidate_ranking", -1.0, r"candidate_ranking is -1\.0; expected a finite number >= 0"),
        ("candidate_degrees", 0.0, r"candidate_degrees is 0\.0; expected a finite number > 0"),
        ("candidate_degrees", 200.0, r"candidate_degrees is 200\.0; expected a finite number > 0 and <= 180"),
        ("rotation_twins", 1, r"rotation_twins"),
    ])
    def test_bad_values_are_refused(self, field, value, message):
        with pytest.raises(InputError, match=message):
            LossWeights(**{field: value})


class TestPoseTarget:
    @staticmethod
    def _target(**changes) -> PoseTarget:
        values = {"rotation": torch.eye(3)[None].expand(2, 3, 3), "scale": torch.tensor([1.1, 0.9]),
                  "translation": torch.zeros(2, 3)}
        return PoseTarget(**{**values, **changes})

    def test_a_good_target_is_kept_as_given(self):
        scale = torch.tensor([1.1, 0.9], dtype=torch.float64)
        assert self._target(scale=scale).scale is scale

    @pytest.mark.parametrize(("changes", "message"), [
        ({"scale": torch.tensor([1.0, 0.0])}, r"target scale\[1\] is 0\.0; expected a scale > 0"),  # was NaN terms
        ({"scale": torch.tensor([-1.0, 1.0])}, r"target scale\[0\] is -1\.0; expected a scale > 0"),
        ({"scale": torch.tensor([1.0, float("nan")])}, r"target scale holds NaN or Inf values"),
        ({"translation": torch.full((2, 3), float("inf"))}, r"target translation holds NaN or Inf values"),
        ({"scale": torch.ones(2, 1)}, r"target scale has shape \(2, 1\); expected a tensor of shape \(batch,\)"),
        ({"scale": torch.ones(3)}, r"target scale has shape \(3,\); expected a batch of 2, as the rotation "
                                   r"\(2, 3, 3\)"),
        ({"translation": torch.zeros(2, 2)}, r"target translation has shape \(2, 2\); expected a tensor of shape "
                                             r"\(batch, 3\)"),
        ({"rotation": torch.eye(3)}, r"target rotation has shape \(3, 3\); expected a tensor of shape \(batch, 3, 3\)"),
        ({"scale": 1.0}, r"target scale is 1\.0 \(float\); expected a tensor of shape \(batch,\)"),
        ({"rotation": torch.zeros(0, 3, 3)}, r"target rotation holds no poses \(shape \(0, 3, 3\)\)"),
    ])
    def test_bad_targets_are_refused(self, changes, message):
        with pytest.raises(InputError, match=message):
            self._target(**changes)

    def test_values_off_the_cpu_are_not_read(self):  # reading them would synchronise a GPU every training step
        target = self._target(scale=torch.empty(2, device="meta"))
        assert target.scale.device.type == "meta"


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
        initial = {"rotation": 0.03, "scale": 0.5, "translation": 2.0}
        weights = {"rotation": 1.0, "scale": 2.0, "translation": 3.0}  # one per stage: each gradient is told apart
        module = Temperatures(StageTemperatures(**initial))
        values = module()
        for name, value in initial.items():
            assert getattr(values, name).item() == pytest.approx(value, rel=1e-5), name
        sum(weight * getattr(values, name) for name, weight in weights.items()).backward()
        for name, value in initial.items():
            # d softplus(raw) / d raw = sigmoid(raw) = 1 - exp(-softplus(raw))
            assert module.raw[name].grad.item() == pytest.approx(weights[name] * -math.expm1(-value), rel=1e-5), name
        with torch.no_grad():
            for parameter in module.parameters():
                parameter.fill_(-50.0)
        assert (torch.stack([module().rotation, module().scale]) > 0).all()

    def test_a_temperature_that_softplus_cannot_hold_is_refused(self):  # softplus gave exactly 0.0 for 1e-50
        with pytest.raises(InputError, match=r"translation temperature is 1e-50; expected a finite number >= 1e-12"):
            Temperatures(StageTemperatures(translation=1e-50))


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
