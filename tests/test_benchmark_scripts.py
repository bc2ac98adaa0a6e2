"""benchmarks/*.py: a bad count or fraction stops at the command line (exit 2, the option named, nothing written),
and what the scripts do without registering anything: cli_time's trees and exit codes, solver_speed's worker,
partial_fov's poses, tables and figure, the other scripts' wording."""

from __future__ import annotations

import csv
import importlib
import json
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch

from dpcn_med.errors import InputError
from dpcn_med.evaluation import random_similarity
from dpcn_med.preprocess import foreground_box
from tests.test_registration import mni_2mm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # as the scripts import each other and their shared helpers


def script(name: str) -> ModuleType:
    """The benchmark script ``benchmarks/NAME.py``, imported."""
    return importlib.import_module(name)


class TestCounts:
    @pytest.mark.parametrize("name, argv, message", [
        ("solver_accuracy", ["--poses", "0"], "argument --poses: 0 is too few; give at least 1"),
        ("learned_accuracy", ["--config", "x.yaml", "--pairs", "1"], "argument --pairs: 1 is too few; give at least 2"),
        ("learned_accuracy", ["--config", "x.yaml", "--variants", "entropy"],
         "argument --variants: 'entropy': expected FIELD=VALUE"),
        ("learned_accuracy", ["--config", "x.yaml", "--variants", "taper=0.2;"],
         "argument --variants: 'taper=0.2;': expected FIELD=VALUE, several joined by ';'"),
        ("learned_accuracy", ["--config", "x.yaml", "--variants", "taper=x"],
         "argument --variants: 'taper=x': 'x' is not a Python literal"),
        ("learned_accuracy", ["--config", "x.yaml", "--models"], "nothing to score: give --models, --variants or both"),
        ("learned_speed", ["--steps", "0"], "argument --steps: 0 is too few"),
        ("learned_speed", ["--batches", "4", "0"], "argument --batches: 0 is too few"),
        ("register_roundtrip", ["--trials", "0"], "argument --trials: 0 is too few"),
        ("register_roundtrip", ["--trials", "2.5"], "argument --trials: '2.5' is not a whole number"),
        ("candidate_cost", ["--repeats", "0"], "argument --repeats: 0 is too few"),
        ("slicer_time", ["--repeats", "0"], "argument --repeats: 0 is too few"),
        ("mridir_reference", ["--starts", "0"], "argument --starts: 0 is too few"),
        ("heldout_factors", ["--config", "x.yaml", "--pairs", "1"], "argument --pairs: 1 is too few; give at least 2"),
        ("mridir_reference", ["--rotations", "-1"], "argument --rotations: -1 is too few; give at least 0"),
        ("partial_fov", ["--trials", "0"], "argument --trials: 0 is too few"),
        ("partial_fov", ["--baseline-trials", "-1"], "argument --baseline-trials: -1 is too few"),
        ("failure_signals", ["--trials", "0"], "argument --trials: 0 is too few"),
        ("partial_fov", ["--seed", "-1"], "argument --seed: -1 is too few; give at least 0"),
        ("failure_signals", ["--seed", "-1"], "argument --seed: -1 is too few; give at least 0"),
        ("cli_time", ["--repeats", "0"], "argument --repeats: 0 is too few"),
        ("stage_time", ["--poses", "0"], "argument --poses: 0 is too few"),
        ("stage_time", ["--rounds", "0"], "argument --rounds: 0 is too few"),
        ("stage_time", ["--cases", "mni-t2"], "argument --cases: invalid choice: 'mni-t2'"),
        ("stage_time", ["--compare", "nowhere"], "--compare nowhere: not a dpcn_med source tree"),
        ("solver_speed", ["--repeats", "0"], "argument --repeats: 0 is too few"),
        ("solver_speed", ["--devices", "gpu"], "argument --devices: 'gpu' is not a torch device"),
        ("ultrasound", ["--trials", "0"], "argument --trials: 0 is too few"),
        ("ultrasound", ["--baseline-trials", "-1"], "argument --baseline-trials: -1 is too few"),
        ("ultrasound", ["--cases", "us-us"], "argument --cases: invalid choice: 'us-us'"),
    ])
    def test_refused_before_any_work(self, name, argv, message, tmp_path, capsys):
        output = tmp_path / "table.md"
        with pytest.raises(SystemExit) as exit_:
            script(name).main([*argv, "--output", str(output)])
        assert exit_.value.code == 2
        assert message in capsys.readouterr().err
        assert not output.exists()


class TestOverlaps:
    @pytest.mark.parametrize("name", ["partial_fov", "failure_signals"])
    @pytest.mark.parametrize("overlaps, message", [
        (["-0.5"], "'-0.5' is not a fraction in (0, 1]"),
        (["0"], "'0' is not a fraction in (0, 1]"),
        (["1.5"], "'1.5' is not a fraction in (0, 1]"),
        (["nan"], "'nan' is not a fraction in (0, 1]"),
        (["0.565"], "'0.565' is not a whole percent"),
        (["0.6", "0.4", "0.60"], "--overlaps: 60% given twice"),
    ])
    def test_refused_before_any_work(self, name, overlaps, message, tmp_path, capsys):
        with pytest.raises(SystemExit) as exit_:
            script(name).main(["--overlaps", *overlaps, "--output", str(tmp_path / "table.md")])
        assert exit_.value.code == 2
        assert message in capsys.readouterr().err
        assert not any(tmp_path.iterdir())

    def test_each_percent_seeds_its_own_poses(self):
        partial_fov = script("partial_fov")
        image = mni_2mm()
        poses = [next(partial_fov.cell_poses(image, overlap, 1, 0))[2] for overlap in (0.56, 0.57)]
        assert poses[0].GetParameters() != poses[1].GetParameters()  # int(0.57 * 100) is 56: one stream for both

    @pytest.mark.parametrize("overlap", [1.0, 0.8, 0.6, 0.4])
    def test_documented_overlaps_keep_their_poses(self, overlap):
        """The overlaps of the committed tables were seeded by ``int(overlap * 100)``: the same slabs and poses."""
        partial_fov = script("partial_fov")
        image = mni_2mm()
        rng = np.random.default_rng([0, int(overlap * 100)])
        slab = partial_fov.slab(image, overlap, rng)
        truth = random_similarity(rng, foreground_box(slab)[0], max_shift_mm=40.0)
        _, found_slab, found = next(partial_fov.cell_poses(image, overlap, 1, 0))
        assert (found_slab.GetSize(), found_slab.GetOrigin()) == (slab.GetSize(), slab.GetOrigin())
        assert found.GetParameters() == truth.GetParameters()


def _write_rows(path: Path, rows: list[tuple], dpcn_label: str = "dpcn_med") -> Path:
    """A partial_fov CSV of ``(case, overlap, trial, method, tre_mm)`` rows (10 s each)."""
    labels = {"dpcn": dpcn_label, "sitk-geometry": "SimpleITK"}
    with open(path, "w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(["case", "overlap", "trial", "method", "tre_mm", "seconds", "label"])
        writer.writerows([*row, 10.0, labels[row[3]]] for row in rows)
    return path


class TestPartialFovCombine:
    def test_cases_with_other_overlaps_and_dpcn_on_the_baselines_poses(self, tmp_path):
        slabs = _write_rows(tmp_path / "pseudo-ct.csv", [
            *(("pseudo-ct", 1.0, trial, "dpcn", 50.0 if trial == 3 else 0.1) for trial in range(4)),
            *(("pseudo-ct", 1.0, trial, "sitk-geometry", 100.0) for trial in range(2))])
        stroke = _write_rows(tmp_path / "t1-flair.csv", [("t1-flair", 0.8, trial, "dpcn", 0.3) for trial in range(2)])
        output = tmp_path / "out" / "partial_fov.md"
        assert script("partial_fov").main(["--combine", str(slabs), str(stroke), "--output", str(output)]) == 0
        lines = output.read_text().splitlines()
        assert "| dpcn_med | 4 | 75% | – | 0.10 | 10.0 |" in lines
        assert "| dpcn_med, on the baselines' poses | 2 | 100% | – | 0.10 | 10.0 |" in lines
        assert "| SimpleITK | 2 | 0% | – | 100.00 | 10.0 |" in lines
        assert "| dpcn_med | 2 | – | 100% | 0.30 | 10.0 |" in lines
        assert sum("on the baselines' poses |" in line for line in lines) == 1  # not for a case without baselines
        assert output.with_suffix(".png").stat().st_size > 0
        assert sorted(path.name for path in output.parent.iterdir()) == ["partial_fov.md", "partial_fov.png"]

    def test_variants_keep_their_own_lines(self, tmp_path):
        """Two --label variants of dpcn_med on the same poses: a line each (they were merged under the last label)."""
        poses = [("pseudo-ct", 0.6, trial, "dpcn", 0.1 if trial else 50.0) for trial in range(2)]
        defaults = _write_rows(tmp_path / "a.csv", [*poses, ("pseudo-ct", 0.6, 0, "sitk-geometry", 100.0)])
        variant = _write_rows(tmp_path / "b.csv", [(*pose[:4], 0.2) for pose in poses], dpcn_label="B = 64")
        output = tmp_path / "partial_fov.md"
        assert script("partial_fov").main(["--combine", str(defaults), str(variant), "--output", str(output)]) == 0
        lines = output.read_text().splitlines()
        assert "| dpcn_med | 2 | 50% | 25.05 | 10.0 |" in lines and "| B = 64 | 2 | 100% | 0.20 | 10.0 |" in lines
        assert "| dpcn_med, on the baselines' poses | 1 | 0% | 50.00 | 10.0 |" in lines
        assert "| B = 64, on the baselines' poses | 1 | 100% | 0.20 | 10.0 |" in lines

    @pytest.mark.parametrize("name", ["partial_fov", "failure_signals"])
    def test_a_file_given_twice_is_refused(self, name, tmp_path, capsys):
        committed = {"partial_fov": ROOT / "docs" / "benchmarks" / "partial_fov" / "mr-mr.csv",
                     "failure_signals": ROOT / "docs" / "benchmarks" / "failure_signals.csv"}[name]
        output = tmp_path / "table.md"
        with pytest.raises(SystemExit) as exit_:
            script(name).main(["--combine", str(committed), str(committed), "--output", str(output)])
        assert exit_.value.code == 2
        assert f"{committed.name}: line 2: " in capsys.readouterr().err
        assert not output.exists()

    @pytest.mark.parametrize("name, argv, flags", [
        ("partial_fov", ["--trials", "20", "--label", "x"], "--trials, --label"),
        ("partial_fov", ["--cases", "mr-mr", "--fill", "0.5"], "--cases, --fill"),
        ("failure_signals", ["--overlaps", "0.4", "--seed", "0"], "--overlaps, --seed"),
    ])
    def test_run_options_are_refused_with_combine(self, name, argv, flags, tmp_path, capsys):
        """They would be ignored: --combine runs nothing (even an option given at its default)."""
        output = tmp_path / "table.md"
        with pytest.raises(SystemExit) as exit_:
            script(name).main(["--combine", str(tmp_path / "a.csv"), *argv, "--output", str(output)])
        assert exit_.value.code == 2
        assert f"--combine registers nothing, so {flags} cannot apply" in capsys.readouterr().err
        assert not any(tmp_path.iterdir())

    def test_the_committed_table_is_its_csvs_combined(self, tmp_path):
        committed = ROOT / "docs" / "benchmarks" / "partial_fov.md"
        csvs = [str(ROOT / "docs" / "benchmarks" / "partial_fov" / f"{case}.csv")
                for case in ("pseudo-ct", "t1-flair", "mr-mr")]
        output = tmp_path / "partial_fov.md"
        assert script("partial_fov").main(["--combine", *csvs, "--output", str(output)]) == 0

        def tables(path: Path) -> str:
            return path.read_text().split("![success against overlap](partial_fov.png)")[1]

        assert tables(output) == tables(committed)


FAKE_REGISTER = """import json, pathlib, sys
output = pathlib.Path(sys.argv[sys.argv.index("-o") + 1])
output.mkdir()
(output / "report.json").write_text(json.dumps({"timings_s": {"total": TOTAL}}))
raise SystemExit(3)  # low confidence: the result is written all the same
"""


def _fake_tree(folder: Path, total: float) -> Path:
    """A source tree whose `python -m dpcn_med register` writes a report with ``total`` seconds and exits 3."""
    (folder / "dpcn_med").mkdir(parents=True)
    (folder / "dpcn_med" / "__init__.py").write_text("")
    (folder / "dpcn_med" / "__main__.py").write_text(FAKE_REGISTER.replace("TOTAL", str(total)))
    return folder


class TestCliTime:
    def test_a_relative_compared_tree_and_exit_code_3(self, tmp_path, monkeypatch):
        cli_time = script("cli_time")
        monkeypatch.setattr(cli_time, "ROOT", _fake_tree(tmp_path / "main", 1.0))
        old = _fake_tree(tmp_path / "old", 2.0)
        monkeypatch.chdir(tmp_path)
        for name in ("fixed.nii.gz", "moving.nii.gz"):
            (tmp_path / name).write_bytes(b"")
        output = tmp_path / "cli_time.md"
        assert cli_time.main(["--compare", "old", "--pair", "fixed.nii.gz", "moving.nii.gz", "--repeats", "1",
                              "--variants", "no-refine", "--output", str(output)]) == 0
        rows = [line.strip("|").split(" | ") for line in output.read_text().splitlines() if "| no-refine |" in line]
        totals = {cells[0].strip(): cells[9].strip() for cells in rows}
        assert totals == {str(tmp_path / "main"): "1.00", str(old.resolve()): "2.00"}

    def test_each_tree_runs_from_bytecode(self, tmp_path, monkeypatch):
        """Compiled first, whatever PYTHONDONTWRITEBYTECODE says: no tree pays for compiling in its timed runs."""
        cli_time = script("cli_time")
        monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
        monkeypatch.setattr(cli_time, "ROOT", _fake_tree(tmp_path / "main", 1.0))
        old = _fake_tree(tmp_path / "old", 2.0)
        for name in ("fixed.nii.gz", "moving.nii.gz"):
            (tmp_path / name).write_bytes(b"")
        assert cli_time.main(["--compare", str(old), "--pair", str(tmp_path / "fixed.nii.gz"),
                              str(tmp_path / "moving.nii.gz"), "--repeats", "1", "--variants", "no-refine",
                              "--output", str(tmp_path / "cli_time.md")]) == 0
        for tree in (tmp_path / "main", old):
            assert sorted(path.name.split(".")[0] for path in (tree / "dpcn_med" / "__pycache__").glob("*.pyc")) == [
                "__init__", "__main__"]


class TestStageTime:
    def test_trees_alternate_and_each_stage_is_compared_with_the_first(self, tmp_path, monkeypatch):
        """Each worker's seconds are merged over the rounds; the second tree's medians read as ratios."""
        stage_time = script("stage_time")
        old = _fake_tree(tmp_path / "old", 1.0)
        asked, real = [], subprocess.run

        def run(command, **options):
            if command[0] == "git":  # source_label's, through the same module
                return real(command, **options)
            tree = Path(options["cwd"])
            asked.append((tree.name, command[3]))
            slow = 2.0 if tree == old else 1.0
            seconds = {"preprocess": [0.1 * slow, 0.3 * slow], "solve": [0.2, 0.2], "refine": [0.5, 0.7],
                       "whole": [1.0 * slow, 1.2 * slow]}
            return subprocess.CompletedProcess(command, 0, stdout=f"warming up\n{json.dumps(seconds)}\n")

        monkeypatch.setattr(stage_time.subprocess, "run", run)
        output = tmp_path / "stage_time.md"
        assert stage_time.main(["--cases", "mni", "seg3d", "--rounds", "2", "--compare", str(old),
                                "--output", str(output)]) == 0
        main = stage_time.ROOT.name
        assert asked == [(main, "mni"), ("old", "mni"), (main, "seg3d"), ("old", "seg3d")] * 2
        rows = {tuple(cells[:2]): cells[2:] for cells in (
            [cell.strip() for cell in line.strip("|").split("|")] for line in output.read_text().splitlines()
            if line.startswith("| mni |"))}
        assert rows[("mni", str(old.resolve()))] == ["4", "0.400 (2.00x)", "0.200 (1.00x)", "0.600 (1.00x)",
                                                      "2.200 (2.00x)"]
        assert rows[("mni", stage_time.source_label(stage_time.ROOT))][:2] == ["4", "0.200"]

    def test_a_failed_worker_writes_nothing(self, tmp_path, monkeypatch, capsys):
        stage_time = script("stage_time")
        real = subprocess.run
        monkeypatch.setattr(stage_time.subprocess, "run", lambda command, **options: real(command, **options)
                            if command[0] == "git" else subprocess.CompletedProcess(command, 1, stdout=""))
        output = tmp_path / "stage_time.md"
        assert stage_time.main(["--cases", "mni", "--rounds", "1", "--output", str(output)]) == 1
        assert "on mni failed with exit code 1" in capsys.readouterr().err
        assert not output.exists()


def _speed_row(device: str, bandwidth: int) -> dict:
    return {"device": device, "bandwidth": bandwidth, "size": 2 * bandwidth, "repeats": 1, "cold": 1.0,
            "stages": {"solve": 0.5}, "median": 0.5, "min": 0.5, "max": 0.5, "baseline": 0.01, "peak_mib": 1.0,
            "peak_kind": "CUDA allocated"}


class TestSolverSpeed:
    def test_a_device_with_an_index_and_the_command_in_the_table(self, tmp_path, monkeypatch):
        solver_speed = script("solver_speed")
        asked = []

        def run(command, **options):
            asked.append(command[3:5])
            row = _speed_row(command[3], int(command[4]))
            return subprocess.CompletedProcess(command, 0, stdout=f"{json.dumps(row)}\n")

        monkeypatch.setattr(solver_speed.subprocess, "run", run)
        output = tmp_path / "solver_speed.md"
        argv = ["--devices", "cuda:0", "--repeats", "1", "--output", str(output)]
        assert solver_speed.main(argv) == 0
        assert asked == [["cuda:0", "64"], ["cuda:0", "128"]]  # CUDA's default bandwidths
        assert f"Generated by `python benchmarks/solver_speed.py --devices cuda:0 --repeats 1 --output {output}`" \
            in output.read_text()

    @pytest.mark.skipif(torch.cuda.is_available(), reason="the CUDA worker fails only where there is no CUDA")
    def test_a_failing_workers_error_is_shown(self, tmp_path, capfd):
        output = tmp_path / "solver_speed.md"
        argv = ["--devices", "cuda", "--bandwidths", "16", "--repeats", "1", "--output", str(output)]
        assert script("solver_speed").main(argv) == 1
        error = capfd.readouterr().err
        assert "Traceback" in error  # the worker's own
        assert "the worker for cuda B=16 failed with exit code 1 (its error is above); nothing written" in error
        assert not output.exists()


class TestWording:
    def test_solver_accuracy_names_its_whole_command(self, tmp_path, monkeypatch):
        solver_accuracy = script("solver_accuracy")
        monkeypatch.setattr(solver_accuracy, "_image", lambda name: None)  # every volume absent: no registration
        output = tmp_path / "solver_accuracy.md"
        try:
            assert solver_accuracy.main(["--poses", "1", "--bandwidths", "32", "--output", str(output)]) == 0
        finally:
            torch.set_grad_enabled(True)  # the script turns gradients off for its process
        assert (f"Generated by `python benchmarks/solver_accuracy.py --poses 1 --bandwidths 32 --output {output}`"
                in output.read_text())

    def test_candidate_cost_help_has_its_whole_first_sentence(self, capsys):
        with pytest.raises(SystemExit) as exit_:
            script("candidate_cost").main(["--help"])
        assert exit_.value.code == 0
        assert "no stored-pose start), side by side." in " ".join(capsys.readouterr().out.split())

    @pytest.mark.parametrize("starts, text", [
        (1, "1 starting rotation (the first of the cube's 24)"),
        (2, "2 starting rotations (the first 2 of the cube's 24)"),
        (24, "24 starting rotations (the cube's 24)"),
        (25, "25 starting rotations (the cube's 24 and 1 seeded uniform one)"),
        (96, "96 starting rotations (the cube's 24 and 72 seeded uniform ones)"),
    ])
    def test_mridir_reference_starts_by_their_count(self, starts, text):
        assert script("mridir_reference").starts_text(starts) == text


class TestFailureSignals:
    def test_a_new_output_folder_is_made_before_the_work(self, tmp_path, monkeypatch):
        failure_signals = script("failure_signals")
        output = tmp_path / "new" / "failure_signals.md"

        def run(case: str, overlaps: list[float], trials: int, seed: int) -> list[dict]:
            assert output.parent.is_dir()
            return [{"case": case, "overlap_fraction": 0.6, "trial": trial, "tre_mm": tre, "start": "candidate 0",
                     "confidence": confidence, "overlap": 1.0, "mattes_mi": -1.0, "nmi": 1.2, "runner_up_gap": 0.1}
                    for trial, (tre, confidence) in enumerate([(0.1, 0.5), (50.0, 0.001)])]

        monkeypatch.setattr(failure_signals, "run", run)
        assert failure_signals.main(["--cases", "mr-mr", "--trials", "2", "--output", str(output)]) == 0
        assert output.is_file() and output.with_suffix(".csv").is_file()


class TestCompareRuns:
    def test_the_committed_table_is_its_runs_joined(self, tmp_path):
        folder = ROOT / "docs" / "benchmarks" / "refine_speed"
        committed = (folder.parent / "refine_speed.md").read_text()
        output = tmp_path / "refine_speed.md"
        assert script("compare_runs").main([str(folder / "e7efb34" / "results.csv"),
                                            str(folder / "e02ba00" / "results.csv"), "--labels", "e7efb34", "e02ba00",
                                            "--output", str(output)]) == 0
        assert output.read_text().split("\n\n", 2)[2] == committed.split("\n\n", 2)[2]
        assert "| seg3d | dpcn | 12 | 4.36 | 1.50 | 2.97x | 12 / 12 |" in committed

    def test_runs_with_no_pose_in_common_are_refused(self, tmp_path, capsys):
        header = "case,bin,trial,method,tre_mm,seconds,peak_mib\n"
        (tmp_path / "a.csv").write_text(header + "mni,0-30,0,dpcn,0.1,1.0,10\n")
        (tmp_path / "b.csv").write_text(header + "mni,0-30,1,dpcn,0.1,0.5,10\n")
        output = tmp_path / "table.md"
        with pytest.raises(SystemExit) as exit_:
            script("compare_runs").main([str(tmp_path / "a.csv"), str(tmp_path / "b.csv"), "--output", str(output)])
        assert exit_.value.code == 2 and "share no pose" in capsys.readouterr().err
        assert not output.exists()


class TestQualityFit:
    def test_the_shipped_model_and_its_page_are_the_committed_registrations_fitted(self, tmp_path):
        from dpcn_med.quality import shipped_model

        output = tmp_path / "quality.md"
        csv_path = ROOT / "docs" / "benchmarks" / "quality" / "registrations.csv"
        assert script("quality_fit").main([str(csv_path), "--output", str(output)]) == 0
        committed = (ROOT / "docs" / "benchmarks" / "quality.md").read_text()
        assert output.read_text().split("![reliability]")[1] == committed.split("![reliability]")[1]
        shipped = shipped_model()
        assert f"threshold {shipped.threshold:.3f}," in committed and output.with_suffix(".png").is_file()

    def test_the_threshold_sits_midway_between_the_classes(self):
        choose = script("quality_fit").choose_threshold
        p = np.array([0.05, 0.2, 0.8, 0.95])
        ok = np.array([False, False, True, True])
        assert choose(p, ok, 0.0) == pytest.approx(0.5)  # log-odds midway between 0.2 and 0.8
        assert choose(np.array([0.9, 0.95]), np.array([True, True]), 0.0) == 0.9  # no failure below: the lowest success


class TestLearnedAccuracy:
    @pytest.mark.parametrize("extra, rows, title", [
        ([], 1, "# Held-out heterogeneous accuracy"),
        (["--per-volume"], 2, "# Held-out heterogeneous accuracy"),
        (["--volumes", "training"], 1, "# Heterogeneous accuracy on the training volumes"),
    ])
    def test_one_row_per_model_and_group(self, extra, rows, title, tmp_path):
        (tmp_path / "tiny.yaml").write_text(
            "model: {bandwidth: 8, channels: [4, 8], modalities: [ct, mr]}\n"
            "data: {volumes: [mni], validation_volumes: [mni, mni-head], pair: {max_shift_fraction: 0.1}}\n")
        output = tmp_path / "table.md"
        assert script("learned_accuracy").main(["--config", str(tmp_path / "tiny.yaml"), "--models", "none",
                                                "--pairs", "2", "--device", "cpu", "--output", str(output),
                                                *extra]) == 0
        text = output.read_text()
        assert text.startswith(title)
        table = [line for line in text.splitlines() if line.startswith("| learning-free solver |")]
        assert len(table) == rows
        for line in table:
            cells = [cell.strip() for cell in line.strip("|").split("|")]
            assert len(cells) == (8 if "--per-volume" in extra else 7)
            assert cells[-1].endswith("%") and 0.0 <= float(cells[-1][:-1]) <= 100.0
        if "--per-volume" in extra:
            assert [line.split("|")[2].strip() for line in table] == ["mni", "mni-head"]

    def test_a_variant_is_a_learning_free_row_with_its_setting(self, tmp_path):
        (tmp_path / "tiny.yaml").write_text(
            "model: {bandwidth: 8, channels: [4, 8], modalities: [ct, mr]}\n"
            "data: {volumes: [mni], validation_volumes: [mni], pair: {max_shift_fraction: 0.1}}\n")
        output = tmp_path / "table.md"
        argv = ["--config", str(tmp_path / "tiny.yaml"), "--models", "none", "--pairs", "2", "--device", "cpu",
                "--output", str(output), "--variants", "entropy_ranking_weight=0", "candidate_size=8;finalists=2"]
        assert script("learned_accuracy").main(argv) == 0
        labels = [line.split("|")[1].strip() for line in output.read_text().splitlines()
                  if line.startswith("| learning-free solver")]
        assert labels == ["learning-free solver", "learning-free solver, `entropy_ranking_weight=0`",
                          "learning-free solver, `candidate_size=8`, `finalists=2`"]
        # --models alone (no model) leaves the variants' rows only.
        only = tmp_path / "only.md"
        assert script("learned_accuracy").main([*argv[:2], "--models", *argv[4:9], str(only), "--variants",
                                                "entropy_ranking_weight=0"]) == 0
        assert [line.split("|")[1].strip() for line in only.read_text().splitlines()
                if line.startswith("| learning-free solver")] == ["learning-free solver, `entropy_ranking_weight=0`"]
        # A setting the solver refuses stops the run with the solver's message, and no table is written.
        refused = tmp_path / "refused.md"
        with pytest.raises(InputError, match="entropy_ranking_weight is -1"):
            script("learned_accuracy").main([*argv[:-5], "--output", str(refused), "--variants",
                                             "entropy_ranking_weight=-1"])
        assert not refused.exists()


class TestRotationGains:
    def test_copies_scale_the_rotation_gains_only_and_keep_the_record(self, tmp_path, capsys):
        from dpcn_med.models import DPCN, ModelConfig, load_model, save_model

        model = DPCN(ModelConfig(bandwidth=8, channels=(4, 8)))
        for name, gain in (("rotation_fixed", 0.5), ("rotation_moving", 0.25), ("translation_fixed", 0.125)):
            getattr(model, name).gain.data.fill_(gain)
        save_model(model, tmp_path / "model", record={"steps": 7})
        assert script("rotation_gains").main([str(tmp_path / "model.safetensors"), "4", "0.5"]) == 0
        scaled = load_model(tmp_path / "model_x4")
        assert [getattr(scaled, name).gain.item() for name in ("rotation_fixed", "rotation_moving",
                                                                 "translation_fixed")] == [2.0, 1.0, 0.125]
        assert load_model(tmp_path / "model_x0.5").rotation_fixed.gain.item() == 0.25
        for name, tensor in model.state_dict().items():
            if not name.endswith(".gain"):
                torch.testing.assert_close(scaled.state_dict()[name], tensor)
        record = json.loads((tmp_path / "model_x4.json").read_text())["record"]
        assert record == {"steps": 7, "rotation_gains_scaled_by": 4.0}
        assert "model_x4: gains rotation_fixed 2" in capsys.readouterr().out

    def test_a_factor_must_be_positive(self, tmp_path):
        with pytest.raises(SystemExit):
            script("rotation_gains").main([str(tmp_path / "model"), "0"])


class TestHeldoutFactors:
    def test_each_row_changes_one_factor_of_the_pairs(self):
        from dpcn_med.synth import PairConfig
        from dpcn_med.synth.contrast import ContrastConfig

        base = PairConfig(crop_probability=0.3)
        rows = script("heldout_factors").variants(base)
        assert rows["as benchmarked (learned_accuracy.py)"] == base
        assert rows["no slab crop"] == PairConfig(crop_probability=0.0)
        identity = rows["same contrast on both sides (identity)"]
        assert (identity.fixed_modality, identity.moving_modality) == ("identity", "identity")
        thick = rows["monotonic map and thick slices alone"]
        assert thick.fixed_contrast == thick.moving_contrast == ContrastConfig(
            monotonic=True, bias_strength=0.0, sigma_range=(0.0, 0.0), noise_std_range=(0.0, 0.0))
        assert rows["non-monotonic intensity map alone"].fixed_contrast.factor_range == (1.0, 1.0)
        assert not rows["non-monotonic intensity map alone"].fixed_contrast.monotonic


class TestUltrasound:
    def test_probes_look_down_within_the_tilt_and_cover_every_azimuth(self):
        module = script("ultrasound")
        rng = np.random.default_rng(0)
        directions = np.stack([module.probe_direction(rng) for _ in range(2000)])
        assert np.allclose(np.linalg.norm(directions, axis=1), 1.0)
        tilt = np.degrees(np.arccos(-directions[:, 2]))
        assert tilt.max() <= module.MAX_TILT_DEGREES + 1e-9 and tilt.max() > module.MAX_TILT_DEGREES - 2
        # uniform over the cap: half its area lies within the angle whose cosine is the mean of 1 and cos(60)
        half = np.degrees(np.arccos((1 + np.cos(np.radians(module.MAX_TILT_DEGREES))) / 2))
        assert abs(np.mean(tilt < half) - 0.5) < 0.05
        azimuth = np.arctan2(directions[:, 1], directions[:, 0])
        assert np.histogram(azimuth, bins=4, range=(-np.pi, np.pi))[0].min() > 400

    def test_the_table_counts_successes_and_repeats_dpcn_on_the_baselines_poses(self):
        module = script("ultrasound")
        rows = [{"case": "us-mr", "trial": trial, "method": "dpcn", "tre_mm": tre, "seconds": 2.0, "flagged": flag}
                for trial, (tre, flag) in enumerate([(1.0, False), (2.0, True), (3.0, True), (50.0, True)])]
        rows += [{"case": "us-mr", "trial": trial, "method": "sitk-exhaustive", "tre_mm": tre, "seconds": 9.0}
                 for trial, tre in enumerate([0.5, 79.5])]
        rows += [{"case": "us-mr", "trial": trial, "method": module.FROM_TRUTH, "tre_mm": 1.0, "seconds": 1.0}
                 for trial in range(4)]
        text = module.table(rows, ["dpcn", module.FROM_TRUTH, "sitk-exhaustive"], baseline_trials=2)
        assert text.index("from the true pose | 4 | 4 of 4 (100%)") < text.index("on the baselines' 2 poses")
        assert "| us-mr | dpcn_med (defaults) | 4 | 2 of 4 (50%) | 2.5 | 2.0 | 3 of 4 |" in text
        assert "| us-mr | dpcn_med, on the baselines' 2 poses | 2 | 2 of 2 (100%) | 1.5 | 2.0 | 1 of 2 |" in text
        assert ("| us-mr | SimpleITK MI after an exhaustive Euler-angle search | 2 | 1 of 2 (50%) | 40.0 | 9.0 "
                "|  |") in text
