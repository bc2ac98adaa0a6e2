"""dpcn_med.train.loop: the schedule, a tiny run with its outputs and resume, the CLI, and the DDP path (gloo)."""

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
from dpcn_med.errors import InputError
from dpcn_med.evaluation import moved_copy, random_similarity
from dpcn_med.io import _umask
from dpcn_med.models import load_model
from dpcn_med.preprocess import foreground_box
from dpcn_med.samples import mni152_t1
from dpcn_med.train import OptimiserConfig, TrainConfig, load_config, train
from dpcn_med.train.loop import learning_rate, pair_stream_seed
from tests.train.conftest import TINY_YAML, tiny_config


def log_rows(folder: Path) -> list[dict]:
    with open(folder / "log.csv", newline="") as handle:
        return list(csv.DictReader(handle))


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
        # The chosen candidate's error is logged beside the best one's: never below it.
        assert all(float(r["best_candidate_error_deg"]) <= float(r["chosen_error_deg"]) + 1e-3
                   for r in rows if r["kind"] == "train")
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

        def nan_at_the_second_step(result, target, weights=None):
            calls.append(1)
            terms = losses(result, target, weights)
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
        with pytest.raises(InputError, match=r"^training: 3 steps in a row gave non-finite gradients \(at step 3\)"
                           ) as raised:
            train(tiny_config(tmp_path))
        # The progress bar is closed with the error, while its traceback (which the command line reports from) still
        # holds the training's frames: an open bar wrote its last line after the error's message, at exit.
        from tqdm import tqdm
        assert raised.tb is not None
        assert not [bar for bar in list(tqdm._instances) if bar.desc.startswith("training")]

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
