"""register-batch on Dask: the same transforms as a sequential run, retries after a worker dies, resumable."""

from __future__ import annotations

import csv
import os
import signal
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import SimpleITK as sitk

from dpcn_med.batch import plan_batch, run_batch
from dpcn_med.cli import main
from dpcn_med.evaluation import foreground_corners, moved_copy, random_similarity, target_registration_error
from dpcn_med.outputs import RegistrationSettings
from dpcn_med.preprocess import foreground_box
from tests.test_registration import mni_2mm

distributed = pytest.importorskip("distributed", reason="Dask is the optional extra dpcn_med[cluster]")

SETTINGS = RegistrationSettings(resampled=False, overview=False)
FLAGS = ["--no-overview", "--no-resampled", "-q"]


@pytest.fixture(scope="module")
def cohort(tmp_path_factory) -> tuple[Path, list[sitk.Transform], np.ndarray]:
    """Four pairs of the 2 mm MNI head and a copy of it moved by a known large similarity, with their pairs file."""
    folder = tmp_path_factory.mktemp("cohort")
    fixed = mni_2mm()
    sitk.WriteImage(fixed, str(folder / "fixed.nii.gz"))
    rng = np.random.default_rng(5)
    truths, lines = [], ["id,fixed,moving"]
    for index in range(4):
        truth = random_similarity(rng, foreground_box(fixed)[0], max_shift_mm=30.0)
        sitk.WriteImage(moved_copy(fixed, truth), str(folder / f"moving{index}.nii.gz"))
        truths.append(truth)
        lines.append(f"p{index},fixed.nii.gz,moving{index}.nii.gz")
    (folder / "pairs.csv").write_text("\n".join(lines) + "\n")
    return folder / "pairs.csv", truths, foreground_corners(fixed)


@pytest.fixture(scope="module")
def sequential(cohort, tmp_path_factory) -> Path:
    """The cohort registered one pair after another, with a worker's solver threads (threads reorder sums: with
    torch's and SimpleITK's defaults here, the transforms differ from a worker's by about 5e-6 mm)."""
    import torch

    from dpcn_med.cluster import WORKER_THREADS

    output = tmp_path_factory.mktemp("sequential") / "out"
    threads = torch.get_num_threads(), sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    torch.set_num_threads(WORKER_THREADS)
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(WORKER_THREADS)
    try:
        assert main(["register-batch", str(cohort[0]), "-o", str(output), *FLAGS]) == 0
    finally:
        torch.set_num_threads(threads[0])
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(threads[1])
    return output


def _statuses(output: Path) -> dict[str, str]:
    with (output / "summary.csv").open() as table:
        return {row["id"]: row["status"] for row in csv.DictReader(table)}


def _largest_difference_mm(first: Path, second: Path, points: np.ndarray) -> float:
    return max(target_registration_error(sitk.ReadTransform(str(first / f"p{i}" / "transform.tfm")),
                                         sitk.ReadTransform(str(second / f"p{i}" / "transform.tfm")), points)
               for i in range(4))


class TestLocalCluster:
    def test_two_workers_give_the_sequential_transforms(self, cohort, sequential, tmp_path, capsys):
        pairs, truths, corners = cohort
        output = tmp_path / "dask"
        assert main(["register-batch", str(pairs), "-o", str(output), "--workers", "2", *FLAGS]) == 0
        assert _statuses(output) == {f"p{i}": "ok" for i in range(4)}
        assert _largest_difference_mm(sequential, output, corners) == 0.0
        for index, truth in enumerate(truths):  # and both registered
            estimate = sitk.ReadTransform(str(output / f"p{index}" / "transform.tfm"))
            assert target_registration_error(estimate, truth, corners) < 2.0

    def test_a_worker_killed_mid_batch_has_its_pair_retried(self, cohort, sequential, tmp_path):
        pairs, _, corners = cohort
        batch = plan_batch(pairs, tmp_path / "out", settings=SETTINGS)
        killed = []

        def kill_a_busy_worker(job, row, error) -> None:
            if killed:
                return
            client = distributed.default_client()
            for _ in range(100):  # the scheduler may not have handed out the next pair yet
                busy = {address: keys for address, keys in client.processing().items() if keys}
                if busy:
                    break
                time.sleep(0.05)
            address, keys = next(iter(busy.items()))
            os.kill(client.run(os.getpid, workers=[address])[address], signal.SIGKILL)
            killed.append(keys)

        rows = run_batch(batch, on_row=kill_a_busy_worker, workers=2)
        assert killed and killed[0]  # a pair was running on the worker when it died
        assert [row["status"] for row in rows] == ["ok"] * 4
        assert _largest_difference_mm(sequential, tmp_path / "out", corners) == 0.0

    def test_an_interrupted_batch_registers_no_pair_twice(self, cohort, tmp_path):
        pairs, _, _ = cohort
        output = tmp_path / "out"
        finished = []

        def interrupt_after_one(job, row, error) -> None:  # the next pair running then, the other two waiting
            finished.append(job.id)
            raise KeyboardInterrupt

        # One worker: with two, the first two pairs finish about together, both workers take the last two at once,
        # and on a loaded machine both could finish before the cancel reaches them (seen on CI: all four written).
        with pytest.raises(KeyboardInterrupt):
            run_batch(plan_batch(pairs, output, settings=SETTINGS), on_row=interrupt_after_one, workers=1)
        assert set(_statuses(output)) == set(finished)
        # A pair that a worker was finishing as the client stopped may be written too; either way, once.
        done = {f"p{i}" for i in range(4) if (output / f"p{i}" / "report.json").exists()}
        assert set(finished) <= done and len(done) < 4
        stamps = {pair: (output / pair / "report.json").stat().st_mtime_ns for pair in done}
        again = []
        rows = run_batch(plan_batch(pairs, output, settings=SETTINGS), workers=2,
                         on_row=lambda job, row, error: again.append((job.id, row["status"])))
        assert sorted(again) == [(f"p{i}", "done earlier" if f"p{i}" in done else "ok") for i in range(4)]
        assert [row["id"] for row in rows] == [f"p{i}" for i in range(4)]
        assert {pair: (output / pair / "report.json").stat().st_mtime_ns for pair in done} == stamps
        assert not list(output.glob("*/.dpcn-med-*"))  # staging of the pairs cut short is gone


class TestWorkerChecks:
    def test_a_model_that_differs_on_a_worker_is_refused(self, cohort, tmp_path):
        import torch

        from dpcn_med.cluster import register_on_worker
        from dpcn_med.models import DPCN, ModelConfig, save_model
        from dpcn_med.outputs import model_identity

        torch.manual_seed(0)
        save_model(DPCN(ModelConfig(bandwidth=8, channels=(4, 8, 16), residual_units=0)), tmp_path / "model")
        settings = RegistrationSettings(model=str(tmp_path / "model"), bandwidth=8, resampled=False, overview=False)
        job = plan_batch(cohort[0], tmp_path / "out", settings=settings).jobs[0]
        client_model = {**model_identity(settings.model), "weights_sha256": "0" * 64}
        threads = torch.get_num_threads(), sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
        row = register_on_worker(job, settings, client_model)
        assert (torch.get_num_threads(), sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()) == threads
        assert row["status"] == "bad input" and "is not the client's" in row["message"]
        assert "give every worker the same model files" in row["message"]
        assert not (tmp_path / "out").exists()


class TestFailedPairs:
    class _Failed:
        """A future whose task failed on the cluster with ``error``."""

        def __init__(self, error: Exception) -> None:
            self.error = error

        def result(self):
            raise self.error

    def test_a_pair_whose_worker_died_twice_is_an_internal_error(self, cohort, tmp_path):
        from dpcn_med.cluster import ATTEMPTS, _row_of

        job = plan_batch(cohort[0], tmp_path / "out", settings=SETTINGS).jobs[2]
        died = distributed.KilledWorker("dpcn-med-x-3", SimpleNamespace(address="tcp://127.0.0.1:1"), ATTEMPTS - 1)
        row, error = _row_of(self._Failed(died), job)
        assert error is died and row["id"] == "p2" and row["status"] == "internal error"
        assert row["message"].startswith(f"KilledWorker: Attempted to run task 'dpcn-med-x-3' on {ATTEMPTS} different")

    def test_a_pair_that_raised_twice_is_an_internal_error(self, cohort, tmp_path):
        from dpcn_med.cluster import _row_of

        job = plan_batch(cohort[0], tmp_path / "out", settings=SETTINGS).jobs[0]
        row, _ = _row_of(self._Failed(RuntimeError("ITK ran out of memory")), job)
        assert (row["status"], row["message"]) == ("internal error", "RuntimeError: ITK ran out of memory")


class TestWithoutDask:
    @pytest.mark.parametrize("flag", [["--workers", "2"], ["--scheduler", "tcp://127.0.0.1:1"]])
    def test_refused_with_the_install_line(self, flag, cohort, tmp_path, monkeypatch, capsys):
        monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed raises ImportError
        assert main(["register-batch", str(cohort[0]), "-o", str(tmp_path / "o"), *flag]) == 2
        assert "pip install 'dpcn_med[cluster]'" in capsys.readouterr().err
        assert not (tmp_path / "o").exists()

    def test_an_unreachable_scheduler_is_named(self, cohort, tmp_path, capsys, monkeypatch):
        monkeypatch.setattr("dpcn_med.cluster.CONNECT_TIMEOUT_S", 2)
        assert main(["register-batch", str(cohort[0]), "-o", str(tmp_path / "o"), "--scheduler",
                     "tcp://127.0.0.1:9"]) == 2
        assert "--scheduler tcp://127.0.0.1:9: cannot reach a Dask scheduler there" in capsys.readouterr().err

    def test_workers_and_scheduler_exclude_each_other(self, cohort, tmp_path, capsys):
        with pytest.raises(SystemExit):
            main(["register-batch", str(cohort[0]), "-o", str(tmp_path / "o"), "--workers", "2", "--scheduler", "x"])
        assert "not allowed with argument" in capsys.readouterr().err
