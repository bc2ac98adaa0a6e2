"""Speed and peak memory of the DPC solver, per stage and end to end; prints a table and writes it under docs/.

Each (device, bandwidth) runs in a fresh subprocess so that its peak memory is its own (CPU: the resident-set
high-water mark above the loaded inputs, Linux; CUDA: ``max_memory_allocated``, the Wigner-d table included).
Per-stage times come from ``solve(..., profile=True)`` (CUDA synchronised at stage boundaries); end-to-end times from
plain calls (CUDA events on the GPU). The baseline, measured in the same process, is a translation-only
registration: one 3-D phase correlation of the same two grids.

    python benchmarks/solver_speed.py                       # CPU B = 32, 64; CUDA B = 64, 128 if present
    python benchmarks/solver_speed.py --devices cuda --bandwidths 64 128 --repeats 20
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_BANDWIDTHS = {"cpu": [32, 64], "cuda": [64, 128]}


def _elapsed(function, device: torch.device) -> float:
    """Seconds for one call, with CUDA events on the GPU."""
    if device.type == "cuda":
        # On the device's own stream: record() alone takes the current device's, cuda:0's idle one for cuda:1.
        stream = torch.cuda.current_stream(device)
        start, stop = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record(stream)
        function()
        stop.record(stream)
        torch.cuda.synchronize(device)
        return start.elapsed_time(stop) / 1000.0
    began = time.perf_counter()
    function()
    return time.perf_counter() - began


def worker(device_name: str, bandwidth: int, repeats: int) -> dict:
    """Measure one configuration in this process and return the numbers."""
    from dpcn_med.benchmark import reset_peak_rss, status_mib
    from dpcn_med.preprocess import solver_grid
    from dpcn_med.samples import mni152_t1
    from dpcn_med.solver import solve
    from dpcn_med.solver.phase_correlation import phase_correlation
    from dpcn_med.synth import random_poses

    device = torch.device(device_name)
    size = 2 * bandwidth
    fixed = solver_grid(mni152_t1(), size)[0].to(device)
    moving = random_poses(1, size, seed=0)[0].moving_from(fixed)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
    baseline_rss = reset_peak_rss()

    cold = _elapsed(lambda: solve(fixed, moving), device)  # builds and caches the Wigner-d table
    for _ in range(2):
        solve(fixed, moving)
    stages: dict[str, list[float]] = {}
    for _ in range(repeats):
        for stage, seconds in solve(fixed, moving, profile=True).timings.items():
            stages.setdefault(stage, []).append(seconds)
    total = [_elapsed(lambda: solve(fixed, moving), device) for _ in range(repeats)]
    translation_only = [_elapsed(lambda: phase_correlation(fixed[:, 0], moving[:, 0], 3), device)
                        for _ in range(repeats)]
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device) / 2 ** 20
        peak_kind = "CUDA allocated"
    else:
        peak = status_mib("VmHWM") - baseline_rss
        peak_kind = "peak RSS above the inputs"
    return {
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else
        f"CPU ({torch.get_num_threads()} threads, {platform.processor() or platform.machine()})",
        "bandwidth": bandwidth, "size": size, "repeats": repeats, "cold": cold,
        "stages": {name: statistics.median(values) for name, values in stages.items()},
        "median": statistics.median(total), "min": min(total), "max": max(total),
        "baseline": statistics.median(translation_only), "peak_mib": peak, "peak_kind": peak_kind,
    }


def _device(text: str) -> str:
    """An argparse type: a torch device (``cpu``, ``cuda``, ``cuda:1``)."""
    try:
        return str(torch.device(text))
    except RuntimeError as error:
        raise argparse.ArgumentTypeError(f"{text!r} is not a torch device ({error})") from None


def table(rows: list[dict]) -> str:
    """Markdown tables: end to end, then per stage."""
    lines = ["| device | B | grid | median (ms) | min | max | first call (ms) | translation-only PC (ms) | ratio | "
             "peak memory (MiB) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['device']} | {r['bandwidth']} | {r['size']}^3 | {r['median'] * 1e3:.1f} | "
                     f"{r['min'] * 1e3:.1f} | {r['max'] * 1e3:.1f} | {r['cold'] * 1e3:.0f} | "
                     f"{r['baseline'] * 1e3:.2f} | {r['median'] / r['baseline']:.1f}x | "
                     f"{r['peak_mib']:.0f} ({r['peak_kind']}) |")
    stages = list(rows[0]["stages"]) if rows else []
    lines += ["", "Per stage, median ms (profiled run; stage boundaries synchronised):", "",
              "| device | B | " + " | ".join(stages) + " |", "|---|---|" + "---|" * len(stages)]
    for r in rows:
        lines.append(f"| {r['device']} | {r['bandwidth']} | " + " | ".join(
            f"{r['stages'].get(s, float('nan')) * 1e3:.1f}" for s in stages) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", nargs="+", type=_device,
                        default=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    parser.add_argument("--bandwidths", nargs="+", type=int, help="default: 32 64 on CPU, 64 128 on CUDA")
    parser.add_argument("--repeats", type=count_type(), default=10)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "solver_speed.md")
    parser.add_argument("--worker", nargs=3, metavar=("DEVICE", "B", "REPEATS"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker[0], int(args.worker[1]), int(args.worker[2]))))
        return 0
    rows = []
    for device in args.devices:
        for bandwidth in args.bandwidths or DEFAULT_BANDWIDTHS[torch.device(device).type]:
            # the worker's stderr passes through: its errors and warnings are the user's to see
            worker_run = subprocess.run([sys.executable, __file__, "--worker", device, str(bandwidth),
                                         str(args.repeats)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
            if worker_run.returncode != 0:
                print(f"solver_speed.py: the worker for {device} B={bandwidth} failed with exit code "
                      f"{worker_run.returncode} (its error is above); nothing written", file=sys.stderr)
                return 1
            rows.append(json.loads(worker_run.stdout.strip().splitlines()[-1]))
            print(f"measured {device} B={bandwidth}", file=sys.stderr)
    text = (f"# Solver speed\n\n{generated_by(__file__, argv)}, torch {torch.__version__}; MNI152 T1 on the canonical "
            f"grid, one random similarity pose, batch 1, float32, {args.repeats} repeats.\n\n" + table(rows) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
