"""dpcn_med.train: configs, the schedule, a tiny run with its outputs and resume, the CLI, and the DDP path (gloo)."""

from __future__ import annotations

import csv
import json
import os
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
from dpcn_med.models import ModelConfig, load_model
from dpcn_med.preprocess import foreground_box
from dpcn_med.samples import mni152_t1
from dpcn_med.train import DataConfig, OptimiserConfig, TrainConfig, load_config, train
from dpcn_med.train.loop import learning_rate

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

    def test_unknown_keys_name_where_they_are(self, tmp_path):
        (tmp_path / "bad.yaml").write_text("optimiser: {lr: 0.1}\n")
        with pytest.raises(InputError, match=r"bad\.yaml\.optimiser: unknown keys \['lr'\]"):
            load_config(tmp_path / "bad.yaml")
        (tmp_path / "model.yaml").write_text("model: {modalities: [ct, pet]}\n")
        with pytest.raises(InputError, match="expected two of ct, mr, us"):
            load_config(tmp_path / "model.yaml")

    def test_missing_and_malformed_files(self, tmp_path):
        with pytest.raises(InputNotFoundError, match=r"none\.yaml: not found"):
            load_config(tmp_path / "none.yaml")
        (tmp_path / "broken.yaml").write_text("model: [unclosed\n")
        with pytest.raises(InputError, match=r"broken\.yaml: not a YAML file"):
            load_config(tmp_path / "broken.yaml")

    def test_defaults_are_the_dataclasses(self):
        assert TrainConfig().data == DataConfig() and TrainConfig().optimiser == OptimiserConfig()


class TestLearningRate:
    def test_warm_up_then_cosine_to_the_final_fraction(self):
        config = TrainConfig(optimiser=OptimiserConfig(steps=100, warmup_steps=10, learning_rate=1.0,
                                                       final_fraction=0.1))
        rates = [learning_rate(step, config) for step in range(101)]
        assert rates[0] == pytest.approx(0.1) and rates[9] == pytest.approx(1.0)
        assert all(a >= b for a, b in zip(rates[10:], rates[11:]))
        assert rates[100] == pytest.approx(0.1)


class TestTrain:
    def test_tiny_run_writes_everything_and_resumes(self, tmp_path):
        config = tiny_config(tmp_path)
        model, record = train(config)
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

    def test_real_pairs_from_folders_train_and_validate(self, tmp_path):
        """Folders of registered pairs (.tfm ground truth) feed every step here and are scored at validation."""
        image = sitk.BinShrink(sitk.SmoothingRecursiveGaussian(mni152_t1(), 4.0), [4, 4, 4])
        centre = foreground_box(image)[0]
        for seed in range(2):
            folder = tmp_path / "pairs" / f"p{seed}"
            folder.mkdir(parents=True)
            truth = random_similarity(np.random.default_rng(seed), centre, max_shift_mm=10.0)
            io.write_image(image, folder / "fixed.nii.gz")
            io.write_image(moved_copy(image, truth), folder / "moving.nii.gz")
            io.write_transform(truth, folder / "transform.tfm")
        config = tiny_config(tmp_path)
        config = replace(config, data=replace(config.data, folders=(str(tmp_path / "pairs"),), folder_fraction=1.0,
                                              validation_folders=(str(tmp_path / "pairs"),)),
                         optimiser=replace(config.optimiser, steps=2))
        train(config)
        rows = [r for r in log_rows(Path(config.output)) if r["kind"] == "validation"]
        assert rows and all(0.0 <= float(r["real_success"]) <= 1.0 for r in rows)
        assert all(float(r["real_rotation_error_deg"]) >= 0 for r in rows)

    def test_cli(self, tmp_path, capsys):
        (tmp_path / "tiny.yaml").write_text(TINY_YAML)
        code = main(["train", "--config", str(tmp_path / "tiny.yaml"), "--steps", "2", "--output",
                     str(tmp_path / "cli")])
        assert code == 0
        assert "trained 2 steps" in capsys.readouterr().out
        assert (tmp_path / "cli" / "model.safetensors").is_file()

    def test_bad_volume_is_named(self, tmp_path, capsys):
        (tmp_path / "bad.yaml").write_text(TINY_YAML.replace("volumes: [mni]", "volumes: [missing.nii.gz]"))
        assert main(["train", "--config", str(tmp_path / "bad.yaml")]) == 2
        assert "missing.nii.gz: not found" in capsys.readouterr().err


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
