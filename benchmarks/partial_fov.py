"""Partial field of view: a slab of the fixed volume against the whole moving volume, from any pose.

For each case and overlap fraction (the share of the fixed foreground's extent along a random voxel axis that the
slab keeps; the image is cropped there, so its field of view ends at the cut), ``--trials`` random poses: rotation
uniform over SO(3), translation up to 40 mm. The moving volume is the whole other image moved exactly
(:func:`dpcn_med.evaluation.moved_copy`). ``dpcn_med.register`` runs with the command line's defaults; success is a
target registration error under 2 mm after refinement, over the corners of the slab's foreground box. Prints a
table and writes it under docs/.

    python benchmarks/partial_fov.py --trials 20 [--cases pseudo-ct t1-flair mr-mr] [--overlaps 1 0.8 0.6 0.4]

Variants of the defaults, for a side-by-side row: ``--bandwidth``, ``--sphere-band LOW HIGH`` (one band only:
:attr:`dpcn_med.solver.SolverConfig.sphere_band` without the extra bands), ``--fill``
(:attr:`dpcn_med.preprocess.Preprocessing.fill`).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med.evaluation import foreground_corners, moved_copy, random_similarity, target_registration_error
from dpcn_med.preprocess import Preprocessing, foreground_box, foreground_mask
from dpcn_med.register import register
from dpcn_med.solver import SolverConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import generated_by, publish  # noqa: E402  (the scripts' shared helpers)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
CASES = {
    "pseudo-ct": "seg3d pseudo-CT slab (fixed) to the whole seg3d T1 MR (moving)",
    "t1-flair": "stroke T1 slab (fixed) to the whole FLAIR (moving)",
    "mr-mr": "seg3d T1 MR slab (fixed) to the whole seg3d T1 MR (moving)",
}


def case_images(name: str) -> tuple[sitk.Image, sitk.Image]:
    """``(fixed whole, moving whole)``, aligned voxel for voxel."""
    if name == "t1-flair":
        return (sitk.ReadImage(str(DATA / "stroke/T1.nii.gz")), sitk.ReadImage(str(DATA / "stroke/FLAIR.nii.gz")))
    mr = sitk.ReadImage(str(DATA / "seg3d/MR.nii.gz"))
    if name == "mr-mr":
        return mr, mr
    from dpcn_med.synth import pseudo_ct

    bone = sitk.ReadImage(str(DATA / "seg3d/skull_mask.nii.gz"))
    brain = sitk.ReadImage(str(DATA / "seg3d/brain_mask.nii.gz"))
    return pseudo_ct(mr, bone=bone, brain=brain, seed=0), mr


def slab(image: sitk.Image, fraction: float, rng: np.random.Generator) -> sitk.Image:
    """``image`` cropped to a slab along a random voxel axis keeping ``fraction`` of its foreground's extent there
    (at a random position inside it); ``fraction`` 1 returns the image whole."""
    if fraction >= 1:
        return image
    stats = sitk.LabelShapeStatisticsImageFilter()
    stats.Execute(foreground_mask(image))
    box = stats.GetBoundingBox(1)
    axis = int(rng.integers(3))
    low, extent = box[axis], box[axis + 3]
    length = max(1, int(round(fraction * extent)))
    start = low + int(rng.integers(0, extent - length + 1))
    index, size = [0, 0, 0], list(image.GetSize())
    index[axis], size[axis] = start, length
    return sitk.RegionOfInterest(image, size, index)


def run(case: str, overlaps: list[float], trials: int, seed: int, **settings) -> list[dict]:
    """The rows of one case; ``settings`` go to :func:`dpcn_med.register.register`."""
    fixed_whole, moving_whole = case_images(case)
    rows = []
    for overlap in overlaps:
        rng = np.random.default_rng([seed, int(overlap * 100)])
        errors, seconds = [], []
        for _ in range(trials):
            fixed = slab(fixed_whole, overlap, rng)
            truth = random_similarity(rng, foreground_box(fixed)[0], max_shift_mm=40.0)
            moving = moved_copy(moving_whole, truth)
            started = time.perf_counter()
            result = register(fixed, moving, **settings)
            seconds.append(time.perf_counter() - started)
            errors.append(target_registration_error(result.fixed_to_moving, truth, foreground_corners(fixed)))
        rows.append({"case": case, "overlap": overlap, "trials": trials,
                     "success": sum(e < 2.0 for e in errors) / trials, "median_tre": statistics.median(errors),
                     "seconds": statistics.median(seconds)})
        print(f"{case} {overlap:.0%}: {rows[-1]['success']:.0%} (median TRE {rows[-1]['median_tre']:.2f} mm)",
              file=sys.stderr)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--overlaps", nargs="+", type=float, default=[1.0, 0.8, 0.6, 0.4])
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--bandwidth", type=int, default=32, help="solver bandwidth B (the CLI's default: 32)")
    parser.add_argument("--sphere-band", type=float, nargs=2, metavar=("LOW", "HIGH"),
                        help="one sphere band instead of the solver's bands, fractions of Nyquist")
    parser.add_argument("--fill", type=float, default=Preprocessing.fill, help="canonical-grid fill")
    parser.add_argument("--label", default="learning-free (CLI defaults)", help="the row label, e.g. the variant")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "partial_fov.md")
    args = parser.parse_args(argv)
    solver = SolverConfig(sphere_band=tuple(args.sphere_band), extra_sphere_bands=()) if args.sphere_band else None
    settings = {"bandwidth": args.bandwidth, "solver": solver, "preprocessing": Preprocessing(fill=args.fill)}
    rows = [row for case in args.cases for row in run(case, args.overlaps, args.trials, args.seed, **settings)]
    lines = ["| case | method | overlap | trials | success (TRE < 2 mm) | median TRE (mm) | median seconds |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {CASES[r['case']]} | {args.label} | {r['overlap']:.0%} | {r['trials']} | {r['success']:.0%} | "
              f"{r['median_tre']:.2f} | {r['seconds']:.1f} |" for r in rows]
    text = (f"# Partial field of view\n\n{generated_by(__file__, argv)}: a slab of the fixed volume "
            f"along a random voxel axis keeping the given share of its foreground's extent, the moving volume whole "
            f"and moved by a random rigid pose (rotation uniform over SO(3), translation up to 40 mm); "
            f"`dpcn_med.register` with the command line's defaults; TRE over the slab foreground's corners.\n\n"
            + "\n".join(lines) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
