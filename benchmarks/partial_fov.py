"""Partial field of view: a slab of the fixed volume against the whole moving volume, from any pose.

For each case and overlap fraction (the share of the fixed foreground's extent along a random voxel axis that the
slab keeps; the image is cropped there, so its field of view ends at the cut), ``--trials`` random poses: rotation
uniform over SO(3), translation up to 40 mm. The moving volume is the whole other image moved exactly
(:func:`dpcn_med.evaluation.moved_copy`). ``dpcn_med.register`` runs with the command line's defaults; success is a
target registration error under 2 mm after refinement, over the corners of the slab's foreground box. The local
baselines of ``dpcn-med benchmark`` (SimpleITK, ANTs, elastix; those installed) register the first
``--baseline-trials`` poses of each cell, and a second dpcn_med row gives its results on those poses alone, like for
like. Prints the tables and writes them under docs/, with a figure of success against overlap beside them.

    python benchmarks/partial_fov.py --trials 20 --baseline-trials 10 [--cases pseudo-ct t1-flair mr-mr]
        [--overlaps 1 0.8 0.6 0.4] [--methods dpcn ...]
    python benchmarks/partial_fov.py --combine A.csv B.csv ...   # the tables and figure of runs made side by side

Variants of dpcn_med's defaults (with ``--methods dpcn`` for its row alone): ``--bandwidth``, ``--sphere-band LOW
HIGH`` (one band only: :attr:`dpcn_med.solver.SolverConfig.sphere_band` without the extra bands),
``--degree-two-weight`` (:attr:`dpcn_med.solver.SolverConfig.degree_two_weight`), ``--entropy-bins``
(:attr:`dpcn_med.solver.SolverConfig.entropy_bins`), ``--cooccurrence-bins``
(:attr:`dpcn_med.solver.SolverConfig.cooccurrence_bins`), ``--fill`` (:attr:`dpcn_med.preprocess.Preprocessing.fill`).
"""

from __future__ import annotations

import argparse
import math
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med.benchmark import METHODS, SUCCESS_MM, available_methods
from dpcn_med.errors import InputError
from dpcn_med.evaluation import foreground_corners, moved_copy, random_similarity, target_registration_error
from dpcn_med.io import atomic_output, write_csv
from dpcn_med.preprocess import Preprocessing, foreground_box, foreground_mask
from dpcn_med.registration import register
from dpcn_med.solver import SolverConfig

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import (  # noqa: E402  (the scripts' shared helpers)
    count_type,
    fraction_type,
    generated_by,
    publish,
    read_unique_rows,
    refuse_run_options,
)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
CASES = {
    "pseudo-ct": "seg3d pseudo-CT slab (fixed) to the whole seg3d T1 MR (moving)",
    "t1-flair": "stroke T1 slab (fixed) to the whole FLAIR (moving)",
    "mr-mr": "seg3d T1 MR slab (fixed) to the whole seg3d T1 MR (moving)",
}
BASELINES = ["sitk-geometry", "sitk-moments", "sitk-exhaustive", "ants-rigid", "elastix-rigid"]
"""The local tools of ``dpcn-med benchmark``'s quick mode (ANTs' multi-start only on request; its cost:
docs/design_notes/benchmark.md)."""
SAME_POSES = "dpcn-baseline-poses"
"""The method name of dpcn_med's rows restricted to the poses the baselines ran (:func:`on_baseline_poses`)."""
SAME_POSES_LABEL = ", on the baselines' poses"
"""Appended to the label of the dpcn_med rows that :data:`SAME_POSES` rows repeat."""


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


def overlap_type(text: str) -> float:
    """An argparse type for an overlap: a fraction in (0, 1] in whole percents (the percent seeds the cell's poses)."""
    value = fraction_type(text)
    if not math.isclose(100 * value, round(100 * value), abs_tol=1e-6):
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole percent; the poses of an overlap are seeded by its "
                                         "percent, so give one such as 0.55")
    return value


def check_overlaps(parser: argparse.ArgumentParser, overlaps: list[float]) -> None:
    """Exit through ``parser`` if two of ``overlaps`` are the same percent (the same cell twice)."""
    percents = [round(100 * overlap) for overlap in overlaps]
    repeated = sorted({percent for percent in percents if percents.count(percent) > 1})
    if repeated:
        parser.error(f"--overlaps: {', '.join(f'{percent}%' for percent in repeated)} given twice")


def cell_poses(fixed_whole: sitk.Image, overlap: float, trials: int, seed: int
               ) -> Iterator[tuple[int, sitk.Image, sitk.Similarity3DTransform]]:
    """The poses of one cell, ``(trial, fixed slab, true fixed_to_moving)``, each following from ``seed`` and
    ``overlap`` alone (whatever runs on them)."""
    # round, not int: int(0.57 * 100) is 56, so 0.56 and 0.57 would share one stream; both give the same for the
    # documented 1, 0.8, 0.6 and 0.4, whose poses stay as they were
    rng = np.random.default_rng([seed, round(overlap * 100)])
    for trial in range(trials):
        fixed = slab(fixed_whole, overlap, rng)
        yield trial, fixed, random_similarity(rng, foreground_box(fixed)[0], max_shift_mm=40.0)


ROW_FIELDS = {"case": str, "overlap": float, "trial": int, "method": str, "tre_mm": float, "seconds": float,
              "label": str}
"""Columns of the per-registration CSV beside the table, and their types (:func:`run`'s rows and their labels)."""


def run(case: str, overlaps: list[float], trials: int, seed: int, methods: list[str], baseline_trials: int,
        **settings) -> list[dict]:
    """One row per pose and method of one case: ``case``, ``overlap``, ``trial``, ``method``, ``tre_mm``,
    ``seconds``. ``settings`` go to :func:`dpcn_med.register` for ``"dpcn"``; the other methods (keys of
    :data:`dpcn_med.benchmark.METHODS`) run on the first ``baseline_trials`` poses."""
    fixed_whole, moving_whole = case_images(case)
    rows = []
    folder = Path(tempfile.mkdtemp(prefix="dpcn-med-partial-fov-"))
    try:
        for overlap in overlaps:
            for trial, fixed, truth in cell_poses(fixed_whole, overlap, trials, seed):
                moving = moved_copy(moving_whole, truth)
                corners = foreground_corners(fixed)
                for method in methods:
                    if method != "dpcn" and trial >= baseline_trials:
                        continue
                    started = time.perf_counter()
                    if method == "dpcn":
                        estimate = register(fixed, moving, **settings).fixed_to_moving
                    else:
                        estimate = METHODS[method][2](fixed, moving, folder)
                    rows.append({"case": case, "overlap": overlap, "trial": trial, "method": method,
                                 "tre_mm": target_registration_error(estimate, truth, corners),
                                 "seconds": time.perf_counter() - started})
            for method in methods:
                errors = [r["tre_mm"] for r in rows if (r["overlap"], r["method"]) == (overlap, method)]
                print(f"{case} {overlap:.0%} {method}: {sum(e < SUCCESS_MM for e in errors)} of {len(errors)}",
                      file=sys.stderr)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return rows


def on_baseline_poses(rows: list[dict]) -> list[dict]:
    """dpcn_med's rows on the poses that the baselines ran too (the first ``--baseline-trials`` of each cell),
    renamed :data:`SAME_POSES`, labelled with :data:`SAME_POSES_LABEL`: its results like for like with theirs. None
    for a case and label where the baselines ran all of dpcn_med's poses, or none of them."""
    ran = {(r["case"], r["overlap"], r["trial"]) for r in rows if r["method"] not in ("dpcn", SAME_POSES)}
    same = []
    for case, label in dict.fromkeys((r["case"], r["label"]) for r in rows if r["method"] == "dpcn"):
        dpcn = [r for r in rows if (r["case"], r["method"], r["label"]) == (case, "dpcn", label)]
        shared = [r for r in dpcn if (case, r["overlap"], r["trial"]) in ran]
        if 0 < len(shared) < len(dpcn):
            same += [{**r, "method": SAME_POSES, "label": label + SAME_POSES_LABEL} for r in shared]
    return same


def combined_rows(paths: list[Path]) -> list[dict]:
    """The rows of earlier runs' per-pose CSVs, in the files' order.

    Raises:
        InputError: a missing or malformed file (:func:`dpcn_med.io.read_csv`), or a registration (case, overlap,
            trial, method, label) found twice: a file given twice would count its poses twice.
    """
    return read_unique_rows(
        paths, ROW_FIELDS, lambda r: (r["case"], round(100 * r["overlap"]), r["trial"], r["method"], r["label"]),
        lambda r: f"{r['case']}, {r['overlap']:.0%} overlap, trial {r['trial']}, {r['method']} ({r['label']})")


def series(rows: list[dict]) -> list[tuple[str, str]]:
    """The table's lines and the figure's curves, ``(method, label)``: dpcn_med's (each label a variant), its rows on
    the baselines' poses, then the others as they ran."""
    found = dict.fromkeys((r["method"], r["label"]) for r in rows)
    return sorted(found, key=lambda item: (item[0] != "dpcn", item[0] != SAME_POSES))


def table(rows: list[dict], lines_of: list[tuple[str, str]]) -> str:
    """Per case, one line per ``(method, label)`` of ``lines_of``: success at each overlap (``–`` where it has no
    poses there), median TRE and seconds over all its poses."""
    overlaps = list(dict.fromkeys(r["overlap"] for r in rows))
    lines = []
    for case in dict.fromkeys(r["case"] for r in rows):
        lines += [f"### {CASES[case]}", "",
                  "| method | poses per cell | " + " | ".join(f"{o:.0%} overlap" for o in overlaps)
                  + " | median TRE (mm) | median seconds |", "|---|---|" + "---|" * (len(overlaps) + 2)]
        for method, label in lines_of:
            mine = [r for r in rows if (r["case"], r["method"], r["label"]) == (case, method, label)]
            if not mine:
                continue
            cells = [[r["tre_mm"] for r in mine if r["overlap"] == o] for o in overlaps]
            poses = ", ".join(str(n) for n in dict.fromkeys(len(c) for c in cells if c))
            lines.append(f"| {label} | {poses} | "
                         + " | ".join(f"{100 * sum(e < SUCCESS_MM for e in c) / len(c):.0f}%" if c else "–"
                                      for c in cells)
                         + f" | {statistics.median(r['tre_mm'] for r in mine):.2f}"
                         + f" | {statistics.median(r['seconds'] for r in mine):.1f} |")
        lines.append("")
    return "\n".join(lines)


def figure(rows: list[dict], curves: list[tuple[str, str]], path: Path) -> None:
    """Success against overlap, one panel per case, one line per method (the baselines offset by up to a few
    points so that equal curves do not hide each other; dpcn_med on the baselines' poses dashed, in dpcn_med's
    colour), written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(dict.fromkeys(r["case"] for r in rows))
    figure_, axes = plt.subplots(1, len(cases), figsize=(4.5 * len(cases), 4.2), squeeze=False,
                                 constrained_layout=True)
    markers = "os^vDP*X"
    # colours, markers and offsets as without the like-for-like lines, which borrow their dpcn_med row's
    own = [curve for curve in curves if curve[0] != SAME_POSES]
    for ax, case in zip(axes[0], cases):
        for method, label in curves:
            mine = [r for r in rows if (r["case"], r["method"], r["label"]) == (case, method, label)]
            overlaps = sorted({r["overlap"] for r in mine})
            success = [100 * statistics.mean(r["tre_mm"] < SUCCESS_MM for r in mine if r["overlap"] == o)
                       for o in overlaps]
            index = own.index(("dpcn", label.removesuffix(SAME_POSES_LABEL)) if method == SAME_POSES
                              else (method, label))
            # equal baselines stay visible side by side; dpcn_med's curves are drawn where they are
            offset = 0.0 if method in ("dpcn", SAME_POSES) else 1.2 * (index - len(own) / 2)
            style = {"dpcn": {"lw": 2.5}, SAME_POSES: {"lw": 1.5, "ls": "--", "mfc": "none"}}.get(method, {"lw": 1.2})
            ax.plot([100 * o for o in overlaps], [value + offset for value in success], marker=markers[index % 8],
                    color=f"C{index}", label=label, **style)
        ax.set(title=CASES[case], xlabel="overlap (% of the fixed foreground's extent)",
               ylabel=f"success (TRE < {SUCCESS_MM:g} mm), %", ylim=(-8, 108))
        ax.title.set_fontsize(8)
    figure_.legend(*axes[0][0].get_legend_handles_labels(), loc="outside lower center", ncols=3, fontsize=7)
    with atomic_output(path) as temporary:
        figure_.savefig(temporary, dpi=110)
    plt.close(figure_)


def build_parser() -> argparse.ArgumentParser:
    """The script's options."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--overlaps", nargs="+", type=overlap_type, default=[1.0, 0.8, 0.6, 0.4],
                        help="shares of the fixed foreground's extent kept, in (0, 1], whole percents")
    parser.add_argument("--trials", type=count_type(), default=20)
    parser.add_argument("--methods", nargs="+", default=["dpcn", *BASELINES], choices=list(METHODS),
                        help="dpcn_med (with the settings below) and local baselines of dpcn_med.benchmark")
    parser.add_argument("--baseline-trials", type=count_type(0), default=10,
                        help="the methods other than dpcn run on the first this many poses of each cell")
    parser.add_argument("--seed", type=count_type(0), default=0)
    parser.add_argument("--bandwidth", type=int, default=32, help="solver bandwidth B (the CLI's default: 32)")
    parser.add_argument("--sphere-band", type=float, nargs=2, metavar=("LOW", "HIGH"),
                        help="one sphere band instead of the solver's bands, fractions of Nyquist")
    parser.add_argument("--degree-two-weight", type=float, default=SolverConfig.degree_two_weight,
                        help="SolverConfig.degree_two_weight: the spheres' degree-2 harmonics' weight")
    parser.add_argument("--entropy-bins", type=int, default=SolverConfig.entropy_bins,
                        help="SolverConfig.entropy_bins: the entropy images' candidates (0: none)")
    parser.add_argument("--cooccurrence-bins", type=int, default=SolverConfig.cooccurrence_bins,
                        help="SolverConfig.cooccurrence_bins: the co-occurrence spectra's candidates (0: none)")
    parser.add_argument("--fill", type=float, default=Preprocessing.fill, help="canonical-grid fill")
    parser.add_argument("--label", default="dpcn_med learning-free (CLI defaults)",
                        help="the dpcn row's label, e.g. the variant")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "partial_fov.md",
                        help="the table; the figure (.png) and every registration (.csv) go beside it")
    parser.add_argument("--note", default="", help="a sentence for the description, e.g. when the combined rows ran")
    parser.add_argument("--combine", nargs="+", type=Path, metavar="CSV",
                        help="run nothing: the tables and figure of earlier runs' per-pose CSVs (say, one per case, "
                             "run side by side on separate cores, or variants with their own --label); with --output "
                             "and --note only")
    return parser


def run_all(args: argparse.Namespace, methods: list[str]) -> list[dict]:
    """Every case of ``args`` with ``methods``, each row labelled (``args.label`` for dpcn_med's), also written to the
    per-registration CSV beside ``args.output`` for ``--combine``."""
    bands = {"sphere_band": tuple(args.sphere_band), "extra_sphere_bands": ()} if args.sphere_band else {}
    solver = SolverConfig(degree_two_weight=args.degree_two_weight, entropy_bins=args.entropy_bins,
                          cooccurrence_bins=args.cooccurrence_bins, **bands)
    settings = {"bandwidth": args.bandwidth, "solver": solver, "preprocessing": Preprocessing(fill=args.fill)}
    rows = [{**row, "label": args.label if row["method"] == "dpcn" else METHODS[row["method"]][0]}
            for case in args.cases
            for row in run(case, args.overlaps, args.trials, args.seed, methods, args.baseline_trials, **settings)]
    write_csv(rows, args.output.with_suffix(".csv"))  # every registration, for --combine
    return rows


def description(args: argparse.Namespace, argv: list[str] | None, same: list[dict], missing: list[str]) -> str:
    """The page's title and paragraph, and the figure's link."""
    return (f"# Partial field of view\n\n{generated_by(__file__, argv)}: a slab of the fixed volume "
            f"along a random voxel axis keeping the given share of its foreground's extent, the moving volume whole "
            f"and moved by a random rigid pose (rotation uniform over SO(3), translation up to 40 mm); "
            f"`dpcn_med.register` with the command line's defaults unless the label says otherwise, the local "
            f"baselines (`dpcn-med benchmark`'s settings) on the first poses of each cell; success is a TRE under "
            f"{SUCCESS_MM:g} mm over the slab foreground's corners; times on a shared CPU."
            + (" dpcn_med \"on the baselines' poses\": its results on those poses alone." if same else "")
            + (f" Not installed, left out: {', '.join(missing)}." if missing else "")
            + (f" {args.note}" if args.note else "")
            + f"\n\n![success against overlap]({args.output.with_suffix('.png').name})\n\n")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    check_overlaps(parser, args.overlaps)
    if args.combine:
        refuse_run_options(parser, argv, {
            "cases": "--cases", "overlaps": "--overlaps", "trials": "--trials", "methods": "--methods",
            "baseline_trials": "--baseline-trials", "seed": "--seed", "bandwidth": "--bandwidth",
            "sphere_band": "--sphere-band", "degree_two_weight": "--degree-two-weight",
            "entropy_bins": "--entropy-bins", "cooccurrence_bins": "--cooccurrence-bins", "fill": "--fill",
            "label": "--label"})
    installed = available_methods()
    methods = [m for m in args.methods if m in installed]
    missing = [] if args.combine else [m for m in args.methods if m not in installed]
    args.output.parent.mkdir(parents=True, exist_ok=True)
    if args.combine:
        try:
            rows = combined_rows(args.combine)
        except InputError as error:
            parser.error(str(error))
    else:
        rows = run_all(args, methods)
    same = on_baseline_poses(rows)
    rows += same
    lines_of = series(rows)
    text = description(args, argv, same, missing) + table(rows, lines_of)
    figure(rows, lines_of, args.output.with_suffix(".png"))  # after the table: a failing table leaves the figure as was
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
