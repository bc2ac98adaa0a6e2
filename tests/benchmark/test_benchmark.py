"""dpcn_med.benchmark: poses by rotation bin, every tool's transform read the right way round, the outputs."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace

import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med import benchmark
from dpcn_med.benchmark import (
    BenchmarkConfig,
    global_success,
    markdown,
    rotation_in_bin,
    run_benchmark,
    write_outputs,
)
from dpcn_med.cli import main
from dpcn_med.errors import InputError
from dpcn_med.evaluation import foreground_corners, moved_copy, target_registration_error
from dpcn_med.geometry import homogeneous_matrix
from dpcn_med.preprocess import foreground_box
from tests.test_registration import mni_2mm


class TestRotationInBin:
    def test_angle_in_the_bin_and_shift_bounded(self):
        rng = np.random.default_rng(0)
        centre = np.array([10.0, -20.0, 5.0])
        for _ in range(50):
            transform = rotation_in_bin(rng, 120, 150, centre, 60.0)
            rotation = homogeneous_matrix(transform)[:3, :3]
            angle = math.degrees(math.acos(np.clip((np.trace(rotation) - 1) / 2, -1, 1)))
            assert 120 - 1e-6 <= angle < 150 + 1e-6
            assert np.linalg.norm(transform.GetTranslation()) <= 60.0
            np.testing.assert_allclose(transform.GetCenter(), centre)


@pytest.mark.parametrize("method", ["ants-rigid", "elastix-rigid"])
def test_classical_tools_read_the_right_way_round(method, tmp_path):
    """A small known rotation, well inside every local optimiser's capture range: the tool's result, converted to a
    fixed-to-moving SimpleITK transform, must give it back (a transform read the wrong way round is off by cm)."""
    if method not in benchmark.available_methods():
        pytest.skip(f"{benchmark.METHODS[method][1]} is not installed (pip install 'dpcn_med[benchmark]')")
    fixed = mni_2mm()
    truth = rotation_in_bin(np.random.default_rng(1), 8, 10, foreground_box(fixed)[0], 8.0)
    estimate = benchmark.METHODS[method][2](fixed, moved_copy(fixed, truth), tmp_path)
    assert target_registration_error(estimate, truth, foreground_corners(fixed)) < 1.0


class TestRunBenchmark:
    def test_the_global_method_works_at_any_angle_a_local_one_does_not(self, tmp_path):
        config = BenchmarkConfig(cases=("mni",), methods=("dpcn-global", "sitk-geometry"), bins=((0, 30), (150, 180)),
                                 trials=1, max_shift_mm=20.0)
        rows = run_benchmark(config)
        assert [(r["bin"], r["method"]) for r in rows] == [("0-30", "dpcn-global"), ("0-30", "sitk-geometry"),
                                                           ("150-180", "dpcn-global"), ("150-180", "sitk-geometry")]
        tre = {(r["bin"], r["method"]): r["tre_mm"] for r in rows}
        assert tre[("0-30", "dpcn-global")] < 4.0 and tre[("150-180", "dpcn-global")] < 4.0  # about one grid voxel
        assert tre[("0-30", "sitk-geometry")] < 2.0 and tre[("150-180", "sitk-geometry")] > 20.0
        assert all(r["seconds"] > 0 for r in rows)

        text = write_outputs(rows, config, tmp_path / "out", command="test")
        assert {p.name for p in (tmp_path / "out").iterdir()} == {"results.csv", "summary.md", "success.png"}
        write_outputs(rows, config, tmp_path / "run", command="test", settings=benchmark.pose_settings(config))
        assert json.loads((tmp_path / "run" / "settings.json").read_text())["bins"] == ["0-30", "150-180"]
        with open(tmp_path / "out" / "results.csv", newline="") as handle:
            assert len(list(csv.DictReader(handle))) == 4
        assert "| dpcn_med learning-free, global estimate only | 100% | 100% |" in text
        # the solver's own criterion, beside the TRE: the global estimate meets it at any angle, the local tool not
        assert [global_success(r) for r in rows] == [True, True, True, False]
        assert all(r["canonical_voxel_mm"] > 2.0 and 0 <= r["rotation_error_deg"] <= 180 for r in rows)
        assert "Global estimate within 5 degrees and 2 canonical voxels" in text
        assert text.count("| dpcn_med learning-free, global estimate only | 100% | 100% |") == 2
        assert "| SimpleITK MI from GEOMETRY initialiser | 100% | 0% |" in text

    def test_the_showcase_is_rendered_before_and_after(self, tmp_path):
        pytest.importorskip("pyvista", reason="pyvista (the mesh extra) is not installed")
        config = BenchmarkConfig(cases=("mni",), methods=("dpcn",), bins=((150, 180),), trials=1)
        showcase: dict = {}
        rows = run_benchmark(config, showcase=showcase)
        assert showcase["case"] == "mni" and showcase["bin"] == "150-180" and rows[0]["tre_mm"] < 2.0
        text = write_outputs(rows, config, tmp_path, command="test", showcase=showcase)
        assert (tmp_path / "render.png").stat().st_size > 10_000
        assert "![before and after](render.png)" in text

    def test_a_run_of_some_bins_registers_the_poses_of_a_run_of_every_bin(self, tmp_path, monkeypatch):
        config = BenchmarkConfig(cases=("mni",), methods=("dpcn-global",), bins=((0, 30), (60, 90), (150, 180)))
        poses: list[tuple[float, ...]] = []
        moved_copy_ = benchmark.runner.moved_copy
        monkeypatch.setattr(benchmark.runner, "moved_copy", lambda image, truth: (
            poses.append(truth.GetParameters()), moved_copy_(image, truth))[1])
        every = run_benchmark(config)
        some = run_benchmark(replace(config, run_bins=("60-90",)))
        assert [r["bin"] for r in every] == ["0-30", "60-90", "150-180"] and [r["bin"] for r in some] == ["60-90"]
        assert poses[3] == poses[1] and some[0]["tre_mm"] == pytest.approx(every[1]["tre_mm"])
        text = write_outputs(some, config, tmp_path, command="test")
        assert "| dpcn_med learning-free, global estimate only | - | 100% | - |" in text
        with pytest.raises(InputError, match="unknown bin 60-80; use one of 0-30, 60-90, 150-180"):
            run_benchmark(replace(config, run_bins=("60-80",)))

    def test_unknown_names_are_refused(self):
        with pytest.raises(InputError, match="unknown case brain; use one of mni"):
            run_benchmark(BenchmarkConfig(cases=("brain",), methods=("dpcn",)))
        with pytest.raises(InputError, match="unknown method flirt; use one of dpcn"):
            run_benchmark(BenchmarkConfig(cases=("mni",), methods=("flirt",)))

    def test_cli(self, tmp_path, capsys):
        code = main(["benchmark", "--cases", "mni", "--methods", "dpcn-global", "--trials", "1", "--bins", "0-30",
                     "150-180", "-o", str(tmp_path / "b")])
        assert code == 0
        output = capsys.readouterr().out
        assert "# dpcn_med against SimpleITK, ANTs and elastix" in output
        assert (f"Generated by `dpcn-med benchmark --cases mni --methods dpcn-global --trials 1 --bins 0-30 150-180 -o "
                f"{tmp_path / 'b'}`") in output
        assert "| dpcn_med learning-free, global estimate only | 100% | - | - | - | - | 100% |" in output
        assert (tmp_path / "b" / "success.png").is_file()

    def test_combine_makes_one_summary_of_runs_split_over_processes(self, tmp_path, capsys):
        """Two runs of the same poses, one method each (as two cores would make them), become one summary; what cannot
        be combined is refused with exit 2 and nothing written."""
        for method in ("dpcn-global", "sitk-geometry"):
            assert main(["benchmark", "--cases", "mni", "--methods", method, "-o", str(tmp_path / method)]) == 0
        parts = [benchmark.combine_results([tmp_path / method]) for method in ("dpcn-global", "sitk-geometry")]
        capsys.readouterr()
        assert main(["benchmark", "--combine", str(tmp_path / "dpcn-global"), str(tmp_path / "sitk-geometry"),
                     "-o", str(tmp_path / "both")]) == 0
        output = capsys.readouterr().out
        combined = benchmark.combine_results([tmp_path / "both"])
        assert combined == parts[0] + parts[1] and len(combined) == 12
        assert isinstance(combined[0]["trial"], int) and isinstance(combined[0]["tre_mm"], float)
        assert "1 pose(s) per case, method and bin" in output and "--combine" in output
        assert "| dpcn_med learning-free, global estimate only |" in output
        assert "| SimpleITK MI from GEOMETRY initialiser |" in output
        assert (tmp_path / "both" / "success.png").is_file()

        before = (tmp_path / "both" / "results.csv").read_bytes()
        assert main(["benchmark", "--combine", str(tmp_path / "both"), "-o", str(tmp_path / "both")]) == 2
        assert "is an input of --combine" in capsys.readouterr().err
        assert (tmp_path / "both" / "results.csv").read_bytes() == before
        assert main(["benchmark", "--combine", str(tmp_path / "both"), str(tmp_path / "dpcn-global"),
                     "-o", str(tmp_path / "twice")]) == 2
        assert "mni, 0-30, 0, dpcn-global is also in" in capsys.readouterr().err
        (tmp_path / "bad").mkdir()
        (tmp_path / "bad" / "results.csv").write_text("case,bin\nmni,0-30\n")
        (tmp_path / "more").mkdir()
        lines = (tmp_path / "both" / "results.csv").read_text().splitlines()
        (tmp_path / "more" / "results.csv").write_text("\n".join([lines[0] + ",note", lines[1] + ",x"]) + "\n")
        for folder, message in ((tmp_path / "bad", "results.csv: no column trial, method, tre_mm, seconds, peak_mib"),
                                (tmp_path / "more", "results.csv: unknown column 'note'"),
                                (tmp_path / "none", "results.csv: not found")):
            assert main(["benchmark", "--combine", str(folder), "-o", str(tmp_path / "out")]) == 2
            assert message in capsys.readouterr().err
        assert not (tmp_path / "twice").exists() and not (tmp_path / "out").exists()

    def test_impossible_rows_are_refused_by_combine(self, tmp_path, capsys):
        header = ",".join(benchmark.RESULT_FIELDS)
        good = "mni,0-30,0,dpcn,0.02,2.5,-0.2"  # a peak slightly below zero happens (the RSS reset is approximate)
        (tmp_path / "good").mkdir()
        (tmp_path / "good" / "results.csv").write_text(f"{header}\n{good}\n")
        assert benchmark.combine_results([tmp_path / "good"])[0]["peak_mib"] == -0.2
        for name, row, message in (("bin", "mni,200-230,0,dpcn,0.02,2.5,100", "line 2: unknown bin '200-230'"),
                                   ("trial", "mni,0-30,-3,dpcn,0.02,2.5,100", "line 2: trial -3; expected a finite"),
                                   ("nan", "mni,0-30,0,dpcn,nan,2.5,100", "line 2: tre_mm nan; expected a finite"),
                                   ("negative", "mni,0-30,0,dpcn,-50,2.5,100", "line 2: tre_mm -50.0; expected"),
                                   ("time", "mni,0-30,0,dpcn,0.02,inf,100", "line 2: seconds inf; expected")):
            (tmp_path / name).mkdir()
            (tmp_path / name / "results.csv").write_text(f"{header}\n{row}\n")
            assert main(["benchmark", "--combine", str(tmp_path / name), "-o", str(tmp_path / "out")]) == 2
            assert message in capsys.readouterr().err, name
        assert main(["benchmark", "--combine", str(tmp_path / "good"), "--cases", "mni", "--bins", "0-30",
                     "-o", str(tmp_path / "out")]) == 2
        assert "--combine registers nothing, so --cases, --bins cannot apply" in capsys.readouterr().err
        assert not (tmp_path / "out").exists()

    def test_what_cannot_run_is_refused_before_any_work(self, tmp_path, capsys, monkeypatch):
        config = BenchmarkConfig(cases=("mni",), methods=("dpcn-global",), bins=((0, 30),))
        with pytest.raises(InputError, match="case mni given more than once"):
            run_benchmark(replace(config, cases=("mni", "mni")))
        with pytest.raises(InputError, match="method dpcn-global given more than once"):
            run_benchmark(replace(config, methods=("dpcn-global", "dpcn-global")))
        with pytest.raises(InputError, match=r"nothing to register: 1 case\(s\), 0 trial\(s\)"):
            run_benchmark(replace(config, trials=0))
        for flag, value, message in (("--trials", "-2", "argument --trials: -2 is too few; give at least 1"),
                                     ("--trials", "0", "argument --trials: 0 is too few; give at least 1"),
                                     ("--seed", "-1", "argument --seed: -1 is too few; give at least 0"),
                                     ("--seed", "x", "argument --seed: 'x' is not a whole number")):
            with pytest.raises(SystemExit) as exit_:  # at the command line, before any volume is loaded
                main(["benchmark", "--cases", "mni", flag, value, "-o", str(tmp_path / "b")])
            assert exit_.value.code == 2 and message in capsys.readouterr().err
        assert not (tmp_path / "b").exists()
        (tmp_path / "file").write_text("x")
        assert main(["benchmark", "--cases", "mni", "-o", str(tmp_path / "file")]) == 2
        assert "exists and is not a folder" in capsys.readouterr().err

        # Without antspyx: asked for by name, refused; among the default methods, left out and said so.
        monkeypatch.setattr(benchmark.runner, "available_methods", lambda: ("dpcn", "dpcn-global"))
        with pytest.raises(InputError, match=r"ants-rigid needs antspyx \(pip install 'dpcn_med\[benchmark\]'\)"):
            run_benchmark(replace(config, methods=("dpcn-global", "ants-rigid")))
        said: list[str] = []
        rows = run_benchmark(replace(config, methods=("dpcn-global", "ants-rigid")), progress=said.append,
                             skip_missing=True)
        assert [r["method"] for r in rows] == ["dpcn-global"]
        assert said[0] == "left out: ants-rigid needs antspyx (pip install 'dpcn_med[benchmark]')"


def _row(bin_: str, trial: int, method: str, tre: float, seconds: float = 1.0, peak: float = 10.0,
         rotation: float = 1.0, centre: float = 1.0) -> dict:
    return {"case": "mni", "bin": bin_, "trial": trial, "method": method, "tre_mm": tre, "seconds": seconds,
            "peak_mib": peak, "rotation_error_deg": rotation, "centre_error_mm": centre, "canonical_voxel_mm": 4.0}


def _results(folder, rows: list[dict], settings: dict | None = None):
    folder.mkdir()
    header = ",".join(benchmark.RESULT_FIELDS)
    lines = [",".join(str(row[field]) for field in benchmark.RESULT_FIELDS) for row in rows]
    (folder / "results.csv").write_text("\n".join([header, *lines]) + "\n")
    if settings is not None:
        (folder / "settings.json").write_text(json.dumps(settings))
    return folder


class TestSummary:
    def test_medians_are_over_the_registrations_not_the_bins_medians(self):
        """One pose in 0-30, three in 30-60: the bins' medians (1, 20) have median 10.5; the four registrations 15."""
        rows = [_row("0-30", 0, "dpcn", 1.0, 1.0, 100.0),
                *(_row("30-60", trial, "dpcn", tre, tre, 10 * tre) for trial, tre in enumerate((10.0, 20.0, 30.0)))]
        text = markdown(rows, BenchmarkConfig(bins=((0, 30), (30, 60))))
        assert "| median TRE (mm) | median s | median peak MiB |" in text
        assert "| dpcn_med learning-free + refinement (defaults) | 100% | 0% | 15.00 | 15.0 | 150 |" in text

    def test_the_global_criterion_is_5_degrees_and_2_canonical_voxels(self):
        assert global_success(_row("0-30", 0, "dpcn", 9.0, rotation=4.9, centre=7.9))
        assert not global_success(_row("0-30", 0, "dpcn", 0.1, rotation=5.1, centre=0.1))
        assert not global_success(_row("0-30", 0, "dpcn", 0.1, rotation=0.1, centre=8.1))  # 2 voxels of 4 mm
        assert global_success({**_row("0-30", 0, "dpcn", 1.0), "rotation_error_deg": math.nan}) is None
        rows = [_row("0-30", 0, "dpcn-global", 9.0, rotation=2.0), _row("0-30", 1, "dpcn-global", 9.0, rotation=60.0),
                _row("30-60", 0, "dpcn-global", 9.0)]
        text = markdown(rows, BenchmarkConfig(bins=((0, 30), (30, 60))))
        assert "canonical voxels (8.0 mm at the fixed grid's centre" in text
        assert text.endswith("| dpcn_med learning-free, global estimate only | 50% | 100% |\n")

    def test_results_written_before_the_global_columns_combine_without_its_table(self, tmp_path, capsys):
        old = ("case,bin,trial,method,tre_mm,seconds,peak_mib\n"
               "mni,0-30,0,dpcn,0.5,2.0,10\nmni,0-30,1,dpcn,9.0,2.0,10\n")
        (tmp_path / "old").mkdir()
        (tmp_path / "old" / "results.csv").write_text(old)
        rows = benchmark.combine_results([tmp_path / "old"])
        assert all(math.isnan(r[name]) for r in rows for name in benchmark.GLOBAL_FIELDS)
        assert main(["benchmark", "--combine", str(tmp_path / "old"), "-o", str(tmp_path / "out")]) == 0
        summary = (tmp_path / "out" / "summary.md").read_text()
        assert "| dpcn_med learning-free + refinement (defaults) | 50% |" in summary and "Global estimate" not in summary
        (tmp_path / "some").mkdir()
        (tmp_path / "some" / "results.csv").write_text(old.replace("peak_mib", "peak_mib,rotation_error_deg")
                                                       .replace(",10\n", ",10,3.0\n"))
        assert main(["benchmark", "--combine", str(tmp_path / "some"), "-o", str(tmp_path / "out2")]) == 2
        assert "has some of the columns rotation_error_deg" in capsys.readouterr().err

    def test_sitk_exhaustive_samples_with_a_fixed_seed(self, monkeypatch):
        """SimpleITK takes seed 0 for the wall clock: a new sample, and result, on every run."""
        seeds: list[int] = []

        def spy(self, percentage, seed=0):
            seeds.append(seed)
            raise InterruptedError  # the seed is all this test needs

        monkeypatch.setattr(benchmark.methods.sitk.ImageRegistrationMethod, "SetMetricSamplingPercentage", spy)
        image = mni_2mm()
        with pytest.raises(InterruptedError):
            benchmark.METHODS["sitk-exhaustive"][2](image, image, None)
        assert seeds == [benchmark.BASELINE_REFINEMENT.seed] and seeds[0] != 0

    def test_combine_counts_the_poses_of_every_cell(self, tmp_path, capsys):
        """Cells of 2 and 1 poses give a range (the highest trial number told nothing about the others)."""
        one = _results(tmp_path / "one", [_row("0-30", 0, "dpcn", 0.1), _row("0-30", 1, "dpcn", 0.1)])
        two = _results(tmp_path / "two", [_row("0-30", 0, "sitk-geometry", 0.1)])
        assert main(["benchmark", "--combine", str(one), str(two), "-o", str(tmp_path / "out")]) == 0
        assert "1-2 pose(s) per case, method and bin" in capsys.readouterr().out

    def test_combine_refuses_folders_of_other_settings(self, tmp_path, capsys):
        settings = benchmark.pose_settings(BenchmarkConfig(trials=2))
        one = _results(tmp_path / "one", [_row("0-30", 0, "dpcn", 0.1)], settings)
        two = _results(tmp_path / "two", [_row("0-30", 0, "sitk-geometry", 0.1)], {**settings, "trials": 1})
        old = _results(tmp_path / "old", [_row("0-30", 0, "elastix-rigid", 0.1)])  # before settings.json
        assert main(["benchmark", "--combine", str(one), str(two), "-o", str(tmp_path / "out")]) == 2
        assert "two/settings.json: other settings than" in capsys.readouterr().err
        assert not (tmp_path / "out").exists()
        assert main(["benchmark", "--combine", str(one), str(old), "-o", str(tmp_path / "out")]) == 0
        assert not (tmp_path / "out" / "settings.json").exists()  # the old folder's settings are unknown
        assert main(["benchmark", "--combine", str(one), "-o", str(tmp_path / "same")]) == 0
        assert json.loads((tmp_path / "same" / "settings.json").read_text()) == settings

    def test_the_help_names_the_methods_quick_mode_leaves_out(self, capsys):
        with pytest.raises(SystemExit):
            main(["benchmark", "--help"])
        assert "quick mode leaves out ants-multistart" in " ".join(capsys.readouterr().out.split())
        assert set(benchmark.METHODS) - set(benchmark.QUICK.methods) == {"ants-multistart"}


class TestFailures:
    def test_a_baseline_that_raises_scores_the_starting_pose_and_the_run_goes_on(self, tmp_path, monkeypatch):
        """An ITK error in a baseline stopped the whole run, at the same pose on every rerun."""
        label, package, _ = benchmark.METHODS["sitk-geometry"]

        def broken(fixed, moving, folder):
            raise RuntimeError("Joint PDF summed to zero")

        monkeypatch.setitem(benchmark.METHODS, "sitk-geometry", (label, package, broken))
        said: list[str] = []
        config = BenchmarkConfig(cases=("mni",), methods=("sitk-geometry",), trials=1, run_bins=("150-180",))
        rows = benchmark.run_benchmark(config, progress=said.append)
        fixed, _ = benchmark.CASES["mni"][2]()
        rng = np.random.default_rng([config.seed, 0])
        truth = [benchmark.rotation_in_bin(rng, low, high, foreground_box(fixed)[0], config.max_shift_mm)
                 for low, high in config.bins][-1]
        start = target_registration_error(sitk.Transform(3, sitk.sitkIdentity), truth, foreground_corners(fixed))
        assert [r["tre_mm"] for r in rows] == [pytest.approx(start)] and start > 2.0
        assert said[-2].endswith("sitk-geometry: raised RuntimeError (Joint PDF summed to zero); scored at the "
                                 "starting pose")

    def test_an_error_of_dpcn_med_stops_the_run(self, monkeypatch):
        label, package, _ = benchmark.METHODS["dpcn-global"]

        def broken(fixed, moving, folder):
            raise RuntimeError("a bug of ours")

        monkeypatch.setitem(benchmark.METHODS, "dpcn-global", (label, package, broken))
        with pytest.raises(RuntimeError, match="a bug of ours"):
            benchmark.run_benchmark(BenchmarkConfig(cases=("mni",), methods=("dpcn-global",), trials=1,
                                                    run_bins=("0-30",)))


class TestJournal:
    """An interrupted run (hours of ANTs on the real volumes) goes on where it stopped."""

    def test_an_interrupted_run_goes_on_where_it_stopped(self, tmp_path, capsys, monkeypatch):
        label, package, register_ = benchmark.METHODS["dpcn-global"]
        calls: list[int] = []

        def interrupted_second(fixed, moving, folder):
            calls.append(1)
            if len(calls) == 2:
                raise KeyboardInterrupt
            return register_(fixed, moving, folder)

        monkeypatch.setitem(benchmark.METHODS, "dpcn-global", (label, package, interrupted_second))
        command = ["benchmark", "--cases", "mni", "--methods", "dpcn-global", "--trials", "1", "--bins", "0-30",
                   "150-180", "-o", str(tmp_path / "b")]
        assert main(command) == 130
        assert "the finished registrations are kept (results.partial.jsonl" in capsys.readouterr().err
        journal = benchmark.Journal(tmp_path / "b" / benchmark.JOURNAL, BenchmarkConfig(trials=1))
        first = journal.rows()
        assert list(first) == [("mni", "0-30", 0, "dpcn-global")] and not (tmp_path / "b" / "results.csv").exists()

        assert main(command) == 0
        assert len(calls) == 3  # the second run registered only the unfinished pose
        assert "going on from" in capsys.readouterr().err
        rows = benchmark.combine_results([tmp_path / "b"])
        assert [r["bin"] for r in rows] == ["0-30", "150-180"] and rows[0] == first[("mni", "0-30", 0, "dpcn-global")]
        assert not journal.path.exists()

    def test_a_registration_journalled_before_the_global_fields_reads_them_as_nan(self, tmp_path):
        journal = benchmark.Journal(tmp_path / benchmark.JOURNAL, BenchmarkConfig())
        journal.append(_row("0-30", 0, "dpcn", 0.5))
        older = {k: v for k, v in _row("0-30", 1, "dpcn", 0.7).items() if k not in benchmark.GLOBAL_FIELDS}
        with open(journal.path, "a") as stream:
            stream.write(json.dumps(older) + "\n")
        rows = journal.rows()
        assert rows[("mni", "0-30", 0, "dpcn")]["rotation_error_deg"] == 1.0
        assert all(math.isnan(rows[("mni", "0-30", 1, "dpcn")][name]) for name in benchmark.GLOBAL_FIELDS)

    def test_other_settings_are_refused_not_mixed_in(self, tmp_path, capsys):
        journal = benchmark.Journal(tmp_path / "b" / benchmark.JOURNAL, BenchmarkConfig(trials=2))
        journal.append(_row("0-30", 1, "dpcn-global", 0.5))
        assert main(["benchmark", "--cases", "mni", "--methods", "dpcn-global", "--trials", "1", "-o",
                     str(tmp_path / "b")]) == 2
        err = capsys.readouterr().err
        assert "results.partial.jsonl: holds an interrupted run with other settings" in err and "'trials': 2" in err
        assert sorted(p.name for p in (tmp_path / "b").iterdir()) == [benchmark.JOURNAL]

    def test_registrations_outside_a_narrower_rerun_are_kept(self, tmp_path, capsys):
        """An interrupted run's registrations that a rerun with fewer methods does not cover stay in the journal, for
        the interrupted run's command to go on from; those it covers are in results.csv."""
        journal = benchmark.Journal(tmp_path / "b" / benchmark.JOURNAL, BenchmarkConfig(trials=1))
        other = {**_row("0-30", 0, "sitk-geometry", 0.5), "peak_mib": 1.0}
        journal.append(other)
        assert main(["benchmark", "--cases", "mni", "--methods", "dpcn-global", "--trials", "1", "--bins", "0-30",
                     "-o", str(tmp_path / "b")]) == 0
        assert "1 registration(s) in" in capsys.readouterr().err
        assert journal.rows()[("mni", "0-30", 0, "sitk-geometry")] == other
        assert [r["method"] for r in benchmark.combine_results([tmp_path / "b"])] == ["dpcn-global"]
        assert main(["benchmark", "--cases", "mni", "--methods", "dpcn-global", "sitk-geometry", "--trials", "1",
                     "--bins", "0-30", "-o", str(tmp_path / "b")]) == 0
        assert not journal.path.exists()  # every registration of it is in results.csv now
        rows = benchmark.combine_results([tmp_path / "b"])
        assert [r["method"] for r in rows] == ["dpcn-global", "sitk-geometry"] and rows[1] == other

    @pytest.mark.parametrize("text", ["", '{"settings": {"version": "0', '{"settings"'])
    def test_a_journal_without_a_whole_first_line_is_empty(self, tmp_path, text):
        """Cut before its settings line ended (or made empty): nothing registered, and the settings are written again
        (it blocked the run with 'other settings (None, ...)', and a row was appended without them)."""
        journal = benchmark.Journal(tmp_path / benchmark.JOURNAL, BenchmarkConfig())
        journal.path.write_text(text)
        assert journal.rows() == {}
        journal.append(_row("0-30", 0, "dpcn", 0.5))
        assert json.loads(journal.path.read_text().splitlines()[0]) == {"settings": journal.settings}
        assert list(journal.rows()) == [("mni", "0-30", 0, "dpcn")]

    def test_a_file_that_is_not_a_journal_is_refused(self, tmp_path):
        journal = benchmark.Journal(tmp_path / benchmark.JOURNAL, BenchmarkConfig())
        journal.path.write_text("case,bin\n")
        with pytest.raises(InputError, match=r"results\.partial\.jsonl: not a journal of dpcn-med benchmark"):
            journal.rows()

    def test_a_line_cut_by_the_interruption_is_dropped(self, tmp_path):
        journal = benchmark.Journal(tmp_path / benchmark.JOURNAL, BenchmarkConfig())
        row = _row("0-30", 0, "sitk-geometry", 0.5, peak=float("nan"))
        journal.append(row)
        journal.append({**row, "trial": 1})
        text = journal.path.read_bytes()
        journal.path.write_bytes(text[:-10])  # the second row, cut
        assert list(journal.rows()) == [("mni", "0-30", 0, "sitk-geometry")]
        journal.append({**row, "trial": 2})
        assert [key[2] for key in journal.rows()] == [0, 2]
        assert math.isnan(journal.rows()[("mni", "0-30", 0, "sitk-geometry")]["peak_mib"])

        journal.path.write_text(journal.path.read_text().replace('"tre_mm": 0.5', '"tre_mm": -0.5', 1))
        with pytest.raises(InputError, match=r"results\.partial\.jsonl: line 2: tre_mm -0\.5; expected a finite"):
            journal.rows()
        journal.path.write_text(journal.path.read_text().replace("-0.5", "0.5").replace('"trial": 2', '"trial": "two"'))
        with pytest.raises(InputError, match=r"line 3: not a registration \(ValueError"):
            journal.rows()

    def test_registrations_in_the_journal_are_not_run_again_but_the_showcase_is(self, tmp_path, monkeypatch):
        config = BenchmarkConfig(cases=("mni",), methods=("dpcn", "sitk-geometry"), bins=((150, 180),), trials=1)
        journal = benchmark.Journal(tmp_path / benchmark.JOURNAL, config)
        for method, tre in (("dpcn", 99.0), ("sitk-geometry", 42.0)):
            journal.append(_row("150-180", 0, method, tre, peak=1.0))
        label, package, _ = benchmark.METHODS["sitk-geometry"]
        monkeypatch.setitem(benchmark.METHODS, "sitk-geometry", (label, package, lambda *a: pytest.fail("ran")))
        showcase: dict = {}
        rows = run_benchmark(config, showcase=showcase, journal=journal)
        assert [r["tre_mm"] for r in rows][1] == 42.0 and rows[0]["tre_mm"] < 2.0  # the showcase, registered again
        assert showcase["bin"] == "150-180" and journal.rows()[("mni", "150-180", 0, "dpcn")]["tre_mm"] < 2.0
