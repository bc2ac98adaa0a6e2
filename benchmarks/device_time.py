"""The whole registration on the CPU and on a CUDA GPU, side by side: seconds per stage, accuracy, and how far the
two devices' results lie apart.

`dpcn_med.register` with its defaults, once with ``device="cpu"`` and once with ``device="cuda"`` on each pose (the
same poses as `dpcn-med benchmark`: rotation uniform in 100-180 degrees about a uniform axis, shift up to 60 mm), in
one process, after one unrecorded registration on each device (CUDA's start-up, cuFFT's plans). Success is a TRE under
2 mm over the fixed foreground's box. Without a GPU only the CPU rows are made.

    python benchmarks/device_time.py [--poses 5] [--cases seg3d seg3d-pseudo-ct]
        [--output docs/benchmarks/device_time.md]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)

from dpcn_med.benchmark import CASES, SUCCESS_MM, rotation_in_bin
from dpcn_med.evaluation import foreground_corners, moved_copy, target_registration_error
from dpcn_med.preprocess import foreground_box
from dpcn_med.registration import register

ROOT = Path(__file__).resolve().parents[1]


def _machine() -> str:
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no CUDA GPU"
    return f"{platform.machine()}, {torch.get_num_threads()} CPU threads, {gpu}, torch {torch.__version__}"


def run_case(case: str, poses: int, devices: list[str]) -> list[dict]:
    """One row per device: medians over ``poses`` registrations, and the devices' disagreement."""
    fixed, whole = CASES[case][2]()
    corners, centre = foreground_corners(fixed), foreground_box(fixed)[0]
    rng = np.random.default_rng(20261204)
    for device in devices:  # unrecorded: CUDA's context, cuFFT's plans, the allocator's first blocks
        register(fixed, moved_copy(whole, rotation_in_bin(rng, 100, 180, centre, 60.0)), device=device)
    runs: dict[str, list[dict]] = {device: [] for device in devices}
    for _ in range(poses):
        truth = rotation_in_bin(rng, 100, 180, centre, 60.0)
        moving = moved_copy(whole, truth)
        for device in devices:
            started = time.perf_counter()
            result = register(fixed, moving, device=device)
            if device != "cpu":
                torch.cuda.synchronize()
            runs[device].append({"seconds": time.perf_counter() - started, "result": result,
                                 "tre": target_registration_error(result.fixed_to_moving, truth, corners)})
    rows = []
    for device, done in runs.items():
        apart = [target_registration_error(run["result"].fixed_to_moving, cpu["result"].fixed_to_moving, corners)
                 for run, cpu in zip(done, runs["cpu"], strict=True)]
        same = sum(run["result"].candidate == cpu["result"].candidate for run, cpu in zip(done, runs["cpu"]))
        rows.append({
            "case": CASES[case][0], "device": device, "poses": len(done),
            "seconds": statistics.median(run["seconds"] for run in done),
            **{stage: statistics.median(run["result"].timings.get(stage, 0.0) for run in done)
               for stage in ("preprocess", "solve", "refine")},
            "success": sum(run["tre"] < SUCCESS_MM for run in done),
            "tre": statistics.median(run["tre"] for run in done),
            "apart": max(apart), "same": same})
    return rows


def table(rows: list[dict]) -> str:
    lines = [("| pair | device | poses | median s | preprocess | solve | refine | success | median TRE (mm) | "
              "farthest from the CPU's pose (mm) | same start as the CPU |"), "|" + "---|" * 11]
    for row in rows:
        lines.append(f"| {row['case']} | {row['device']} | {row['poses']} | {row['seconds']:.2f} | "
                     f"{row['preprocess']:.2f} | {row['solve']:.2f} | {row['refine']:.2f} | "
                     f"{row['success']} of {row['poses']} | {row['tre']:.2f} | {row['apart']:.3f} | "
                     f"{row['same']} of {row['poses']} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=count_type(), default=5, help="poses per pair")
    parser.add_argument("--cases", nargs="+", choices=sorted(CASES), default=["seg3d", "seg3d-pseudo-ct"])
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "device_time.md")
    args = parser.parse_args(argv)
    devices = ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]
    rows = [row for case in args.cases for row in run_case(case, args.poses, devices)]
    text = (f"# The registration on the CPU and on a GPU\n\n{generated_by(__file__, argv)}, on {_machine()}: "
            "`dpcn_med.register` with its defaults on each device in turn, the same poses (100-180 degrees, shift up "
            "to 60 mm), one process, after an unrecorded registration on each; medians in seconds, stages from the "
            f"result's timings; success is a TRE under {SUCCESS_MM:g} mm.\n\n{table(rows)}\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
