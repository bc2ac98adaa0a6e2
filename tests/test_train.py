"""dpcn_med.train: configs, the schedule, a tiny run with its outputs and resume, the CLI, and the DDP path (gloo)."""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
import signal
import socket
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import torch
import torch.multiprocessing as mp

from dpcn_med import io
from dpcn_med.cli import main
from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.evaluation import moved_copy, random_similarity
from dpcn_med.io import _umask
from dpcn_med.models import ModelConfig, load_model
from dpcn_med.preprocess import foreground_box
from dpcn_med.samples import mni152_t1
from dpcn_med.train import DataConfig, OptimiserConfig, TrainConfig, load_config, train
from dpcn_med.train.data import volume_bank
from dpcn_med.train.loop import learning_rate, pair_stream_seed

TINY_YAML = """
output: run
seed: 3
device: cpu
model: {bandwidth: 8, channels: [4, 8, 16], residual_units: 0, modalities: [ct, mr]}
data:
  volumes: [mni]
  validation_volumes: [mni]
  validation_pairs: 4
  pair: {max_shift_fraction: 0.1}
optimiser: {steps: 4, batch_size: 4, learning_rate: 0.03, warmup_steps: 1, amp: false}
log_every: 1
validate_every: 2
checkpoint_every: 2
"""


def tiny_config(folder: Path, **changes) -> TrainConfig:
    path = folder / "tiny.yaml"
    path.write_text(TINY_YAML)
    return replace(load_config(path), **changes)


def log_rows(folder: Path) -> list[dict]:
    with open(folder / "log.csv", newline="") as handle:
        return list(csv.DictReader(handle))


class TestConfig:
    def test_nested_values_and_relative_paths(self, tmp_path):
        config = tiny_config(tmp_path)
        assert config.model == ModelConfig(bandwidth=8, channels=(4, 8, 16), residual_units=0)
        assert config.optimiser.steps == 4 and config.optimiser.amp is False
        assert config.data.pair.max_shift_fraction == 0.1
        assert config.output == str(tmp_path / "run") and config.data.volumes == ("mni",)
        (tmp_path / "paths.yaml").write_text("data: {volumes: [images/ct.nii.gz, /abs/mr.nii.gz]}\n")
        assert load_config(tmp_path / "paths.yaml").data.volumes == (str(tmp_path / "images" / "ct.nii.gz"),
                                                                      "/abs/mr.nii.gz")

    def test_a_tilde_is_the_home_folder(self, tmp_path, monkeypatch):
        monkeypatch.setenv("HOME", str(tmp_path / "home"))
        (tmp_path / "home.yaml").write_text("output: ~/runs/a\ndata: {volumes: [~/ct.nii.gz, mni]}\n")
        config = load_config(tmp_path / "home.yaml")
        assert config.output == str(tmp_path / "home" / "runs" / "a")
        assert config.data.volumes == (str(tmp_path / "home" / "ct.nii.gz"), "mni")

    def test_unknown_keys_name_where_they_are(self, tmp_path):
        (tmp_path / "bad.yaml").write_text("optimiser: {lr: 0.1}\n")
        with pytest.raises(InputError, match=r"bad\.yaml: optimiser: unknown keys \['lr'\]"):
            load_config(tmp_path / "bad.yaml")
        (tmp_path / "model.yaml").write_text("model: {modalities: [ct, pet]}\n")
        with pytest.raises(InputError, match="expected two of ct, mr, us"):
            load_config(tmp_path / "model.yaml")

    def test_missing_and_malformed_files(self, tmp_path):
        with pytest.raises(InputNotFoundError, match=r"none\.yaml: not found"):
            load_config(tmp_path / "none.yaml")
        with pytest.raises(InputError, match=r": is a folder; give the YAML config file"):
            load_config(tmp_path)
        (tmp_path / "broken.yaml").write_text("model: [unclosed\n")
        with pytest.raises(InputError, match=r"broken\.yaml: not a YAML file: line 2, column 1: expected ',' or "
                           r"']', but got '<stream end>'$"):
            load_config(tmp_path / "broken.yaml")

    def test_an_empty_file_is_not_a_default_run(self, tmp_path):
        """An empty or truncated file (or the wrong one) must not start hours of training on the defaults; ``{}``
        asks for them."""
        for text in ("", "# nothing set yet\n", "---\n"):
            (tmp_path / "empty.yaml").write_text(text)
            with pytest.raises(InputError, match=r"empty\.yaml: holds no settings \(empty, or comments only\)"):
                load_config(tmp_path / "empty.yaml")
        (tmp_path / "defaults.yaml").write_text("{}\n")
        assert load_config(tmp_path / "defaults.yaml").model == TrainConfig().model

    def test_values_convert_as_their_fields_say(self, tmp_path):
        (tmp_path / "types.yaml").write_text("optimiser: {learning_rate: 1, gradient_clip: 0}\n"
                                             "data: {folder_crop: null, pair: {scale_range: [1, 2]}}\n")
        config = load_config(tmp_path / "types.yaml")
        assert config.optimiser.learning_rate == 1.0 and type(config.optimiser.learning_rate) is float
        assert config.optimiser.gradient_clip == 0.0  # no clipping, as documented
        assert config.data.folder_crop is None and config.data.pair.scale_range == (1.0, 2.0)

    def test_defaults_are_the_dataclasses(self):
        assert TrainConfig().data == DataConfig() and TrainConfig().optimiser == OptimiserConfig()


BAD_CONFIGS = {  # (text of TINY_YAML, its replacement, the message's key words)
    "quoted_resume": ("log_every: 1", "log_every: 1\nresume: 'false'", r"tiny\.yaml: resume: expected true or false, "
                      r"got 'false' \(a quoted string"),
    "empty_section": ("pair: {max_shift_fraction: 0.1}", "pair:", r"data\.pair: expected a mapping, got null"),
    "quoted_amp": ("amp: false", "amp: 'false'", r"optimiser\.amp: expected true or false, got 'false'"),
    "volumes_not_a_list": ("  volumes: [mni]", "  volumes: mni",
                           r"data\.volumes: expected a list of strings, got 'mni'"),
    "volume_not_a_string": ("  volumes: [mni]", "  volumes: [3]", r"data\.volumes\[0\]: expected a string, got 3"),
    "no_validation_volumes": ("validation_volumes: [mni]", "validation_volumes: []",
                              r"data\.validation_volumes is empty"),
    "zero_rate": ("learning_rate: 0.03", "learning_rate: 0", r"optimiser\.learning_rate is 0\.0; expected a finite "
                  "number > 0"),
    "nan_rate": ("learning_rate: 0.03", "learning_rate: .nan", r"optimiser\.learning_rate is nan"),
    "infinite_rate": ("learning_rate: 0.03", "learning_rate: .inf", r"optimiser\.learning_rate is inf"),
    "exponent_as_string": ("learning_rate: 0.03", "learning_rate: 3e-2", r"optimiser\.learning_rate: expected a "
                           r"number, got '3e-2' \(YAML reads 1e-3 as a string"),
    "negative_weight_decay": ("amp: false", "amp: false, weight_decay: -0.1", r"optimiser\.weight_decay is -0\.1"),
    "nan_gradient_clip": ("amp: false", "amp: false, gradient_clip: .nan", r"optimiser\.gradient_clip is nan; "
                          "expected a finite norm > 0, or 0 for no clipping"),
    "negative_gradient_clip": ("amp: false", "amp: false, gradient_clip: -1", r"optimiser\.gradient_clip is -1\.0"),
    "nan_final_fraction": ("amp: false", "amp: false, final_fraction: .nan", r"optimiser\.final_fraction is nan"),
    "final_fraction_above_1": ("amp: false", "amp: false, final_fraction: 2", r"optimiser\.final_fraction is 2\.0"),
    "zero_steps": ("steps: 4", "steps: 0", r"optimiser\.steps is 0; expected at least 1"),
    "negative_steps": ("steps: 4", "steps: -3", r"optimiser\.steps is -3"),
    "fractional_batch": ("batch_size: 4", "batch_size: 2.5", r"optimiser\.batch_size: expected an integer, got 2\.5"),
    "zero_batch": ("batch_size: 4", "batch_size: 0", r"optimiser\.batch_size is 0"),
    "boolean_steps": ("steps: 4", "steps: true", r"optimiser\.steps: expected an integer, got true"),
    "negative_warmup": ("warmup_steps: 1", "warmup_steps: -1", r"optimiser\.warmup_steps is -1"),
    "nan_folder_fraction": ("validation_pairs: 4", "validation_pairs: 4\n  folder_fraction: .nan",
                            r"data\.folder_fraction is nan; expected a fraction of the steps in \[0, 1\]"),
    "negative_folder_fraction": ("validation_pairs: 4", "validation_pairs: 4\n  folder_fraction: -1",
                                 r"data\.folder_fraction is -1\.0"),
    "short_folder_crop": ("validation_pairs: 4", "validation_pairs: 4\n  folder_crop: [0.5]",
                          r"data\.folder_crop: expected a list of 2 numbers or null, got \[0\.5\]"),
    "reversed_folder_crop": ("validation_pairs: 4", "validation_pairs: 4\n  folder_crop: [0.9, 0.5]",
                             r"data\.folder_crop is \(0\.9, 0\.5\)"),
    "zero_validation_pairs": ("validation_pairs: 4", "validation_pairs: 0", r"data\.validation_pairs is 0"),
    "string_validation_seed": ("validation_pairs: 4", "validation_pairs: 4\n  validation_seed: x",
                               r"data\.validation_seed: expected an integer, got 'x'"),
    "nan_shift": ("max_shift_fraction: 0.1", "max_shift_fraction: .nan", r"data\.pair\.max_shift_fraction is nan"),
    "nested_type": ("max_shift_fraction: 0.1", "max_shift_fraction: 0.1, fixed_contrast: {rician: 1}",
                    r"data\.pair\.fixed_contrast\.rician: expected true or false, got 1"),
    # Values that made NaN or blank training volumes, or a NaN loss, with no error:
    "nan_bias": ("max_shift_fraction: 0.1", "max_shift_fraction: 0.1, moving_contrast: {bias_strength: .nan}",
                 r"data\.pair\.moving_contrast\.bias_strength is nan; expected a finite number >= 0"),
    "one_knot": ("max_shift_fraction: 0.1", "max_shift_fraction: 0.1, moving_contrast: {knots: 1}",
                 r"data\.pair\.moving_contrast\.knots is 1; expected an integer >= 2"),
    "infinite_impedance": ("max_shift_fraction: 0.1", "max_shift_fraction: 0.1, ultrasound: {impedance_gain: .inf}",
                           r"data\.pair\.ultrasound\.impedance_gain is inf"),
    "nan_standoff": ("max_shift_fraction: 0.1", "max_shift_fraction: 0.1, ultrasound: {standoff: .nan}",
                     r"data\.pair\.ultrasound\.standoff is nan"),
    "shift_past_half": ("max_shift_fraction: 0.1", "max_shift_fraction: 100", r"data\.pair\.max_shift_fraction is "
                        r"100\.0; expected a finite number >= 0 and <= 0\.5 \(a fraction of N"),
    "unknown_device": ("device: cpu", "device: gpu", r"tiny\.yaml: device is 'gpu'; expected auto, cpu, cuda or "
                       "cuda:N"),
    "zero_temperature": ("residual_units: 0,", "residual_units: 0, temperatures: [0, 1, 1],",
                         r"model: temperatures\[0\] is 0\.0; expected a finite number > 0"),
    "nan_compensation": ("residual_units: 0,", "residual_units: 0, compensation_noise_degrees: .nan,",
                         r"model\.compensation_noise_degrees is nan; expected a finite number >= 0"),
    "one_voxel_deep": ("channels: [4, 8, 16]", "channels: [2, 4, 8, 16, 32]", r"model\.channels \(2, 4, 8, 16, 32\): "
                       r"need at least two levels, and the grid size 16 .* least 2 voxels at the deepest level"),
    # Seeds numpy or torch refused mid-run as internal errors:
    "negative_seed": ("seed: 3", "seed: -1", r"tiny\.yaml: seed is -1; expected an integer >= 0 and <= 4294967295"),
    "huge_seed": ("seed: 3", "seed: 100000000000000", r"tiny\.yaml: seed is 100000000000000"),
    "huge_validation_seed": ("validation_pairs: 4", "validation_pairs: 4\n  validation_seed: 100000000000000000000",
                             r"data\.validation_seed is 100000000000000000000"),
    "zero_log_every": ("log_every: 1", "log_every: 0", r"tiny\.yaml: log_every is 0; expected a number of steps"),
    "zero_validate_every": ("validate_every: 2", "validate_every: 0", r"tiny\.yaml: validate_every is 0"),
    "zero_checkpoint_every": ("checkpoint_every: 2", "checkpoint_every: 0", r"tiny\.yaml: checkpoint_every is 0"),
    "numeric_output": ("output: run", "output: 3", r"tiny\.yaml: output: expected a string, got 3"),
    "null_output": ("output: run", "output: null", r"tiny\.yaml: output: expected a string, got null"),
    "fractional_seed": ("seed: 3", "seed: 3.5", r"tiny\.yaml: seed: expected an integer, got 3\.5"),
    "negative_channels": ("channels: [4, 8, 16]", "channels: [4, -8, 16]", r"model\.channels \(4, -8, 16\): "
                          "expected positive integers"),
    "channels_not_a_list": ("channels: [4, 8, 16]", "channels: 4", r"model\.channels: expected a list of integers"),
    "string_bandwidth": ("bandwidth: 8", "bandwidth: '8'", r"model\.bandwidth: expected an integer, got '8'"),
    "zero_bandwidth": ("bandwidth: 8", "bandwidth: 0", r"model\.bandwidth 0 is out of range: use an integer in "
                       r"\[8, 128\]"),
    "negative_bandwidth": ("bandwidth: 8", "bandwidth: -8", r"model\.bandwidth -8 is out of range"),
    "huge_bandwidth": ("bandwidth: 8", "bandwidth: 200", r"model\.bandwidth 200 is out of range"),
    "preprocessing_type": ("modalities: [ct, mr]}", "modalities: [ct, mr], preprocessing: {fill: x}}",
                           r"model\.preprocessing\.fill: expected a number, got 'x'"),
    "key_twice": ("log_every: 1", "log_every: 1\nlog_every: 2", r"tiny\.yaml: line 13, column 1: key 'log_every' "
                  r"appears twice \(also at line 12\)"),
    "not_yaml": ("log_every: 1", "log_every: [1", r"tiny\.yaml: not a YAML file: line 13, column 15: expected ','"),
}


class TestBadConfig:
    """Every mistake is exit 2 with one line naming the file and the key, before anything is written."""

    @pytest.mark.parametrize("case", list(BAD_CONFIGS))
    def test_exit_2_one_line_nothing_written(self, case, tmp_path, capsys):
        old, new, message = BAD_CONFIGS[case]
        assert old in TINY_YAML
        (tmp_path / "tiny.yaml").write_text(TINY_YAML.replace(old, new))
        assert main(["train", "--config", str(tmp_path / "tiny.yaml")]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and re.search(message, err), err
        assert [p.name for p in tmp_path.iterdir()] == ["tiny.yaml"]

    @pytest.mark.parametrize("steps,message", [("0", "0 is too few; give at least 1"),
                                               ("-5", "-5 is too few; give at least 1"),
                                               ("two", "'two' is not a whole number")])
    def test_steps_option_must_be_positive(self, steps, message, tmp_path, capsys):
        (tmp_path / "tiny.yaml").write_text(TINY_YAML)
        with pytest.raises(SystemExit) as caught:
            main(["train", "--config", str(tmp_path / "tiny.yaml"), "--steps", steps])
        assert caught.value.code == 2 and f"--steps: {message}" in capsys.readouterr().err
        assert [p.name for p in tmp_path.iterdir()] == ["tiny.yaml"]

    @pytest.mark.parametrize("device, message", [
        ("tpu", "device is 'tpu'; expected auto, cpu, cuda or cuda:N"),
        ("gpu", "device is 'gpu'; expected auto, cpu, cuda or cuda:N"),
        ("mps", "device is 'mps'; expected auto, cpu, cuda or cuda:N"),
        pytest.param("cuda", "device 'cuda' asked for, but this torch build sees no CUDA GPU",
                     marks=pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")),
    ])
    @pytest.mark.parametrize("where", ["config", "option"])
    def test_unknown_or_absent_device(self, device, message, where, tmp_path, capsys):
        text = TINY_YAML.replace("device: cpu", f"device: {device}") if where == "config" else TINY_YAML
        (tmp_path / "tiny.yaml").write_text(text)
        option = ["--device", device] if where == "option" else []
        assert main(["train", "--config", str(tmp_path / "tiny.yaml"), *option]) == 2
        assert message in capsys.readouterr().err
        assert [p.name for p in tmp_path.iterdir()] == ["tiny.yaml"]

    @pytest.mark.parametrize("where", ["under_a_file", "over_a_file", "read_only"])
    def test_unusable_output_folder_is_refused_before_any_work(self, where, tmp_path, capsys, monkeypatch):
        if where == "read_only" and os.geteuid() == 0:
            pytest.skip("root writes into read-only folders")
        import dpcn_med.train

        monkeypatch.setattr(dpcn_med.train, "train", lambda *args, **kwargs: pytest.fail("trained"))
        (tmp_path / "tiny.yaml").write_text(TINY_YAML)
        (tmp_path / "notes.txt").write_text("x")
        (tmp_path / "locked").mkdir(mode=0o555)
        output = {"under_a_file": tmp_path / "notes.txt" / "run", "over_a_file": tmp_path / "notes.txt",
                  "read_only": tmp_path / "locked" / "run"}[where]
        assert main(["train", "--config", str(tmp_path / "tiny.yaml"), "--output", str(output)]) == 2
        assert re.search(r"(notes\.txt|locked).*(is a file|is not a folder|no write permission)",
                         capsys.readouterr().err)
        assert (tmp_path / "notes.txt").read_text() == "x" and not list((tmp_path / "locked").iterdir())

    def test_empty_volume_list_is_named(self):
        with pytest.raises(InputError, match=r"data\.validation_volumes: no volumes"):
            volume_bank((), 16, key="data.validation_volumes")


class TestLearningRate:
    def test_warm_up_then_cosine_to_the_final_fraction(self):
        config = TrainConfig(optimiser=OptimiserConfig(steps=100, warmup_steps=10, learning_rate=1.0,
                                                       final_fraction=0.1))
        rates = [learning_rate(step, config) for step in range(101)]
        assert rates[0] == pytest.approx(0.1) and rates[9] == pytest.approx(1.0)
        assert all(a >= b for a, b in zip(rates[10:], rates[11:]))
        assert rates[100] == pytest.approx(0.1)


def test_every_rank_and_start_step_draws_its_own_pairs():
    """rank 0 resumed at step 7919 drew the pairs of rank 1 from step 0 (seed * 1_000_003 + rank * 7_919 + step)."""
    seeds = {pair_stream_seed(seed, rank, step) for seed in (0, 1) for rank in (0, 1, 2) for step in (0, 1, 7919)}
    assert len(seeds) == 18 and pair_stream_seed(0, 0, 7919) == pair_stream_seed(0, 0, 7919)


class TestTrain:
    def test_tiny_run_writes_everything_and_resumes(self, tmp_path):
        config = tiny_config(tmp_path)
        model, record = train(config)
        assert not model.training  # ready to register, as load_model's
        output = Path(config.output)
        for name in ("model.safetensors", "model.json", "checkpoint.safetensors", "checkpoint.json", "log.csv",
                     "training.png"):
            assert (output / name).is_file(), name
        rows = log_rows(output)
        assert [int(r["step"]) for r in rows if r["kind"] == "train"] == [1, 2, 3, 4]
        assert [int(r["step"]) for r in rows if r["kind"] == "validation"] == [0, 2, 4]
        assert all(float(r["total"]) > 0 for r in rows if r["kind"] == "train")
        assert record["steps"] == 4 and record["validation_after"]["step"] == 4
        loaded = load_model(output / "model")
        assert loaded.config == config.model
        saved = json.loads((output / "model.json").read_text())["record"]
        assert saved["training_volumes"] == ["mni"] and saved["pairs_seen"] == 16
        for name, tensor in model.state_dict().items():
            torch.testing.assert_close(loaded.state_dict()[name], tensor.cpu())

        # Resume to 6 steps: the log continues from the checkpoint, nothing is repeated.
        resumed, _ = train(replace(config, optimiser=replace(config.optimiser, steps=6)))
        rows = log_rows(output)
        assert [int(r["step"]) for r in rows if r["kind"] == "train"] == [1, 2, 3, 4, 5, 6]
        assert json.loads((output / "checkpoint.json").read_text())["step"] == 6

    # Before: the model drew its compensation noise from the global RNG, the same on every DDP rank.
    def test_the_model_draws_from_the_loop_s_generator(self, tmp_path, monkeypatch):
        from dpcn_med.models import DPCN

        forward, generators = DPCN.forward, []

        def recorded(model, *args, **options):
            if model.training:
                generators.append(options.get("generator"))
            return forward(model, *args, **options)

        monkeypatch.setattr(DPCN, "forward", recorded)
        train(tiny_config(tmp_path))
        assert len(generators) == 4 and all(isinstance(g, torch.Generator) for g in generators)

    def test_a_step_with_non_finite_gradients_is_skipped(self, tmp_path, monkeypatch):
        """A NaN gradient (a degenerate pair) made every weight NaN; the step is skipped and counted."""
        from dpcn_med.train import loop

        losses, calls = loop.pose_loss, []

        def nan_at_the_second_step(result, target):
            calls.append(1)
            terms = losses(result, target)
            return {**terms, "total": terms["total"] * math.nan} if len(calls) == 2 else terms

        monkeypatch.setattr(loop, "pose_loss", nan_at_the_second_step)
        model, _ = train(tiny_config(tmp_path))
        assert all(torch.isfinite(p).all() for p in model.parameters())
        rows = [r for r in log_rows(tmp_path / "run") if r["kind"] == "train"]
        assert [int(r["skipped_steps"]) for r in rows] == [0, 1, 0, 0]

    def test_steps_that_keep_failing_stop_the_run(self, tmp_path, monkeypatch):
        from dpcn_med.train import loop

        losses = loop.pose_loss
        monkeypatch.setattr(loop, "pose_loss", lambda *a: {**losses(*a), "total": losses(*a)["total"] * math.nan})
        monkeypatch.setattr(loop, "MAX_SKIPPED_IN_A_ROW", 3)
        with pytest.raises(InputError, match=r"^training: 3 steps in a row gave non-finite gradients \(at step 3\)"):
            train(tiny_config(tmp_path))

    def test_real_pairs_from_folders_train_and_validate(self, tmp_path, monkeypatch):
        """Folders of registered pairs (.tfm ground truth) feed every step here and are scored at validation."""
        from dpcn_med.models import DPCN
        from dpcn_med.train.folders import FolderPairs

        _write_pairs(tmp_path / "pairs", 2)
        config = tiny_config(tmp_path)
        config = replace(config, data=replace(config.data, folders=(str(tmp_path / "pairs"),), folder_fraction=1.0,
                                              validation_folders=(str(tmp_path / "pairs"),)),
                         optimiser=replace(config.optimiser, steps=2))
        forward, batches = DPCN.forward, []

        def recorded(model, fixed, moving, target=None, **options):
            if model.training:
                batches.append((fixed, moving, target))
            return forward(model, fixed, moving, target, **options)

        monkeypatch.setattr(DPCN, "forward", recorded)
        train(config)
        pairs = FolderPairs(tmp_path / "pairs", config.model.bandwidth,
                            preprocessing=config.model.grid_preprocessing())
        grids = [pairs.grids(index) for index in range(len(pairs))]
        assert len(batches) == 2
        for fixed, moving, target in batches:
            assert len(moving) == config.optimiser.batch_size
            for item in range(len(moving)):
                pair = next((p for p in grids if torch.equal(moving[item], p.moving)), None)
                assert pair is not None, "a training pair that is not from the folder"
                assert torch.equal(target.rotation[item], pair.target.rotation[0])
                assert torch.equal(target.translation[item], pair.target.translation[0])
                kept = fixed[item] != 0  # a random slab of the fixed grid is kept (data.folder_crop), the rest is 0
                assert kept.any() and torch.equal(fixed[item][kept], pair.fixed[kept])
        rows = [r for r in log_rows(Path(config.output)) if r["kind"] == "validation"]
        assert rows and all(0.0 <= float(r["real_success"]) <= 1.0 for r in rows)
        assert all(float(r["real_rotation_error_deg"]) >= 0 for r in rows)

    def test_each_folder_crops_its_pairs_its_own_way(self, tmp_path):
        """With one seed for every folder, pair i of each was cropped alike at every step."""
        from dpcn_med.train import loop

        for name in ("a", "b"):
            _write_pairs(tmp_path / name, 1)
        real = loop._real_pairs((str(tmp_path / "a"), str(tmp_path / "b")), tiny_config(tmp_path), crop=(0.3, 0.9),
                                seed=0)
        for dataset in real.datasets:
            dataset.set_epoch(3)
        first, second = real[0]["fixed"], real[1]["fixed"]  # the same pair, in two folders
        assert not torch.equal(first, second)

    def test_cli(self, tmp_path, capsys):
        (tmp_path / "tiny.yaml").write_text(TINY_YAML)
        code = main(["train", "--config", str(tmp_path / "tiny.yaml"), "--steps", "2", "--output",
                     str(tmp_path / "cli")])
        assert code == 0
        assert "trained 2 steps" in capsys.readouterr().out
        assert (tmp_path / "cli" / "model.safetensors").is_file()

    def test_a_broken_training_pair_is_named_before_any_work(self, tmp_path, capsys):
        """Read on first use, a broken pair had surfaced mid-run (or hours in, after checkpoints)."""
        _write_pairs(tmp_path / "pairs", 2)
        (tmp_path / "pairs" / "p1" / "fixed.nii.gz").write_bytes(b"not an image")
        (tmp_path / "tiny.yaml").write_text(TINY_YAML.replace("validation_pairs: 4", "validation_pairs: 4\n"
                                                              "  folders: [pairs]\n  folder_fraction: 0.5"))
        assert main(["train", "--config", str(tmp_path / "tiny.yaml")]) == 2
        err = capsys.readouterr().err
        assert str(tmp_path / "pairs" / "p1" / "fixed.nii.gz") in err and len(err.splitlines()) == 1, err
        assert not (tmp_path / "run").exists()

    @pytest.mark.parametrize("key", ["folders", "validation_folders"])
    def test_an_output_inside_the_pairs_is_refused(self, key, tmp_path, capsys):
        (tmp_path / "pairs").mkdir()
        (tmp_path / "tiny.yaml").write_text(TINY_YAML.replace("output: run", "output: pairs/run").replace(
            "validation_pairs: 4", f"validation_pairs: 4\n  {key}: [pairs]"))
        assert main(["train", "--config", str(tmp_path / "tiny.yaml")]) == 2
        assert capsys.readouterr().err == (f"dpcn-med: error: {tmp_path / 'pairs' / 'run'}: is inside data.{key} "
                                           f"{tmp_path / 'pairs'}, where the run's folder would read as a pair "
                                           "folder; choose an output folder outside the data\n")
        assert list((tmp_path / "pairs").iterdir()) == []

    @pytest.mark.parametrize("key", ["volumes", "validation_volumes"])
    def test_bad_volume_is_named_and_nothing_written(self, key, tmp_path, capsys):
        (tmp_path / "bad.yaml").write_text(TINY_YAML.replace(f"  {key}: [mni]", f"  {key}: [missing.nii.gz]"))
        assert main(["train", "--config", str(tmp_path / "bad.yaml")]) == 2
        assert "missing.nii.gz: not found" in capsys.readouterr().err
        assert not (tmp_path / "run").exists()  # the output folder is made once the inputs are read


def _write_pairs(root: Path, count: int) -> None:
    """``count`` pair folders of a smoothed 8 mm MNI head and a moved copy, with the ground truth as .tfm."""
    image = sitk.BinShrink(sitk.SmoothingRecursiveGaussian(mni152_t1(), 4.0), [4, 4, 4])
    centre = foreground_box(image)[0]
    for seed in range(count):
        folder = root / f"p{seed}"
        folder.mkdir(parents=True)
        truth = random_similarity(np.random.default_rng(seed), centre, max_shift_mm=10.0)
        io.write_image(image, folder / "fixed.nii.gz")
        io.write_image(moved_copy(image, truth), folder / "moving.nii.gz")
        io.write_transform(truth, folder / "transform.tfm")


@pytest.fixture(scope="module")
def checkpointed(tmp_path_factory) -> Path:
    """A folder with ``tiny.yaml`` and the one-step run it made in ``run/`` (checkpoint and model)."""
    folder = tmp_path_factory.mktemp("checkpointed")
    (folder / "tiny.yaml").write_text(TINY_YAML)
    assert main(["train", "--config", str(folder / "tiny.yaml"), "--steps", "1"]) == 0
    return folder


def _damage_json(run: Path, change: dict) -> None:
    saved = json.loads((run / "checkpoint.json").read_text())
    (run / "checkpoint.json").write_text(json.dumps({**saved, **change} if change else {}))


def _damage_tensors(run: Path, drop: bool) -> None:
    tensors = io.read_tensors(run / "checkpoint.safetensors")
    name = next(name for name in tensors if name.startswith("model.") and tensors[name].dim() > 1)
    tensors[name] = tensors[name][:1]
    if drop:
        del tensors[name]
    io.write_tensors(tensors, run / "checkpoint.safetensors", metadata=io.read_tensor_header(
        run / "checkpoint.safetensors")[0])


class TestResume:
    def test_a_checkpoint_given_as_a_model_names_the_model(self, checkpointed):
        from dpcn_med.models import load_model

        run = checkpointed / "run"
        model = re.escape(str(run / "model.safetensors"))
        with pytest.raises(InputError, match=rf"checkpoint\.json: not a dpcn_med model config .*: a training "
                                             rf"checkpoint; the trained model is {model}$"):
            load_model(run / "checkpoint")

    def test_a_signal_while_saving_waits_for_the_pair(self):
        """SIGTERM (or Ctrl-C) between the two files of a checkpoint would leave new weights beside an old step."""
        written, before = [], signal.getsignal(signal.SIGTERM)
        with pytest.raises(KeyboardInterrupt):
            with io.interrupts_deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                written.append("weights")
                written.append("description")
        assert written == ["weights", "description"] and signal.getsignal(signal.SIGTERM) == before

    def test_tensor_files_follow_the_umask(self, checkpointed):
        run = checkpointed / "run"
        for name in ("checkpoint", "model"):
            mode = (run / f"{name}.json").stat().st_mode & 0o777
            assert (run / f"{name}.safetensors").stat().st_mode & 0o777 == mode == 0o666 & ~_umask()

    @pytest.mark.parametrize("old, new, difference", [
        ("bandwidth: 8", "bandwidth: 16", "model.bandwidth 8, this config has 16"),
        ("  volumes: [mni]", "  volumes: [mni, mni-head]", 'data.volumes ["mni"], this config has ["mni", '
         '"mni-head"]'),
        ("amp: false", "amp: false, weight_decay: 0.5", "optimiser.weight_decay 0.0001, this config has 0.5"),
    ])
    def test_checkpoint_of_another_config_is_refused(self, old, new, difference, checkpointed, tmp_path, capsys):
        folder = shutil.copytree(checkpointed, tmp_path / "copy")
        (folder / "tiny.yaml").write_text(TINY_YAML.replace(old, new, 1))
        before = {path.name: path.read_bytes() for path in (folder / "run").iterdir()}
        assert main(["train", "--config", str(folder / "tiny.yaml"), "--steps", "8"]) == 2
        assert capsys.readouterr().err == (
            f"dpcn-med: error: {folder / 'run' / 'checkpoint.json'}: was made with {difference}; train into another "
            "output folder, or start afresh over this one with --restart (resume: false)\n")
        assert {path.name: path.read_bytes() for path in (folder / "run").iterdir()} == before

    def test_project_folder_moved_whole_resumes(self, tmp_path):
        folder = tmp_path / "project"
        folder.mkdir()
        io.write_image(sitk.BinShrink(mni152_t1(), [4, 4, 4]), folder / "head.nii.gz")
        (folder / "tiny.yaml").write_text(TINY_YAML.replace("validation_volumes: [mni]",
                                                            "validation_volumes: [head.nii.gz]"))
        assert main(["train", "--config", str(folder / "tiny.yaml"), "--steps", "1"]) == 0
        moved = shutil.move(folder, tmp_path / "elsewhere")
        assert main(["train", "--config", str(moved / "tiny.yaml"), "--steps", "2"]) == 0
        assert json.loads((moved / "run" / "checkpoint.json").read_text())["step"] == 2

    @pytest.mark.parametrize("damage, name, message", [
        (lambda run: _damage_json(run, {}), "checkpoint.json", r"not a dpcn_med checkpoint \(no valid step, "
         r"param_groups, optimiser_scalars, config, rows\)"),
        (lambda run: _damage_json(run, {"step": -5}), "checkpoint.json",
         r"not a dpcn_med checkpoint \(no valid step\)"),
        (lambda run: (run / "checkpoint.safetensors").write_bytes(b"garbled"), "checkpoint.safetensors",
         r"not a readable \.safetensors file .*; train into another output folder, or start afresh"),
        (lambda run: _damage_json(run, {"step": 9}), "checkpoint.json", "is at step 9, past this config's "
         "optimiser.steps 4; ask for more steps"),
        (lambda run: _damage_json(run, {"param_groups": []}), "checkpoint.json", "its optimiser state does not fit "
         "this model"),
        (lambda run: _damage_tensors(run, drop=False), "checkpoint.safetensors", r"does not fit this model \(1 "
         "tensors missing, unexpected or of another shape, such as "),
        (lambda run: _damage_tensors(run, drop=True), "checkpoint.safetensors", r"does not fit this model \(1 "),
        (lambda run: _damage_json(run, {"step": 0}), "checkpoint.safetensors", "holds step 1, checkpoint.json step 0: "
         r"the two files are from different saves \(one cut short\?\); train into another output folder"),
        (lambda run: (run / "checkpoint.json").unlink(), "checkpoint.json", "missing beside checkpoint.safetensors"),
        (lambda run: (run / "checkpoint.safetensors").unlink(), "checkpoint.safetensors", "missing beside "
         r"checkpoint.json \(a checkpoint is the two files\)"),
    ], ids=["empty", "negative_step", "garbled_weights", "past_the_steps", "optimiser", "reshaped", "missing", "torn",
            "no_json", "no_weights"])
    def test_damaged_checkpoint_is_named(self, damage, name, message, checkpointed, tmp_path, capsys):
        folder = shutil.copytree(checkpointed, tmp_path / "copy")
        damage(folder / "run")
        assert main(["train", "--config", str(folder / "tiny.yaml")]) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and len(err) < 400, err
        assert re.search(re.escape(f"{folder / 'run' / name}: ") + message, err), err



def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _ddp_worker(rank: int, folder: str, port: int) -> None:
    os.environ.update({"MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port), "RANK": str(rank),
                       "LOCAL_RANK": str(rank), "WORLD_SIZE": "2"})
    torch.set_num_threads(1)
    config = load_config(Path(folder) / "tiny.yaml")  # written once by the test: ranks must not race on it
    config = replace(config, optimiser=replace(config.optimiser, steps=2))
    model, _ = train(config)
    io.write_tensors(model.state_dict(), Path(folder) / f"rank{rank}.safetensors")


class TestDistributed:
    def test_two_gloo_processes_train_one_model(self, tmp_path):
        """DistributedDataParallel on the CPU (gloo), as torchrun would start it: both ranks end with the same
        weights, which moved from the initial ones, and rank 0 alone wrote the outputs."""
        (tmp_path / "tiny.yaml").write_text(TINY_YAML)
        mp.spawn(_ddp_worker, args=(str(tmp_path), _free_port()), nprocs=2, join=True)
        ranks = [io.read_tensors(tmp_path / f"rank{r}.safetensors") for r in (0, 1)]
        for name in ranks[0]:
            torch.testing.assert_close(ranks[0][name], ranks[1][name])
        assert ranks[0]["rotation_fixed.gain"].abs() > 0  # trained: the gains start at exactly 0
        record = json.loads((tmp_path / "run" / "model.json").read_text())["record"]
        assert record["processes"] == 2 and record["pairs_seen"] == 2 * 4 * 2

    def test_one_named_gpu_for_every_process_is_refused(self, monkeypatch):
        """device cuda:1 under torchrun put every rank on one GPU, where NCCL fails ('Duplicate GPU')."""
        from dpcn_med.train import distributed

        # No GPU here: the device resolves as it would on a machine with two.
        monkeypatch.setattr(distributed, "resolve_device", lambda device: torch.device(device))
        monkeypatch.setenv("WORLD_SIZE", "2")
        with pytest.raises(InputError, match=r"^device 'cuda:1' names one GPU for all 2 processes of torchrun on "
                                             r"this machine; use 'cuda' \(each process takes cuda:LOCAL_RANK\) or "
                                             r"'auto'$"):
            distributed.start("cuda:1")


class TestShippedConfigs:
    @pytest.mark.parametrize("name", ["ct_mr", "mr_mr", "ct_us"])
    def test_loads_and_names_existing_volumes(self, name):
        root = Path(__file__).resolve().parents[1]
        config = load_config(root / "training" / "configs" / f"{name}.yaml")
        assert config.model.bandwidth == 32  # the command line's default
        for volume in config.data.volumes + config.data.validation_volumes:
            if volume.startswith("mni"):
                continue
            if not Path(volume).exists():
                pytest.skip(f"{volume} is absent: the shared data volumes sit beside the checkout in CI")
        assert not set(config.data.volumes) & set(config.data.validation_volumes)  # held out
