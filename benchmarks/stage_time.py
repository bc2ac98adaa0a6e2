"""Seconds of each stage of `dpcn_med.register`, per benchmark pair, for this source tree and others side by side.

The stages are the registration's own timings (``RegistrationResult.timings``: preprocess, solve, refine) and the
whole call, on the full benchmark's pairs (:data:`dpcn_med.benchmark.CASES`) turned by random rotations (uniform
0-180 degrees, shifts up to 60 mm) and registered with the defaults. Whole registrations vary by a fifth from one
minute to the next on a shared machine; a stage's median moves less, which is what a change to one stage needs.

Each (tree, case) runs in a fresh process (an unrecorded first registration, then ``--poses`` timed ones), and the
trees alternate case by case, ``--rounds`` times, so that each sees the same machine. Poses follow from ``--seed`` and
the case: every tree registers the same ones.

    python benchmarks/stage_time.py --compare /tmp/old_clone [--cases seg3d t1-flair] [--poses 6] [--rounds 2]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import (  # noqa: E402  (the scripts' shared helpers)
    count_type,
    generated_by,
    publish,
    source_label,
    source_trees,
    tree_environment,
)

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("preprocess", "solve", "refine", "whole")


def worker(case: str, poses: int, seed: int) -> dict[str, list[float]]:
    """Register ``poses`` poses of ``case`` in this process: each stage's seconds, one value per registration."""
    import numpy as np

    from dpcn_med.benchmark import CASES, rotation_in_bin
    from dpcn_med.evaluation import moved_copy
    from dpcn_med.preprocess import foreground_box
    from dpcn_med.registration import register

    fixed, whole = CASES[case][2]()
    centre = foreground_box(fixed)[0]
    rng = np.random.default_rng([seed, sorted(CASES).index(case)])
    register(fixed, whole)  # unrecorded: the first call's imports and Wigner tables
    seconds: dict[str, list[float]] = {stage: [] for stage in STAGES}
    for _ in range(poses):
        moving = moved_copy(whole, rotation_in_bin(rng, 0, 180, centre, 60.0))
        started = time.perf_counter()
        result = register(fixed, moving)
        seconds["whole"].append(time.perf_counter() - started)
        for stage in STAGES[:-1]:
            seconds[stage].append(result.timings[stage])
    return seconds


def table(runs: dict[tuple[str, str], dict[str, list[float]]], labels: list[str]) -> str:
    """Markdown: one row per (case, tree), each stage's median seconds; the other trees' rows give each stage's
    median over the first tree's (above 1: the first tree is faster)."""
    lines = ["| case | source | registrations | " + " | ".join(f"{stage} (s)" for stage in STAGES) + " |",
             "|---|---|---|" + "---|" * len(STAGES)]
    for case in dict.fromkeys(case for case, _ in runs):
        first = {stage: statistics.median(runs[case, labels[0]][stage]) for stage in STAGES}
        for label in labels:
            seconds = runs[case, label]
            cells = []
            for stage in STAGES:
                median = statistics.median(seconds[stage])
                ratio = "" if label == labels[0] else f" ({median / first[stage]:.2f}x)" if first[stage] > 0 else ""
                cells.append(f"{median:.3f}{ratio}")
            lines.append(f"| {case} | {label} | {len(seconds['whole'])} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from dpcn_med.benchmark import CASES

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    parser.add_argument("--poses", type=count_type(), default=6, help="timed registrations per case, tree and round")
    parser.add_argument("--rounds", type=count_type(), default=2, help="times the trees alternate over the cases")
    parser.add_argument("--seed", type=count_type(minimum=0), default=0, help="of the poses")
    parser.add_argument("--compare", type=Path, nargs="*", default=[], help="other source trees, alternated with this")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "stage_time.md")
    parser.add_argument("--worker", nargs=3, metavar=("CASE", "POSES", "SEED"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker[0], int(args.worker[1]), int(args.worker[2]))))
        return 0
    trees = source_trees(parser, ROOT, args.compare)
    labels = [source_label(tree) for tree in trees]
    runs: dict[tuple[str, str], dict[str, list[float]]] = {}
    for round_ in range(args.rounds):
        for case in args.cases:
            for tree, label in zip(trees, labels, strict=True):
                # the worker's stderr passes through: its errors and warnings are the user's to see
                done = subprocess.run([sys.executable, __file__, "--worker", case, str(args.poses), str(args.seed)],
                                      stdout=subprocess.PIPE, text=True, env=tree_environment(tree), cwd=tree,
                                      check=False)
                if done.returncode != 0:
                    print(f"stage_time.py: {label} on {case} failed with exit code {done.returncode} (its error is "
                          "above); nothing written", file=sys.stderr)
                    return 1
                seconds = json.loads(done.stdout.strip().splitlines()[-1])
                merged = runs.setdefault((case, label), {stage: [] for stage in STAGES})
                for stage in STAGES:
                    merged[stage] += seconds[stage]
                print(f"round {round_ + 1}: {label} {case}: {statistics.median(seconds['whole']):.2f} s",
                      file=sys.stderr)
    text = (f"# Stage times of a registration\n\n{generated_by(__file__, argv)}, {os.cpu_count()} CPU cores: "
            "`dpcn_med.register` with its defaults on the full benchmark's pairs, each turned by a random rotation "
            "(0-180 degrees) and shift (up to 60 mm), the same poses for every source tree; a fresh process per tree "
            "and case, the trees alternated case by case. Medians in seconds of the registration's own stage "
            "timings and of the whole call; in brackets, a tree's median over the first tree's.\n\n"
            + table(runs, labels) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
