"""dpcn_med against SimpleITK's exhaustive search, the seg3d 1 mm head: the seconds of a whole registration.

Both methods register the seg3d head T1 (1 x 0.9 x 0.9 mm) onto a copy of itself turned by 100-180 degrees about a
uniform axis and shifted up to 60 mm, the same poses, one after the other in one process: `dpcn_med.register` with
its defaults, and SimpleITK's exhaustive search over Euler angles in 22.5-degree steps (Mattes MI, 4x shrunk) followed
by the same local Mattes optimiser (:func:`dpcn_med.benchmark.methods.exhaustive_search`). Success is a TRE under 2 mm
over the fixed foreground's box. The ratio is of the medians.

    python benchmarks/exhaustive_speed.py [--poses 5] [--step 22.5] [--output docs/benchmarks/exhaustive_speed.md]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)

from dpcn_med.benchmark import CASES, SUCCESS_MM, rotation_in_bin
from dpcn_med.benchmark.methods import exhaustive_search
from dpcn_med.evaluation import foreground_corners, moved_copy, target_registration_error
from dpcn_med.preprocess import foreground_box
from dpcn_med.registration import register

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=count_type(), default=5)
    parser.add_argument("--step", type=float, default=22.5, choices=[90.0, 45.0, 30.0, 22.5, 15.0],
                        help="the exhaustive search's step, degrees")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "exhaustive_speed.md")
    args = parser.parse_args(argv)
    fixed, whole = CASES["seg3d"][2]()
    corners, centre = foreground_corners(fixed), foreground_box(fixed)[0]
    rng = np.random.default_rng(20261204)
    methods = {"dpcn_med register (defaults)": lambda moving: register(fixed, moving).fixed_to_moving,
               f"SimpleITK exhaustive {args.step:g}-degree search + Mattes MI":
                   lambda moving: exhaustive_search(fixed, moving, args.step)}
    runs: dict[str, list[tuple[float, float]]] = {name: [] for name in methods}
    register(fixed, whole)  # unrecorded: the first call's imports and Wigner tables
    for pose in range(args.poses):
        truth = rotation_in_bin(rng, 100, 180, centre, 60.0)
        moving = moved_copy(whole, truth)
        for name, method in methods.items():
            started = time.perf_counter()
            estimate = method(moving)
            seconds = time.perf_counter() - started
            error = target_registration_error(estimate, truth, corners)
            runs[name].append((seconds, error))
            print(f"pose {pose + 1}: {name}: {seconds:.2f} s, {error:.2f} mm", file=sys.stderr)
    medians = {name: statistics.median(seconds for seconds, _ in done) for name, done in runs.items()}
    fastest = medians[next(iter(methods))]
    lines = ["| method | poses | median s | slower than dpcn_med | success | median TRE (mm) |",
             "|---|---|---|---|---|---|"]
    for name, done in runs.items():
        lines.append(f"| {name} | {len(done)} | {medians[name]:.2f} | {medians[name] / fastest:.1f}x | "
                     f"{sum(error < SUCCESS_MM for _, error in done)} of {len(done)} | "
                     f"{statistics.median(error for _, error in done):.2f} |")
    text = (f"# dpcn_med against SimpleITK's exhaustive search: the seg3d 1 mm head\n\n{generated_by(__file__, argv)}, "
            "one process on this machine's CPU: the seg3d head T1 onto itself turned by 100-180 degrees and shifted "
            f"up to 60 mm, both methods on the same poses in turn; success is a TRE under {SUCCESS_MM:g} mm.\n\n"
            + "\n".join(lines) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
