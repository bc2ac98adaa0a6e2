"""dpcn_med.train.pretrain: the dense cross-modal loss, its band-pass and masks, and pretraining in the loop."""

from __future__ import annotations

import csv
import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from dpcn_med.errors import InputError
from dpcn_med.geometry import axis_angle_to_matrix
from dpcn_med.models import load_model
from dpcn_med.solver import PoseTarget
from dpcn_med.synth import PairConfig, synthetic_pairs
from dpcn_med.train import OptimiserConfig, train
from dpcn_med.train.data import canonical_volume, load_volume
from dpcn_med.train.pretrain import (
    PretrainConfig,
    band_pass,
    decoy_poses,
    dense_similarity,
    masked_ncc,
    pose_contrast,
)
from tests.train.conftest import tiny_config


def _identity(batch: int) -> PoseTarget:
    return PoseTarget(torch.eye(3).expand(batch, 3, 3), torch.ones(batch), torch.zeros(batch, 3))


@pytest.fixture(scope="module")
def head() -> torch.Tensor:
    """The MNI head on the 64^3 canonical grid of bandwidth 32, ``(1, 1, 64, 64, 64)`` (about 20 voxels across)."""
    return canonical_volume(load_volume("mni"), 64)


class TestDenseSimilarity:
    def test_identical_features_score_one_shuffled_ones_about_zero(self, head):
        """The loss (one minus the similarity) is zero for identical features and positive for shuffled ones."""
        identical = dense_similarity(head, head, head, head, _identity(1))
        assert 1 - identical.item() == pytest.approx(0, abs=1e-5)
        order = torch.randperm(head.numel(), generator=torch.Generator().manual_seed(0))
        shuffled = head.flatten()[order].view_as(head)
        loss = 1 - dense_similarity(head, shuffled, head, head, _identity(1)).item()
        assert 0.8 < loss < 1.2

    def test_the_moving_features_are_warped_back_by_the_pose(self, head):
        generator = torch.Generator().manual_seed(1)
        config = PairConfig(mode="rigid", crop_probability=0.0, fixed_modality="identity", moving_modality="identity")
        fixed, moving, target = synthetic_pairs(head.expand(2, -1, -1, -1, -1), generator, config)
        right = dense_similarity(fixed, moving, fixed, moving, target)
        turned = replace(target, rotation=target.rotation @ axis_angle_to_matrix(
            torch.tensor([[0.0, 0.0, math.pi / 2]]).expand(2, 3)))
        wrong = dense_similarity(fixed, moving, fixed, moving, turned)
        assert (right > 0.8).all() and (wrong < 0.5).all(), (right, wrong)

    def test_a_constant_feature_correlates_with_nothing(self, head):
        assert dense_similarity(torch.ones_like(head), head, head, head, _identity(1)).item() == pytest.approx(0)

    @pytest.mark.parametrize("near_degrees", [0.0, 10.0])
    def test_the_contrast_rewards_features_that_tell_the_pose_from_its_decoys(self, head, near_degrees):
        axis = torch.arange(32.0) - 16  # voxels from the grid centre (dpcn_med.geometry), about which decoys turn
        ball = (axis.view(1, 1, 32, 1, 1) ** 2 + axis.view(1, 1, 1, 32, 1) ** 2 + axis.view(1, 1, 1, 1, 32) ** 2
                < 100).float()
        config = PretrainConfig(erosion_voxels=1, near_degrees=near_degrees)
        poses = 1 + len(decoy_poses(torch.eye(3)[None], near_degrees))
        assert poses == (13 if near_degrees else 7)
        symmetric = pose_contrast(ball, ball, ball, ball, _identity(1), config)  # every decoy is the truth
        assert symmetric.item() == pytest.approx(math.log(poses), abs=0.05)  # interpolation blurs a turned ball
        asymmetric = pose_contrast(head, head, head, head, _identity(1), config)
        assert asymmetric.item() < symmetric.item() - 0.5

    def test_a_few_decoys_drawn_per_step(self, head, monkeypatch):
        from dpcn_med.train import pretrain

        seen = []
        similarity = pretrain._similarity
        monkeypatch.setattr(pretrain, "_similarity", lambda *args: seen.append(args[4]) or similarity(*args))
        generator = torch.Generator().manual_seed(0)
        loss = pose_contrast(head, head, head, head, _identity(1), PretrainConfig(near_degrees=8.0, decoys=3),
                             generator)
        assert len(seen) == 4 and torch.equal(seen[0], torch.eye(3)[None])  # the truth, then three of the twelve
        assert 0 < loss.item() < math.log(4)

    def test_ncc_ignores_gain_and_offset_and_reads_inside_the_mask_only(self):
        first = torch.randn(2, 1, 8, 8, 8, generator=torch.Generator().manual_seed(2))
        mask = torch.zeros_like(first)
        mask[..., 2:6, 2:6, 2:6] = 1
        second = 3 * first + 2 + 100 * (1 - mask) * torch.randn_like(first)  # anything outside the mask
        torch.testing.assert_close(masked_ncc(first, second, mask), torch.ones(2))
        torch.testing.assert_close(masked_ncc(first, -second, mask), -torch.ones(2))


class TestBandPass:
    @pytest.mark.parametrize(("band", "kept"), [((0.1, 0.6), True), ((0.6, 0.9), False), ((0.05, 0.4), False)])
    def test_a_wave_is_kept_only_inside_the_band(self, band, kept):
        """A wave of 0.25 cycles per voxel along x lies at half the Nyquist radius."""
        x = torch.arange(32, dtype=torch.float64)
        wave = torch.cos(2 * math.pi * 0.25 * x).expand(1, 1, 32, 32, 32)
        filtered = band_pass(wave + 5.0, band)  # the constant (radius 0) is below every band here
        torch.testing.assert_close(filtered, wave if kept else torch.zeros_like(wave), atol=1e-9, rtol=0)

    def test_odd_sizes_and_channels(self):
        volume = torch.randn(2, 3, 9, 10, 11, dtype=torch.float64)
        assert band_pass(volume, (0.0, 2.0)).shape == volume.shape
        torch.testing.assert_close(band_pass(volume, (0.0, 2.0)), volume)


class TestConfig:
    @pytest.mark.parametrize(("settings", "message"), [
        ({"steps": -1}, "steps is -1"), ({"band": (0.6, 0.1)}, "band is"), ({"band": (0.1, 3.0)}, "band is"),
        ({"erosion_voxels": -2}, "erosion_voxels"), ({"feature_gain": 0.0}, "feature_gain"),
        ({"contrast_weight": -1.0}, "contrast_weight"), ({"contrast_temperature": 0.0}, "contrast_temperature"),
        ({"near_degrees": 120.0}, "near_degrees")])
    def test_out_of_range_is_named(self, settings, message):
        with pytest.raises(InputError, match=message):
            PretrainConfig(**settings)

    def test_more_pretraining_than_steps_is_refused(self, tmp_path):
        with pytest.raises(InputError, match=r"pretrain.steps is 9; expected at most optimiser.steps \(4\)"):
            tiny_config(tmp_path, pretrain=PretrainConfig(steps=9))

    def test_read_from_yaml(self, tmp_path):
        from dpcn_med.train import load_config
        from tests.train.conftest import TINY_YAML

        path = tmp_path / "pretrain.yaml"
        path.write_text(TINY_YAML + "pretrain: {steps: 2, band: [0.2, 0.7]}\n")
        assert load_config(path).pretrain == PretrainConfig(steps=2, band=(0.2, 0.7))
        path.write_text(TINY_YAML + "pretrain: {steps: 2, band: 0.2}\n")
        with pytest.raises(InputError, match="pretrain.band: expected a list of 2 numbers"):
            load_config(path)


def _rows(folder: Path) -> list[dict]:
    with open(folder / "log.csv", newline="") as handle:
        return [row for row in csv.DictReader(handle) if row["kind"] == "train"]


class TestPretrainingRun:
    def test_the_dense_loss_falls_and_the_gains_are_set(self, tmp_path):
        config = tiny_config(tmp_path, pretrain=PretrainConfig(steps=8, erosion_voxels=1),
                             optimiser=OptimiserConfig(steps=8, batch_size=4, learning_rate=0.01, warmup_steps=1,
                                                       amp=False), checkpoint_every=8, validate_every=8)
        train(config)
        rows = _rows(Path(config.output))
        similarity = [float(row["dense_ncc"]) for row in rows]
        assert similarity[-1] > similarity[0], similarity
        assert all(float(row["rotation_kl"]) == 0 for row in rows)  # no solver, no pose loss
        loaded = load_model(Path(config.output) / "model")
        for name in ("rotation_fixed", "rotation_moving"):
            assert getattr(loaded, name).gain.item() > 0
        for name in ("translation_fixed", "translation_moving"):
            assert getattr(loaded, name).gain.item() == 0  # untouched: the choice stays the learning-free one

    def test_the_contrast_is_logged_and_trains(self, tmp_path):
        config = tiny_config(tmp_path, pretrain=PretrainConfig(steps=2, erosion_voxels=1, contrast_weight=1.0,
                                                               near_degrees=8.0))
        train(replace(config, optimiser=replace(config.optimiser, steps=2), validate_every=2, checkpoint_every=2))
        rows = _rows(tmp_path / "run")
        assert all(0 < float(row["pose_contrast"]) for row in rows)
        assert all(float(row["total"]) == pytest.approx(1 - float(row["dense_ncc"]) + float(row["pose_contrast"]),
                                                       rel=1e-5) for row in rows)

    def test_the_pose_loss_takes_over_after_pretraining(self, tmp_path):
        model, _ = train(tiny_config(tmp_path, pretrain=PretrainConfig(steps=2)))
        rows = _rows(tmp_path / "run")
        assert [float(row["dense_ncc"]) != 0 for row in rows] == [True, True, False, False]
        assert [float(row["rotation_kl"]) > 0 for row in rows] == [False, False, True, True]
        assert model.rotation_fixed.gain.item() != 0
