"""Learning-free accuracy of the DPC solver on real anatomy over random poses; prints a table and writes it to docs/.

3-D: each volume on its canonical (2B)^3 cube, warped by random poses (rotation uniform over SO(3), translation up to
20% of the grid, scale 0.8-1.2 in similarity mode) and registered back. 2-D: 256 x 256 axial slices, angle uniform in
[0, 360), scale 0.8-1.2, translation up to 50 px. Success thresholds are the solver issue's.

    python benchmarks/solver_accuracy.py               # 100 poses per row (run time: docs/design_notes/benchmark.md)
    python benchmarks/solver_accuracy.py --poses 10    # a quick look
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import torch

from dpcn_med.preprocess import solver_grid, solver_slice
from dpcn_med.samples import mni152_t1
from dpcn_med.solver import solve, solve2d
from dpcn_med.synth import random_poses

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
VOLUMES = {"seg3d MR": "seg3d/MR.nii.gz", "MRI-DIR T2": "mridir/mridir_t2_1p5mm.nii.gz", "MNI152 T1": None}
# (bandwidth, rotation degrees, translation voxels, relative scale) per the solver issue.
THRESHOLDS = {32: (5.0, 2.0, 0.03), 64: (2.5, 1.0, 0.02)}
THRESHOLDS_2D = (1.0, 1.0, 0.01)


def _image(name: str) -> sitk.Image | None:
    relative = VOLUMES[name]
    if relative is None:
        return mni152_t1()
    path = SHARED / relative
    return sitk.ReadImage(str(path)) if path.exists() else None


def _row(label: str, errors: list[tuple[float, float, float]], seconds: list[float],
         limits: tuple[float, float, float]) -> dict:
    array = np.array(errors)
    success = np.mean((array[:, 0] < limits[0]) & (array[:, 1] < limits[1]) & (array[:, 2] < limits[2]))
    return {"label": label, "poses": len(errors), "limits": limits, "success": 100 * success,
            "median": np.median(array, 0), "p95": np.percentile(array, 95, 0), "worst": array.max(0),
            "time": statistics.median(seconds)}


def run_3d(name: str, image: sitk.Image, bandwidth: int, mode: str, count: int) -> dict:
    size = 2 * bandwidth
    fixed = solver_grid(image, size)[0]
    errors, seconds = [], []
    solve(fixed, fixed)  # warm the Wigner-d cache
    for pose in random_poses(count, size, seed=bandwidth, similarity=mode == "similarity"):
        moving = pose.moving_from(fixed)
        began = time.perf_counter()
        result = solve(fixed, moving, mode)
        seconds.append(time.perf_counter() - began)
        errors.append(pose.errors(result.rotation[0], result.scale[0], result.translation[0]))
    return _row(f"{name}, 3-D, B = {bandwidth}, {mode}", errors, seconds, THRESHOLDS[bandwidth])


def run_2d(name: str, image: sitk.Image, count: int) -> dict:
    fixed = solver_slice(image, 256)
    errors, seconds = [], []
    for pose in random_poses(count, 256, seed=2, dim=2, max_shift=50.0):
        moving = pose.moving_from(fixed)
        began = time.perf_counter()
        result = solve2d(fixed, moving)
        seconds.append(time.perf_counter() - began)
        errors.append(pose.errors(result.rotation[0], result.scale[0], result.translation[0]))
    return _row(f"{name}, 2-D slice 256^2, similarity", errors, seconds, THRESHOLDS_2D)


def table(rows: list[dict]) -> str:
    lines = ["| case | poses | success | criterion (deg / vox / %) | rotation error, median / p95 / max (deg) | "
             "translation error (vox) | scale error (%) | median time (ms) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        rot, trans, scale = (f"{r['median'][i] * k:.2f} / {r['p95'][i] * k:.2f} / {r['worst'][i] * k:.2f}"
                             for i, k in ((0, 1), (1, 1), (2, 100)))
        lines.append(f"| {r['label']} | {r['poses']} | {r['success']:.0f}% | {r['limits'][0]} / {r['limits'][1]} / "
                     f"{r['limits'][2] * 100:.0f} | {rot} | {trans} | {scale} | {r['time'] * 1e3:.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=count_type(), default=100)
    parser.add_argument("--bandwidths", nargs="+", type=int, default=[32, 64], choices=sorted(THRESHOLDS),
                        help="the bandwidths the solver issue sets thresholds for")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "solver_accuracy.md")
    args = parser.parse_args(argv)
    torch.set_grad_enabled(False)
    rows, missing = [], []
    for name in VOLUMES:
        image = _image(name)
        if image is None:
            missing.append(name)
            continue
        for bandwidth in args.bandwidths:
            for mode in ("similarity", "rigid"):
                rows.append(run_3d(name, image, bandwidth, mode, args.poses))
                print(table(rows[-1:]).splitlines()[-1], file=sys.stderr)
        rows.append(run_2d(name, image, args.poses))
        print(table(rows[-1:]).splitlines()[-1], file=sys.stderr)
    note = f"\n\nSkipped (../shared/data absent): {', '.join(missing)}." if missing else ""
    text = (f"# Solver accuracy (learning-free)\n\n{generated_by(__file__, argv)}, torch {torch.__version__}, "
            f"{torch.get_num_threads()} CPU threads, float32. Success: all three errors under the criterion.\n\n"
            + table(rows) + note + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
