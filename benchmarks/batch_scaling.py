"""Throughput of `dpcn-med register-batch`: one process after another, and on a local Dask cluster of 1 or 2 workers.

A cohort of ``--pairs`` pairs (the 2 mm MNI152 head and copies of it moved by random similarities over SO(3), shifts up
to 30 mm, seed 0) is written once; then each back-end registers the whole cohort into a fresh folder, in a fresh
process (start-up and, for Dask, the cluster's start included), with the command's defaults less the overview and the
resampled volume. Back-ends alternate run by run, so that all see the same machine. The table gives the median wall
time of a batch, pairs per minute, and the ratio to the sequential run measured beside it.

    python benchmarks/batch_scaling.py [--pairs 8] [--repeats 3] [--output docs/benchmarks/batch_scaling.md]
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)

ROOT = Path(__file__).resolve().parents[1]
BACKENDS = {  # name: extra options of `dpcn-med register-batch`
    "sequential": [],
    "dask, 1 worker": ["--workers", "1"],
    "dask, 2 workers": ["--workers", "2"],
}


def write_cohort(folder: Path, pairs: int) -> Path:
    """``pairs`` moved copies of the 2 mm MNI head and their pairs file, in ``folder``."""
    from dpcn_med.evaluation import moved_copy, random_similarity
    from dpcn_med.preprocess import foreground_box
    from dpcn_med.samples import mni152_t1

    fixed = sitk.BinShrink(mni152_t1(), [2, 2, 2])
    sitk.WriteImage(fixed, str(folder / "fixed.nii.gz"))
    rng = np.random.default_rng(0)
    lines = ["id,fixed,moving"]
    for index in range(pairs):
        truth = random_similarity(rng, foreground_box(fixed)[0], max_shift_mm=30.0)
        sitk.WriteImage(moved_copy(fixed, truth), str(folder / f"moving{index}.nii.gz"))
        lines.append(f"p{index},fixed.nii.gz,moving{index}.nii.gz")
    (folder / "pairs.csv").write_text("\n".join(lines) + "\n")
    return folder / "pairs.csv"


def run_batch(pairs_file: Path, extra: list[str], output: Path) -> tuple[float, int, list[float]]:
    """One batch in a fresh process: its wall time (s), how many pairs it registered ``ok``, and each pair's own
    registration time (s, summary.csv's ``seconds``: reading, registering and writing, without start-up)."""
    command = [sys.executable, "-m", "dpcn_med", "register-batch", str(pairs_file), "-o", str(output), "-q",
               "--no-overview", "--no-resampled", *extra]
    started = time.perf_counter()
    code = subprocess.run(command).returncode
    wall = time.perf_counter() - started
    if code not in (0, 3):
        raise SystemExit(f"{' '.join(command)} exited {code}")
    with (output / "summary.csv").open() as table:
        rows = list(csv.DictReader(table))
    return wall, sum(row["status"] == "ok" for row in rows), [float(row["seconds"]) for row in rows]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=count_type(), default=8)
    parser.add_argument("--repeats", type=count_type(), default=3)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "batch_scaling.md")
    args = parser.parse_args(argv)

    folder = Path(tempfile.mkdtemp(prefix="batch-scaling-"))
    try:
        pairs_file = write_cohort(folder, args.pairs)
        walls: dict[str, list[float]] = {name: [] for name in BACKENDS}
        registered: dict[str, set[int]] = {name: set() for name in BACKENDS}
        pair_seconds: dict[str, list[float]] = {name: [] for name in BACKENDS}
        for repeat in range(args.repeats):
            for index, (name, extra) in enumerate(BACKENDS.items()):
                wall, ok, seconds = run_batch(pairs_file, extra, folder / f"out-{repeat}-{index}")
                walls[name].append(wall)
                pair_seconds[name] += seconds
                registered[name].add(ok)
                print(f"repeat {repeat + 1}/{args.repeats} {name}: {wall:.1f} s, {ok} ok", file=sys.stderr)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    baseline = statistics.median(walls["sequential"])
    lines = ["# register-batch throughput", "",
             f"{generated_by(__file__, argv)}. {args.pairs} pairs of the 2 mm MNI152 head (any rotation, shifts up to "
             "30 mm), `dpcn-med register-batch -q --no-overview --no-resampled`, a fresh process per batch (start-up "
             f"and cluster start included), median of {args.repeats} alternating runs on {os.cpu_count()} CPU cores.",
             "",
             "| back-end | wall s (median) | min | max | pairs / min | speed-up vs sequential | s per pair, "
             "registration alone (median) | pairs ok |",
             "|---|---|---|---|---|---|---|---|"]
    for name in BACKENDS:
        median = statistics.median(walls[name])
        ok = "/".join(str(count) for count in sorted(registered[name]))
        lines.append(f"| {name} | {median:.1f} | {min(walls[name]):.1f} | {max(walls[name]):.1f} | "
                     f"{60 * args.pairs / median:.1f} | {baseline / median:.2f}x | "
                     f"{statistics.median(pair_seconds[name]):.2f} | {ok} of {args.pairs} |")
    return publish("\n".join(lines) + "\n", args.output)


if __name__ == "__main__":
    sys.exit(main())
