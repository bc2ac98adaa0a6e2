"""What the refinement's starts cost: `dpcn_med.register` with the defaults against the defaults without the stored
pose as a start, and against the settings before the partial-field-of-view change (second sphere band 0.2-0.6 of
Nyquist, eight refinement starts, no stored-pose start), side by side.

The quick mode's pairs and poses of `dpcn-med benchmark` (MNI T1 to itself and to its pseudo-CT, one pose per 30-degree
bin); the settings register every pose in turn, ``--repeats`` times; medians of the wall-clock time, success (TRE
under 2 mm) and the number of starts offered to the refinement (those without overlap are dropped at once).

    python benchmarks/candidate_cost.py                 # run time: docs/design_notes/benchmark.md
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from dpcn_med.benchmark import CASES, QUICK, SUCCESS_MM, rotation_in_bin
from dpcn_med.evaluation import foreground_corners, moved_copy, target_registration_error
from dpcn_med.preprocess import foreground_box
from dpcn_med.refine import Refinement
from dpcn_med.registration import register
from dpcn_med.solver import SolverConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = {
    "defaults (second band 0.3-0.9, up to 16 candidates and the stored pose)": {},
    "without the stored pose": {"refinement": Refinement(stored_start=False)},
    "before (second band 0.2-0.6, 8 candidates)": {"solver": SolverConfig(extra_sphere_bands=((0.2, 0.6),)),
                                                   "refinement": Refinement(starts=8, stored_start=False)},
}


def measure(case: str, repeats: int) -> list[dict]:
    """One row per setting: median seconds, successes and the range of starts offered over the case's poses."""
    fixed, moving_whole = CASES[case][2]()
    corners, centre = foreground_corners(fixed), foreground_box(fixed)[0]
    rng = np.random.default_rng([QUICK.seed, list(CASES).index(case)])  # the benchmark's own poses
    poses = [rotation_in_bin(rng, low, high, centre, QUICK.max_shift_mm) for low, high in QUICK.bins]
    seconds = {name: [] for name in SETTINGS}
    results = {name: [] for name in SETTINGS}
    for repeat in range(repeats):
        for truth in poses:
            moving = moved_copy(moving_whole, truth)
            for name, options in SETTINGS.items():  # interleaved, so that the machine's load hits all alike
                started = time.perf_counter()
                result = register(fixed, moving, **options)
                seconds[name].append(time.perf_counter() - started)
                if repeat == 0:
                    error = target_registration_error(result.fixed_to_moving, truth, corners)
                    results[name].append((error < SUCCESS_MM, len(result.candidate_metrics)))
    return [{"case": case, "setting": name, "seconds": statistics.median(seconds[name]),
             "success": sum(ok for ok, _ in results[name]), "poses": len(poses),
             "candidates": (min(n for _, n in results[name]), max(n for _, n in results[name]))}
            for name in SETTINGS]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])  # its first line ends mid-sentence
    parser.add_argument("--cases", nargs="+", default=list(QUICK.cases), choices=list(CASES))
    parser.add_argument("--repeats", type=count_type(), default=3)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "candidate_cost.md")
    args = parser.parse_args(argv)
    rows = [row for case in args.cases for row in measure(case, args.repeats)]
    lines = ["| pair | settings | median s a registration | success | starts |", "|---|---|---|---|---|"]
    lines += [f"| {CASES[r['case']][0]} | {r['setting']} | {r['seconds']:.2f} | {r['success']} of {r['poses']} | "
              f"{r['candidates'][0]}-{r['candidates'][1]} |" for r in rows]
    text = (f"# The cost of the refinement's starts\n\n{generated_by(__file__, argv)}: `dpcn_med.register` on the "
            f"quick benchmark's poses, the settings in turn, {args.repeats} repeats, one CPU process.\n\n"
            + "\n".join(lines) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
