"""Fit and check the quality model: how likely a registration is right, from its own numbers.

Collect (``--collect``): register pairs whose right answer is known (whole volumes and slabs, same modality,
cross-contrast and pseudo-CT to MR, from random poses) and deliberate failures where none exists (a head against a
porcine phantom, against a volume of smoothed noise, and a slab against a part of the head it does not contain), and
write each registration's :func:`dpcn_med.quality.signals` inputs and its TRE to a CSV. Mirrored heads (a left-right
header flip) are registered too and reported apart: no rigid answer is right, yet a head is nearly symmetric.

Fit (the default): fit the logistic model on the ``fit`` pairs, choose the threshold there (:func:`choose_threshold`:
midway between the failures and the successes, flagging at most ``--max-flagged-successes`` of these), and check both on the ``check`` pairs, which share no
pair with the fit: a calibration table by decile of probability, a reliability diagram, and the share of failures
and successes flagged per group. Writes the model into the package (``dpcn_med/quality_model.json``) with
``--write-model``.

    python benchmarks/quality_fit.py --collect --output docs/benchmarks/quality/registrations.csv   # ~15 min, 2 cores
    python benchmarks/quality_fit.py docs/benchmarks/quality/registrations.csv --write-model \\
        --output docs/benchmarks/quality.md
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import SimpleITK as sitk

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish, read_unique_rows  # noqa: E402  (the scripts' shared helpers)
from partial_fov import case_images  # noqa: E402  (the same slabs' images)

from dpcn_med.benchmark import CASES, SUCCESS_MM
from dpcn_med.benchmark.cases import rotation_in_bin
from dpcn_med.evaluation import foreground_corners, moved_copy, target_registration_error
from dpcn_med.io import write_csv
from dpcn_med.preprocess import foreground_box, foreground_mask
from dpcn_med.quality import QualityModel, fit, signals
from dpcn_med.registration import mirrored_copy

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
MODEL_PATH = ROOT / "dpcn_med" / "quality_model.json"
FIELDS = {"split": str, "group": str, "pair": str, "trial": int, "tre_mm": float, "confidence": float,
          "overlap": float, "mi_refined": float, "mi_dpc": float, "fixed_entropy": float, "candidate_metrics": str,
          "start": str, "seconds": float}
"""The CSV's columns: ``tre_mm`` is ``nan`` where no answer is right (groups ``deliberate`` and ``mirrored``)."""
DELIBERATE = ("deliberate", "mirrored")
MODEL_SIGNALS = ("log_information_share", "overlap")
"""The shipped model's inputs: the set that did best when each fit pair was held out in turn (the table this script
writes compares it with each signal alone and with all of them)."""
COMPARED = [("log_confidence",), ("information_share",), ("log_information_share",), ("overlap",), ("candidate_lead",),
            MODEL_SIGNALS, ("log_confidence", "log_information_share", "overlap", "candidate_lead")]


def _read(relative: str) -> sitk.Image:
    return sitk.ReadImage(str(DATA / relative))


def _noise_volume(seed: int) -> sitk.Image:
    """Smoothed noise in an ellipsoid, 1.5 mm voxels, 128 x 128 x 110: a volume of the size of a head with no
    anatomy."""
    rng = np.random.default_rng(seed)
    shape = (110, 128, 128)
    image = sitk.GetImageFromArray(rng.normal(size=shape).astype(np.float32))
    image.SetSpacing((1.5, 1.5, 1.5))
    smooth = sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(image, 6.0))
    z, y, x = np.meshgrid(*(np.linspace(-1, 1, n) for n in shape), indexing="ij")
    inside = (x / 0.8) ** 2 + (y / 0.9) ** 2 + (z / 0.85) ** 2 < 1
    values = np.where(inside, 500 + 2000 * (smooth - smooth.min()) / np.ptp(smooth), 0).astype(np.float32)
    noise = sitk.GetImageFromArray(values)
    noise.SetSpacing((1.5, 1.5, 1.5))
    return noise


def _part(image: sitk.Image, low: float, high: float, axis: int = 2) -> sitk.Image:
    """``image`` cropped along voxel ``axis`` to the share ``[low, high]`` of its foreground's extent there."""
    stats = sitk.LabelShapeStatisticsImageFilter()
    stats.Execute(foreground_mask(image))
    box = stats.GetBoundingBox(1)
    start, extent = box[axis], box[axis + 3]
    index, size = [0, 0, 0], list(image.GetSize())
    index[axis] = start + int(round(low * extent))
    size[axis] = max(1, int(round((high - low) * extent)))
    return sitk.RegionOfInterest(image, size, index)


def _slab(image: sitk.Image, fraction: float, rng: np.random.Generator) -> sitk.Image:
    """A slab keeping ``fraction`` of the foreground's extent along a random voxel axis, at a random place."""
    axis = int(rng.integers(3))
    low = float(rng.uniform(0, 1 - fraction))
    return _part(image, low, low + fraction, axis)


Case = tuple[str, str, str, Callable[[], tuple[sitk.Image, sitk.Image]], float | None]
"""``(split, group, pair, loader of the aligned (fixed, moving), slab share or None)``; for the deliberate and mirrored
groups the loader's moving image has no right pose, and the TRE is not measured."""


def cases() -> list[Case]:
    """Every case of the collection. The fit and check splits share no pair of volumes."""
    stroke_t2 = lambda: (_read("stroke/T1.nii.gz"), _read("stroke/T2.nii.gz"))  # noqa: E731
    listed: list[Case] = []
    for split, pairs in (("fit", [("MNI T1 to itself", CASES["mni"][2]),
                                  ("seg3d T1 to its pseudo-CT", lambda: case_images("pseudo-ct")),
                                  ("stroke T1 to FLAIR", CASES["t1-flair"][2])]),
                         ("check", [("MNI T1 to its pseudo-CT", CASES["mni-pseudo-ct"][2]),
                                    ("seg3d T1 to itself", lambda: case_images("mr-mr")),
                                    ("stroke T1 to T2", stroke_t2)])):
        for pair, loader in pairs:
            listed += [(split, "whole", pair, loader, None), (split, "slab 60%", pair, loader, 0.6),
                       (split, "slab 40%", pair, loader, 0.4)]
    seg3d_mr = lambda: _read("seg3d/MR.nii.gz")  # noqa: E731
    listed += [
        ("fit", "deliberate", "seg3d T1 to a porcine phantom CT (wrong body part)",
         lambda: (seg3d_mr(), _read("mridir/mridir_ct_1p5mm.nii.gz")), None),
        ("fit", "deliberate", "stroke T1 to smoothed noise (unrelated)", lambda: (_read("stroke/T1.nii.gz"),
                                                                                  _noise_volume(1)), None),
        ("fit", "deliberate", "seg3d T1 top 30% to its pseudo-CT's lower 40% (no anatomy in common)",
         lambda: (_part(seg3d_mr(), 0.7, 1.0), _part(case_images("pseudo-ct")[0], 0.0, 0.4)), None),
        ("check", "deliberate", "stroke FLAIR to a porcine phantom T2 (wrong body part)",
         lambda: (_read("stroke/FLAIR.nii.gz"), _read("mridir/mridir_t2_1p5mm.nii.gz")), None),
        ("check", "deliberate", "seg3d T1 to smoothed noise (unrelated)", lambda: (seg3d_mr(), _noise_volume(2)), None),
        ("check", "deliberate", "stroke T1 top 30% to its FLAIR's lower 40% (no anatomy in common)",
         lambda: (_part(_read("stroke/T1.nii.gz"), 0.7, 1.0), _part(_read("stroke/FLAIR.nii.gz"), 0.0, 0.4)), None),
        ("check", "mirrored", "seg3d T1 to its mirrored pseudo-CT", lambda: (lambda f, m: (f, mirrored_copy(m)))(
            *case_images("pseudo-ct")[::-1]), None),
        ("check", "mirrored", "stroke T1 to its mirrored FLAIR",
         lambda: (_read("stroke/T1.nii.gz"), mirrored_copy(_read("stroke/FLAIR.nii.gz"))), None),
    ]
    return listed


def poses(case: Case, trials: int, seed: int) -> Iterator[tuple[int, sitk.Image, sitk.Image, sitk.Transform]]:
    """``(trial, fixed, moving, true fixed_to_moving)`` of one case: the moving image moved by a random rigid pose
    (angle uniform in 0-180 degrees about a uniform axis, shift up to 40 mm), the fixed one a random slab where the
    case has a share."""
    split, group, pair, loader, share = case
    fixed_whole, moving_whole = loader()
    rng = np.random.default_rng([seed, sum(map(ord, f"{group} {pair}"))])
    for trial in range(trials):
        fixed = fixed_whole if share is None else _slab(fixed_whole, share, rng)
        truth = rotation_in_bin(rng, 0, 180, foreground_box(fixed)[0], 40.0)
        yield trial, fixed, moved_copy(moving_whole, truth), truth


def collect(trials: int, deliberate_trials: int, seed: int, output: Path) -> list[dict]:
    """Register every case's poses with the command line's defaults; the rows (also written to ``output``)."""
    from dpcn_med.registration import register

    rows = []
    for case in cases():
        split, group, pair = case[:3]
        count = deliberate_trials if group in DELIBERATE else trials
        for trial, fixed, moving, truth in poses(case, count, seed):
            started = time.perf_counter()
            result = register(fixed, moving)
            seconds = time.perf_counter() - started
            tre = (math.nan if group in DELIBERATE
                   else target_registration_error(result.fixed_to_moving, truth, foreground_corners(fixed)))
            nan = lambda value: math.nan if value is None else value  # noqa: E731
            rows.append({"split": split, "group": group, "pair": pair, "trial": trial, "tre_mm": tre,
                         "confidence": result.confidence, "overlap": result.overlap,
                         "mi_refined": nan(result.metric["refined"]), "mi_dpc": nan(result.metric["dpc"]),
                         "fixed_entropy": nan(result.fixed_entropy),
                         "candidate_metrics": json.dumps(result.candidate_metrics), "start": result.start,
                         "seconds": seconds})
            print(f"{split} {group} {pair} #{trial}: {tre:.2f} mm, p={result.success_probability}, {seconds:.1f} s",
                  file=sys.stderr)
            write_csv(rows, output, list(FIELDS))  # after every registration: an interrupted run keeps its rows
    return rows


def row_signals(row: dict) -> dict[str, float] | None:
    """:func:`dpcn_med.quality.signals` of a CSV row."""
    finite = lambda value: None if math.isnan(value) else value  # noqa: E731
    return signals(row["confidence"], row["overlap"], {"refined": finite(row["mi_refined"]),
                                                       "dpc": finite(row["mi_dpc"])},
                   finite(row["fixed_entropy"]), json.loads(row["candidate_metrics"]))


def success(row: dict) -> bool:
    return row["group"] not in DELIBERATE and row["tre_mm"] < SUCCESS_MM


def choose_threshold(probabilities: np.ndarray, successes: np.ndarray, max_flagged: float) -> float:
    """The threshold (flag below it) that flags the most failures while flagging at most ``max_flagged`` of the
    ``successes``, placed midway, in log-odds, between the highest failure it flags and the lowest success it spares:
    on data that separate, the widest margin either way."""
    ranked = np.sort(probabilities[successes])
    lowest_spared = ranked[min(int(math.floor(max_flagged * len(ranked))), len(ranked) - 1)]
    flagged = probabilities[~successes & (probabilities < lowest_spared)]
    if not len(flagged):
        return float(lowest_spared)
    logit = lambda p: math.log(max(p, 1e-12) / max(1 - p, 1e-12))  # noqa: E731
    middle = 0.5 * (logit(float(flagged.max())) + logit(float(lowest_spared)))
    return 1.0 / (1.0 + math.exp(-middle))


def fitted_model(rows: list[dict], names: tuple[str, ...], penalty: float, max_flagged: float) -> QualityModel:
    """The model of ``names`` fitted on ``rows`` (with ``signals``), its threshold chosen on them."""
    mean, scale, coefficients, intercept = fit([row["signals"] for row in rows], [success(row) for row in rows], names,
                                               penalty)
    model = QualityModel(names=names, mean=mean, scale=scale, coefficients=coefficients, intercept=intercept,
                         threshold=0.5)
    probabilities = np.array([model.probability(row["signals"]) for row in rows])
    threshold = choose_threshold(probabilities, np.array([success(row) for row in rows]), max_flagged)
    return dataclasses.replace(model, threshold=threshold)


def held_out_pairs(rows: list[dict], penalty: float, max_flagged: float) -> str:
    """Each set of :data:`COMPARED` signals, fitted with each fit pair held out in turn and judged on it: the markdown
    table."""
    lines = ["| signals | successes flagged | failures flagged | log loss |", "|---|---|---|---|"]
    pairs = sorted({row["pair"] for row in rows})
    for names in COMPARED:
        flagged_good = flagged_bad = good = bad = 0
        losses = []
        for held in pairs:
            model = fitted_model([row for row in rows if row["pair"] != held], names, penalty, max_flagged)
            for row in (row for row in rows if row["pair"] == held):
                p = min(max(model.probability(row["signals"]), 1e-6), 1 - 1e-6)
                losses.append(-math.log(p if success(row) else 1 - p))
                if success(row):
                    good, flagged_good = good + 1, flagged_good + (p < model.threshold)
                else:
                    bad, flagged_bad = bad + 1, flagged_bad + (p < model.threshold)
        lines.append(f"| {', '.join(names)} | {flagged_good} of {good} | {flagged_bad} of {bad} | "
                     f"{np.mean(losses):.3f} |")
    return "\n".join(lines)


def evaluate(rows: list[dict], model: QualityModel) -> str:
    """The check's markdown: flagged shares per split and group, and the calibration table by probability band."""
    lines = ["| split | group | registrations | successes flagged | failures flagged |", "|---|---|---|---|---|"]
    for split in ("fit", "check"):
        for group in dict.fromkeys(row["group"] for row in rows):
            chosen = [row for row in rows if row["split"] == split and row["group"] == group]
            if not chosen:
                continue
            good = [row for row in chosen if success(row)]
            bad = [row for row in chosen if not success(row)]

            def flagged(subset: list[dict]) -> str:
                if not subset:
                    return "–"
                count = sum(row["probability"] < model.threshold for row in subset)
                return f"{count} of {len(subset)}"

            lines.append(f"| {split} | {group} | {len(chosen)} | {flagged(good)} | {flagged(bad)} |")
    checked = [row for row in rows if row["split"] == "check" and row["group"] != "mirrored"]
    bands = [(0.0, 0.1), (0.1, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 0.9), (0.9, 1.0001)]
    calibration = ["| predicted probability | registrations | mean predicted | observed success |", "|---|---|---|---|"]
    for low, high in bands:
        inside = [row for row in checked if low <= row["probability"] < high]
        if inside:
            calibration.append(f"| {low:.1f}-{min(high, 1):.1f} | {len(inside)} | "
                               f"{np.mean([row['probability'] for row in inside]):.2f} | "
                               f"{np.mean([success(row) for row in inside]):.2f} |")
    return "\n".join(lines) + "\n\nCalibration on the check pairs (mirrored heads left out):\n\n" + "\n".join(calibration)


def reliability_figure(rows: list[dict], path: Path) -> None:
    """Observed success against predicted probability, in five bands, fit and check pairs apart."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(4.5, 4.2))
    edges = np.linspace(0, 1, 6)
    for split, marker in (("fit", "o"), ("check", "s")):
        chosen = [row for row in rows if row["split"] == split and row["group"] != "mirrored"]
        p = np.array([row["probability"] for row in chosen])
        y = np.array([success(row) for row in chosen])
        band = np.clip(np.digitize(p, edges) - 1, 0, 4)
        points = [(p[band == k].mean(), y[band == k].mean(), (band == k).sum()) for k in range(5) if (band == k).any()]
        axes.plot([a for a, _, _ in points], [b for _, b, _ in points], marker=marker, label=f"{split} pairs")
        for a, b, n in points:
            axes.annotate(str(n), (a, b), textcoords="offset points", xytext=(4, -10), fontsize=7)
    axes.plot([0, 1], [0, 1], color="grey", linestyle=":", label="perfect calibration")
    axes.set(xlabel="predicted probability of success", ylabel="observed share of successes", xlim=(0, 1),
             ylim=(-0.02, 1.02), title="Reliability of the quality model")
    axes.legend(loc="upper left", fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("csv", type=Path, nargs="?", help="the registrations (fit mode)")
    parser.add_argument("--collect", action="store_true", help="register the cases and write the CSV (--output)")
    parser.add_argument("--trials", type=count_type(), default=8, help="poses per case with a right answer")
    parser.add_argument("--deliberate-trials", type=count_type(), default=6, help="poses per deliberate failure")
    parser.add_argument("--seed", type=count_type(0), default=0)
    parser.add_argument("--max-flagged-successes", type=float, default=0.0,
                        help="the threshold flags at most this share of the fit pairs' successes")
    parser.add_argument("--penalty", type=float, default=0.1, help="the fit's ridge penalty")
    parser.add_argument("--write-model", action="store_true", help=f"write the fitted model to {MODEL_PATH}")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.collect:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        collect(args.trials, args.deliberate_trials, args.seed, args.output)
        return 0
    if args.csv is None:
        parser.error("give the registrations' CSV, or --collect")
    rows = read_unique_rows([args.csv], FIELDS, key=lambda row: (row["group"], row["pair"], row["trial"]),
                            shown=lambda row: f"{row['group']} {row['pair']} #{row['trial']}")
    usable = [dict(row, signals=row_signals(row)) for row in rows]
    usable = [row for row in usable if row["signals"] is not None]
    training = [row for row in usable if row["split"] == "fit"]
    command = generated_by(__file__, argv)
    model = fitted_model(training, MODEL_SIGNALS, args.penalty, args.max_flagged_successes)
    model = dataclasses.replace(model, fitted={
        "by": command, "registrations": len(training), "successes": int(sum(success(row) for row in training)),
        "penalty": args.penalty, "date": time.strftime("%Y-%m-%d")})
    for row in usable:
        row["probability"] = model.probability(row["signals"])
    if args.write_model:
        model.save(MODEL_PATH)
    figure = args.output.with_suffix(".png")
    reliability_figure(usable, figure)
    weights = ", ".join(f"{name} {value:+.2f}" for name, value in zip(model.names, model.coefficients))
    text = (f"# The quality model: fit and check\n\n{command}: a logistic model of {', '.join(model.names)} "
            f"(standardised; coefficients {weights}, intercept {model.intercept:+.2f}, ridge penalty {args.penalty:g}), "
            f"fitted on the `fit` pairs ({len(training)} registrations); threshold {model.threshold:.3f}, midway in "
            f"log-odds between the fit pairs' highest flagged failure and lowest spared success (at most "
            f"{args.max_flagged_successes:.0%} of those successes flagged); checked on the `check` pairs, which share "
            f"no pair of volumes with the fit. Success is a TRE under {SUCCESS_MM:g} mm; deliberate failures and "
            f"mirrored heads have no right answer, so every one counts as a failure. "
            f"{len(rows) - len(usable)} registration(s) without a final similarity are left out.\n\n"
            f"![reliability]({figure.name})\n\n{evaluate(usable, model)}\n\n"
            "Which signals: each set fitted with one fit pair held out in turn (six pairs: three with right answers, "
            "three deliberate failures), judged on the pair held out:\n\n"
            f"{held_out_pairs(training, args.penalty, args.max_flagged_successes)}\n")
    return publish(text, args.output)


if __name__ == "__main__":
    sys.exit(main())
