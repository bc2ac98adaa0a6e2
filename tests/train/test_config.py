"""dpcn_med.train.config: reading YAML configs, their refusals, and the shipped configs."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
import torch

from dpcn_med.cli import main
from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.models import ModelConfig
from dpcn_med.solver import LossWeights
from dpcn_med.train import DataConfig, OptimiserConfig, TrainConfig, load_config
from dpcn_med.train.data import volume_bank
from tests.train.conftest import TINY_YAML, tiny_config


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

    def test_loss_section(self, tmp_path):
        (tmp_path / "loss.yaml").write_text("loss: {rotation_l1: 0, candidate_ranking: 2, rotation_twins: true}\n")
        loss = load_config(tmp_path / "loss.yaml").loss
        assert loss == LossWeights(rotation_l1=0.0, candidate_ranking=2.0, rotation_twins=True)
        assert TrainConfig().loss == LossWeights()
        (tmp_path / "bad.yaml").write_text("loss: {ranking: 1}\n")
        with pytest.raises(InputError, match="ranking"):
            load_config(tmp_path / "bad.yaml")

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


class TestShippedConfigs:
    @pytest.mark.parametrize("name", ["ct_mr", "mr_mr", "ct_us"])
    def test_loads_and_names_existing_volumes(self, name):
        root = Path(__file__).resolve().parents[2]
        config = load_config(root / "training" / "configs" / f"{name}.yaml")
        assert config.model.bandwidth == 32  # the command line's default
        for volume in config.data.volumes + config.data.validation_volumes:
            if volume.startswith("mni"):
                continue
            if not Path(volume).exists():
                pytest.skip(f"{volume} is absent: the shared data volumes sit beside the checkout in CI")
        assert not set(config.data.volumes) & set(config.data.validation_volumes)  # held out
