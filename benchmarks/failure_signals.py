"""Which of a registration's own numbers tell a failed registration from a good one?

The command line warns (exit 3) below ``--min-confidence``, a threshold on the solver's translation-peak mass. This
script measures, on poses where dpcn_med sometimes fails (the partial-field-of-view slabs of ``partial_fov.py``, the
same poses for the same seed), how well that and the registration's other numbers separate failures (TRE of 2 mm or
more) from successes:

- ``confidence``: :attr:`dpcn_med.RegistrationResult.confidence`;
- ``overlap``: the share of the fixed foreground mapped inside the moving field of view;
- ``mattes_mi``: Mattes mutual information at the result (SimpleITK's sign: lower is better);
- ``nmi``: Studholme's normalised mutual information at the result, on the fixed foreground (in ``[1, 2]``, less
  sensitive to the size of the overlap than mutual information);
- ``runner_up_gap``: the best other start's metric after the coarsest refinement level minus the winner's (how
  clearly the winning start won; negative where it won only at a finer level).

Per signal: its medians over successes and failures, the area under the ROC curve (the chance that a random success
scores better than a random failure), and the share of failures flagged at the threshold that flags 5% of successes.

    python benchmarks/failure_signals.py [--cases pseudo-ct t1-flair mr-mr] [--overlaps 0.6 0.4] [--trials 20]
    python benchmarks/failure_signals.py --combine A.csv B.csv ...   # the table of runs made side by side
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy.stats import mannwhitneyu

from dpcn_med.benchmark import SUCCESS_MM
from dpcn_med.outputs import MIN_CONFIDENCE
from dpcn_med.errors import InputError
from dpcn_med.evaluation import foreground_corners, moved_copy, target_registration_error
from dpcn_med.io import write_csv
from dpcn_med.preprocess import foreground_mask
from dpcn_med.registration import register

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish, read_unique_rows, refuse_run_options  # noqa: E402  (the scripts' shared helpers)
from partial_fov import (  # noqa: E402  (the same slabs and poses)
    CASES,
    case_images,
    cell_poses,
    check_overlaps,
    overlap_type,
)

ROOT = Path(__file__).resolve().parents[1]
SIGNALS = {"confidence": 1, "overlap": 1, "mattes_mi": -1, "nmi": 1, "runner_up_gap": 1}
"""Each signal and its sense: +1 where a higher value means a likelier success, -1 where lower does."""
ROW_FIELDS = {"case": str, "overlap_fraction": float, "trial": int, "tre_mm": float, "start": str,
              **{name: float for name in SIGNALS}}


def normalised_mutual_information(a: np.ndarray, b: np.ndarray, bins: int = 64) -> float:
    """``(H(A) + H(B)) / H(A, B)`` of paired samples ``(K,)``. Written here: scikit-image has it, but is not a
    dependency for one formula."""
    joint, _, _ = np.histogram2d(a, b, bins=bins)
    p = joint / joint.sum()

    def entropy(q: np.ndarray) -> float:
        q = q[q > 0]
        return float(-np.sum(q * np.log(q)))

    return (entropy(p.sum(axis=0)) + entropy(p.sum(axis=1))) / entropy(p)


def nmi_at(fixed: sitk.Image, moving: sitk.Image, fixed_to_moving: sitk.Transform) -> float:
    """Normalised mutual information of ``fixed`` and ``moving`` as ``fixed_to_moving`` aligns them, over the fixed
    foreground mapped inside the moving field of view (``nan`` where none is)."""
    resampled = sitk.Resample(sitk.Cast(moving, sitk.sitkFloat32), fixed, fixed_to_moving, sitk.sitkLinear,
                              float("nan"), sitk.sitkFloat32)
    values = sitk.GetArrayViewFromImage(resampled)
    keep = (sitk.GetArrayViewFromImage(foreground_mask(fixed)) > 0) & np.isfinite(values)
    if keep.sum() < 100:
        return float("nan")
    return normalised_mutual_information(sitk.GetArrayViewFromImage(fixed)[keep].astype(np.float64),
                                         values[keep].astype(np.float64))


def run(case: str, overlaps: list[float], trials: int, seed: int) -> list[dict]:
    """One row per pose: the TRE, which start won, and every signal of :data:`SIGNALS`."""
    fixed_whole, moving_whole = case_images(case)
    rows = []
    for overlap in overlaps:
        for trial, fixed, truth in cell_poses(fixed_whole, overlap, trials, seed):
            moving = moved_copy(moving_whole, truth)
            result = register(fixed, moving)
            final = result.metric["refined"] if result.refined else result.metric["dpc"]
            others = [m for k, m in enumerate(result.candidate_metrics) if k != result.candidate and m is not None]
            winner = result.candidate_metrics[result.candidate] if result.candidate_metrics else None
            rows.append({
                "case": case, "overlap_fraction": overlap, "trial": trial, "start": result.start,
                "tre_mm": target_registration_error(result.fixed_to_moving, truth, foreground_corners(fixed)),
                "confidence": result.confidence, "overlap": result.overlap,
                "mattes_mi": float("nan") if final is None else final,
                "nmi": nmi_at(fixed, moving, result.fixed_to_moving),
                "runner_up_gap": min(others) - winner if others and winner is not None else float("nan")})
            print(f"{case} {overlap:.0%} {trial}: {rows[-1]['tre_mm']:.2f} mm", file=sys.stderr)
    return rows


def combined_rows(paths: list[Path]) -> list[dict]:
    """The rows of earlier runs' CSVs, in the files' order.

    Raises:
        InputError: a missing or malformed file (:func:`dpcn_med.io.read_csv`), or a pose (case, overlap, trial)
            found twice: a file given twice would count its poses twice.
    """
    return read_unique_rows(paths, ROW_FIELDS, lambda r: (r["case"], round(100 * r["overlap_fraction"]), r["trial"]),
                            lambda r: f"{r['case']}, {r['overlap_fraction']:.0%} overlap, trial {r['trial']}")


def separation(rows: list[dict]) -> str:
    """The table: per signal, medians over successes and failures, ROC AUC and failures flagged at 5% false
    alarms."""
    success = [r for r in rows if r["tre_mm"] < SUCCESS_MM]
    failure = [r for r in rows if r["tre_mm"] >= SUCCESS_MM]
    lines = [f"{len(success)} successes and {len(failure)} failures (TRE of {SUCCESS_MM:g} mm or more).", "",
             "| signal | better when | median, successes | median, failures | ROC AUC | failures flagged at 5% of "
             "successes flagged |", "|---|---|---|---|---|---|"]
    for name, sense in SIGNALS.items():
        good = np.array([sense * r[name] for r in success if np.isfinite(r[name])])
        bad = np.array([sense * r[name] for r in failure if np.isfinite(r[name])])
        if len(good) == 0 or len(bad) == 0:
            lines.append(f"| `{name}` | {'higher' if sense > 0 else 'lower'} | | | not measurable | |")
            continue
        auc = mannwhitneyu(good, bad).statistic / (len(good) * len(bad))
        threshold = np.quantile(good, 0.05)
        lines.append(f"| `{name}` | {'higher' if sense > 0 else 'lower'} | {sense * np.median(good):.4g} | "
                     f"{sense * np.median(bad):.4g} | {auc:.2f} | {np.mean(bad < threshold):.0%} "
                     f"(threshold {sense * threshold:.4g}) |")
    flagged = [sum(r["confidence"] < MIN_CONFIDENCE for r in group) for group in (failure, success)]
    lines += ["", f"At the command line's `--min-confidence` ({MIN_CONFIDENCE:g}, exit code 3): {flagged[0]} of "
              f"{len(failure)} failures flagged, and {flagged[1]} of {len(success)} successes."]
    lines += ["", "Per pair (the levels are each pair's own):", "",
              "| pair | overlaps | registered | median `confidence`, successes / failures | median `mattes_mi`, "
              "successes / failures |", "|---|---|---|---|---|"]
    for case in dict.fromkeys(r["case"] for r in rows):
        mine = [[r for r in group if r["case"] == case] for group in (success, failure)]
        medians = [" / ".join(f"{statistics.median(r[name] for r in group):.3g}" if group else "-" for group in mine)
                   for name in ("confidence", "mattes_mi")]
        overlaps = ", ".join(f"{o:.0%}" for o in dict.fromkeys(r["overlap_fraction"] for r in rows
                                                                 if r["case"] == case))
        lines.append(f"| {CASES[case]} | {overlaps} | {len(mine[0])} of {len(mine[0]) + len(mine[1])} | "
                     f"{medians[0]} | {medians[1]} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--overlaps", nargs="+", type=overlap_type, default=[0.6, 0.4],
                        help="shares of the fixed foreground's extent kept, in (0, 1], whole percents")
    parser.add_argument("--trials", type=count_type(), default=20)
    parser.add_argument("--seed", type=count_type(0), default=0)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "failure_signals.md",
                        help="the table; every registration (.csv) goes beside it")
    parser.add_argument("--combine", nargs="+", type=Path, metavar="CSV",
                        help="run nothing: the table of earlier runs' per-pose CSVs; with --output and --note only")
    parser.add_argument("--note", default="", help="a sentence for the description, e.g. how the combined rows ran")
    args = parser.parse_args(argv)
    check_overlaps(parser, args.overlaps)
    if args.combine:
        refuse_run_options(parser, argv, {"cases": "--cases", "overlaps": "--overlaps", "trials": "--trials",
                                          "seed": "--seed"})
    args.output.parent.mkdir(parents=True, exist_ok=True)  # before the work: the CSV is written beside the table
    if args.combine:
        try:
            rows = combined_rows(args.combine)
        except InputError as error:
            parser.error(str(error))
    else:
        rows = [row for case in args.cases for row in run(case, args.overlaps, args.trials, args.seed)]
        write_csv(rows, args.output.with_suffix(".csv"))
    text = (f"# Failure signals\n\n{generated_by(__file__, argv)}: `dpcn_med.register` with the command line's "
            f"defaults on the slabs and poses of `partial_fov.py` (same seed), and how well each of its own numbers "
            f"separates its failures from its successes."
            + (f" {args.note}" if args.note else "") + "\n\n" + separation(rows) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
