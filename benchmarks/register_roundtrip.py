"""Round trips through the registration API on real volumes: known physical transforms, target registration error.

For each volume of ../shared/data, ``--trials`` random similarity transforms (rotation uniform over SO(3), shift up to
40 mm, scale 0.85-1.15 in similarity mode) move an exact copy of the volume (:func:`dpcn_med.evaluation.moved_copy`);
``dpcn_med.register`` recovers them from scratch. Target registration error (TRE): mean over the 8 corners of the
fixed foreground box. Criteria of the command-line issue: TRE below 2 canonical-grid voxels before refinement (the
phase-correlation candidate the refinement started from; the solver's own choice where the stored pose won), below
1 mm after, in at least 95% of trials. A multimodal row registers the seg3d MR to a pseudo-CT made from it and its
masks (:func:`dpcn_med.synth.pseudo_ct`), learning-free.

Usage: python benchmarks/register_roundtrip.py [--trials 40] [--modes rigid similarity] [--output docs/benchmarks]
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

from dpcn_med.evaluation import foreground_corners, moved_copy, random_similarity, target_registration_error
from dpcn_med.preprocess import foreground_box
from dpcn_med.registration import register

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
VOLUMES = {  # key: (table label, file under shared/data)
    "seg3d": ("seg3d MR (T1, 1 x 0.9 x 0.9 mm)", "seg3d/MR.nii.gz"),
    "ct": ("MRI-DIR CT (1 mm)", "mridir/mridir_ct_1p0mm.nii.gz"),
    "t2": ("MRI-DIR T2 (1 mm)", "mridir/mridir_t2_1p0mm.nii.gz"),
    "rire": ("RIRE 001 MR T1 (1.25 x 1.25 x 4 mm)", "rire/training_001_mr_T1.mha"),
}
MULTIMODAL = "pseudo-ct"
CASES = [*VOLUMES, MULTIMODAL]
"""Every case, in the table's order; a case's poses follow from its place here, whichever cases a run picks."""


def _pseudo_ct_pair() -> tuple[sitk.Image, sitk.Image]:
    from dpcn_med.synth import pseudo_ct

    mr = sitk.ReadImage(str(DATA / "seg3d/MR.nii.gz"))
    bone = sitk.ReadImage(str(DATA / "seg3d/skull_mask.nii.gz"))
    brain = sitk.ReadImage(str(DATA / "seg3d/brain_mask.nii.gz"))
    return mr, pseudo_ct(mr, bone=bone, brain=brain, seed=0)


def run_case(fixed: sitk.Image, source: sitk.Image, mode: str, trials: int, seed: int) -> dict:
    """Register ``trials`` moved copies of ``source`` onto ``fixed`` (same grid); TREs and timings."""
    corners = foreground_corners(fixed)
    centre, _ = foreground_box(fixed)
    rng = np.random.default_rng(seed)
    scales = (0.85, 1.15) if mode == "similarity" else (1.0, 1.0)
    before, after, voxel, solve_ms, total_s = [], [], [], [], []
    for _ in range(trials):
        truth = random_similarity(rng, centre, max_shift_mm=40.0, scale_range=scales)
        moving = moved_copy(source, truth)
        start = time.perf_counter()
        result = register(fixed, moving, mode=mode)
        total_s.append(time.perf_counter() - start)
        estimate = result.dpc_transform
        if result.start == "stored pose":  # the identity is no global estimate: take the solver's own choice
            estimate = register(fixed, moving, mode=mode, refine=False).dpc_transform
        before.append(target_registration_error(estimate, truth, corners))
        after.append(target_registration_error(result.fixed_to_moving, truth, corners))
        voxel.append(result.fixed_grid.spacing)
        solve_ms.append(result.timings["solve"] * 1000)
    before, after, voxel = np.array(before), np.array(after), np.array(voxel)
    return {"before_ok": float(np.mean(before < 2 * voxel)), "after_ok": float(np.mean(after < 1.0)),
            "before_median": float(np.median(before)), "after_median": float(np.median(after)),
            "after_max": float(after.max()), "voxel": float(np.median(voxel)),
            "solve_ms": statistics.median(solve_ms), "total_s": statistics.median(total_s)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=count_type(), default=40)
    parser.add_argument("--modes", nargs="+", default=["rigid", "similarity"], choices=["rigid", "similarity"])
    parser.add_argument("--cases", nargs="+", default=CASES, choices=CASES)
    parser.add_argument("--output", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "benchmarks")
    parser.add_argument("--output-name", help="file name of the table (default register_roundtrip.md)")
    args = parser.parse_args(argv)
    if not DATA.is_dir():
        print(f"{DATA} is absent: this benchmark needs the shared volumes", file=sys.stderr)
        return 2

    header = ("| volume | mode | trials | canonical voxel (mm) | TRE < 2 voxels, DPC only | median TRE, DPC only (mm) "
              "| TRE < 1 mm, refined | median TRE, refined (mm) | worst refined (mm) | solve (ms) | total (s) |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [header]
    for mode in args.modes:
        for key in args.cases:
            if key == MULTIMODAL:
                label, (fixed, moving) = "seg3d MR fixed, pseudo-CT of it moving (multimodal)", _pseudo_ct_pair()
            else:
                label, path = VOLUMES[key]
                fixed = moving = sitk.ReadImage(str(DATA / path))
            row = run_case(fixed, moving, mode, args.trials, seed=CASES.index(key))
            lines.append(_row(label, mode, args.trials, row))
            print(lines[-1], flush=True)

    text = (f"# Registration round trips\n\n{generated_by(__file__, argv)}. CPU: {torch.get_num_threads()} threads; "
            "`dpcn_med.register` with its defaults (learning-free solver at B = 32, Mattes mutual information "
            "refinement from its candidates). Poses: rotation uniform over SO(3), shift up to 40 mm, scale 0.85-1.15 "
            "in similarity mode; TRE over the 8 corners of the fixed foreground box.\n\n" + "\n".join(lines) + "\n")
    return publish(text, args.output / (args.output_name or "register_roundtrip.md"))


def _row(name: str, mode: str, trials: int, row: dict) -> str:
    return (f"| {name} | {mode} | {trials} | {row['voxel']:.2f} | {row['before_ok']:.0%} | {row['before_median']:.2f} "
            f"| {row['after_ok']:.0%} | {row['after_median']:.3f} | {row['after_max']:.2f} | {row['solve_ms']:.0f} "
            f"| {row['total_s']:.1f} |")


if __name__ == "__main__":
    raise SystemExit(main())
