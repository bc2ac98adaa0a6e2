"""dpcn_med.benchmark: poses by rotation bin, every tool's transform read the right way round, the outputs."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from dpcn_med import benchmark
from dpcn_med.benchmark import BenchmarkConfig, rotation_in_bin, run_benchmark, write_outputs
from dpcn_med.cli import main
from dpcn_med.errors import InputError
from dpcn_med.evaluation import foreground_corners, moved_copy, target_registration_error
from dpcn_med.geometry import homogeneous_matrix
from dpcn_med.preprocess import foreground_box
from tests.test_register import mni_2mm


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
        with open(tmp_path / "out" / "results.csv", newline="") as handle:
            assert len(list(csv.DictReader(handle))) == 4
        assert "| dpcn_med learning-free, global estimate only | 100% | 100% |" in text

    def test_unknown_names_are_refused(self):
        with pytest.raises(InputError, match="unknown case brain; use one of mni"):
            run_benchmark(BenchmarkConfig(cases=("brain",), methods=("dpcn",)))
        with pytest.raises(InputError, match="unknown method flirt; use one of dpcn"):
            run_benchmark(BenchmarkConfig(cases=("mni",), methods=("flirt",)))

    def test_cli(self, tmp_path, capsys):
        code = main(["benchmark", "--cases", "mni", "--methods", "dpcn-global", "--trials", "1", "-o",
                     str(tmp_path / "b")])
        assert code == 0
        assert "# dpcn_med against SimpleITK, ANTs and elastix" in capsys.readouterr().out
        assert (tmp_path / "b" / "success.png").is_file()
