"""Ultrasound: a simulated intra-operative cone through a craniotomy against the whole MR or CT, from any pose.

Each trial simulates one 3-D ultrasound cone (:func:`dpcn_med.synth.ultrasound_image.ultrasound_image`) from the
held-out seg3d head's pseudo-CT (noise seed 1), through a craniotomy on the upper half of the skull, probe tilted up to
60 degrees from the vertex, with simulator settings of its own (:data:`SIMULATOR`; the draws of training pairs use the
defaults of :class:`dpcn_med.synth.UltrasoundConfig`). The other image is the whole seg3d T1 MR, or the whole
pseudo-CT with another noise seed (0). A random pose moves the moving image exactly
(:func:`dpcn_med.evaluation.moved_copy`): rotation uniform over SO(3), shift up to 30 mm. Each case is one direction:
the cone fixed and the whole volume moving, or the reverse. Success: a target registration error under 3 mm over the
corners of the cone's bounding box, after refinement. ``dpcn_med.register`` runs with the command line's defaults and
the modalities named (``us``, ``mr``, ``ct``); the local baselines of ``dpcn-med benchmark`` (those installed) register
the first ``--baseline-trials`` poses, and a second dpcn_med row gives its results on those poses alone. One more row
(``refine-from-truth``) runs dpcn_med's refinement alone from the true pose: whether its similarity holds the truth
at all, the ceiling of any global estimate. Prints the table and writes it under docs/, with a figure of the first
trial's cone beside the MR there, and the per-pose CSV.

    python benchmarks/ultrasound.py --trials 20 --baseline-trials 5 [--cases us-mr us-ct mr-us ct-us]
        [--methods dpcn sitk-exhaustive ...]
"""

from __future__ import annotations

import argparse
import math
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med.benchmark import METHODS, available_methods
from dpcn_med.evaluation import foreground_corners, moved_copy, random_similarity, target_registration_error
from dpcn_med.geometry import homogeneous_matrix, similarity_transform
from dpcn_med.io import write_csv
from dpcn_med.outputs import RegistrationSettings
from dpcn_med.preprocess import foreground_mask
from dpcn_med.refine import Refinement, choose_and_refine, metric_masks, ultrasound_side
from dpcn_med.registration import register
from dpcn_med.synth import UltrasoundConfig, pseudo_ct
from dpcn_med.synth.ultrasound_image import DYNAMIC_RANGE_DB, Craniotomy, ultrasound_image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
SUCCESS_MM = 3.0
"""The ultrasound acceptance's threshold (the learning issue): a TRE under 3 mm."""
MAX_SHIFT_MM = 30.0
CASES = {  # name: (description, fixed, moving); "us" is the cone, "mr" and "ct" the whole volumes
    "us-mr": ("ultrasound cone (fixed) to the whole seg3d T1 MR (moving)", "us", "mr"),
    "us-ct": ("ultrasound cone (fixed) to the whole seg3d pseudo-CT (moving)", "us", "ct"),
    "mr-us": ("whole seg3d T1 MR (fixed) to the ultrasound cone (moving)", "mr", "us"),
    "ct-us": ("whole seg3d pseudo-CT (fixed) to the ultrasound cone (moving)", "ct", "us"),
}
SIMULATOR = UltrasoundConfig(half_angle_degrees=(25.0, 30.0), depth_range=(0.3, 0.4), impedance_gain=4.0,
                             scatter_gain=0.4, bone_attenuation=80.0)
"""The benchmark's probes and acoustics, each outside the ranges that training draws from (the defaults of
:class:`dpcn_med.synth.UltrasoundConfig`): narrower cones (50-60 degrees across), shallower (about 90-120 mm on the
seg3d head), other gain, scatter and bone absorption."""
CRANIOTOMY_MM = (20.0, 30.0)
"""The opening's radius is drawn uniformly in this range per trial."""
MAX_TILT_DEGREES = 60.0
"""The probe's axis lies within this angle of the head's vertical (LPS -z, looking down from the vertex)."""
BASELINES = ["sitk-geometry", "sitk-moments", "sitk-exhaustive", "ants-rigid", "elastix-rigid"]
SAME_POSES = "dpcn-baseline-poses"
FROM_TRUTH = "refine-from-truth"
"""The method name of the refinement alone, started at the true pose (:func:`refined_from_truth`)."""
ROW_FIELDS = ["case", "trial", "method", "tre_mm", "seconds", "flagged"]


def volumes() -> dict[str, sitk.Image]:
    """The whole volumes, aligned voxel for voxel: ``mr``, ``ct`` (pseudo-CT, noise seed 0) and ``source`` (the
    pseudo-CT the cones are simulated from, noise seed 1)."""
    mr = sitk.ReadImage(str(DATA / "seg3d/MR.nii.gz"))
    masks = {"bone": sitk.ReadImage(str(DATA / "seg3d/skull_mask.nii.gz")),
             "brain": sitk.ReadImage(str(DATA / "seg3d/brain_mask.nii.gz"))}
    return {"mr": mr, "ct": pseudo_ct(mr, seed=0, **masks), "source": pseudo_ct(mr, seed=1, **masks)}


def probe_direction(rng: np.random.Generator) -> np.ndarray:
    """A beam direction (LPS) pointing down into the head, uniform over the cap within :data:`MAX_TILT_DEGREES` of
    -z."""
    cos_tilt = rng.uniform(math.cos(math.radians(MAX_TILT_DEGREES)), 1.0)
    azimuth = rng.uniform(0.0, 2 * math.pi)
    sin_tilt = math.sqrt(1.0 - cos_tilt ** 2)
    return np.array([sin_tilt * math.cos(azimuth), sin_tilt * math.sin(azimuth), -cos_tilt])


def trials(whole: dict[str, sitk.Image], count: int, seed: int):
    """``(trial, cone image, true fixed_to_moving, TRE points)`` per trial, each following from ``seed`` and the
    trial's index alone."""
    for trial in range(count):
        rng = np.random.default_rng([seed, trial])
        direction = probe_direction(rng)
        craniotomy = Craniotomy(radius_mm=float(rng.uniform(*CRANIOTOMY_MM)))
        cone, mask = ultrasound_image(whole["source"], direction.tolist(), seed=int(rng.integers(2 ** 31)),
                                      config=SIMULATOR, craniotomy=craniotomy)
        points = foreground_corners(cone, mask)
        truth = random_similarity(rng, points.mean(0), max_shift_mm=MAX_SHIFT_MM)
        yield trial, cone, truth, points


def refined_from_truth(fixed: sitk.Image, moving: sitk.Image, modalities: tuple[str, str],
                       truth: sitk.Transform) -> sitk.Transform:
    """dpcn_med's refinement (:func:`dpcn_med.refine.choose_and_refine`, the defaults) from ``truth`` alone, with the
    similarity and the masks :func:`dpcn_med.register` uses for these ``(fixed, moving)`` modalities (LC2 on the
    ultrasound's cone)."""
    start = similarity_transform(homogeneous_matrix(truth), np.asarray(truth.GetFixedParameters()[:3]), rigid=True)
    ultrasound = ultrasound_side(*modalities)
    masks = metric_masks(None, foreground_mask(fixed), None, Refinement(), ultrasound=ultrasound)
    return choose_and_refine(fixed, moving, [start], masks, ultrasound=ultrasound).fixed_to_moving


def run(cases: list[str], count: int, seed: int, methods: list[str], baseline_trials: int,
        figure: Path | None) -> list[dict]:
    """One row per case, pose and method: ``case``, ``trial``, ``method``, ``tre_mm``, ``seconds`` and, for dpcn_med
    with its defaults, ``flagged``: whether the command line would exit 3 (likely wrong; ``""`` for the others)."""
    whole = volumes()
    rows = []
    folder = Path(tempfile.mkdtemp(prefix="dpcn-med-ultrasound-"))
    try:
        for trial, cone, truth, points in trials(whole, count, seed):
            if trial == 0 and figure is not None:
                cone_figure(cone, whole["mr"], figure)
            images = {"us": cone, **whole}
            for case in cases:
                _, fixed_name, moving_name = CASES[case]
                fixed, moving = images[fixed_name], moved_copy(images[moving_name], truth)
                for method in methods:
                    if method not in ("dpcn", FROM_TRUTH) and trial >= baseline_trials:
                        continue
                    started = time.perf_counter()
                    flagged = ""
                    if method == "dpcn":
                        result = register(fixed, moving, fixed_modality=fixed_name, moving_modality=moving_name)
                        estimate = result.fixed_to_moving
                        flagged = RegistrationSettings().flagged(result.to_dict())
                    elif method == FROM_TRUTH:
                        estimate = refined_from_truth(fixed, moving, (fixed_name, moving_name), truth)
                    else:
                        try:
                            estimate = METHODS[method][2](fixed, moving, folder)
                        except Exception as failure:  # a tool's own error: scored at the starting pose
                            print(f"{case} #{trial} {method}: raised {type(failure).__name__} ({failure})",
                                  file=sys.stderr)
                            estimate = sitk.Transform(3, sitk.sitkIdentity)
                    rows.append({"case": case, "trial": trial, "method": method,
                                 "tre_mm": target_registration_error(estimate, truth, points),
                                 "seconds": time.perf_counter() - started, "flagged": flagged})
                    print(f"{case} #{trial} {method}: {rows[-1]['tre_mm']:.2f} mm, {rows[-1]['seconds']:.1f} s",
                          file=sys.stderr)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return rows


def cone_figure(cone: sitk.Image, mr: sitk.Image, path: Path) -> None:
    """The cone's three central planes above the MR resampled onto the cone's grid."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arrays = [sitk.GetArrayFromImage(cone), sitk.GetArrayFromImage(sitk.Resample(mr, cone, sitk.Transform(),
                                                                                  sitk.sitkLinear, 0.0))]
    figure, axes = plt.subplots(2, 3, figsize=(9, 6))
    for row, (array, name) in enumerate(zip(arrays, ("simulated ultrasound", "T1 MR, same planes"))):
        for axis, plane in enumerate(("axial", "coronal", "sagittal")):
            axes[row, axis].imshow(np.flipud(array.take(array.shape[axis] // 2, axis=axis)), cmap="gray")
            axes[row, axis].set_title(f"{name}: {plane}", fontsize=8)
            axes[row, axis].axis("off")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)
    plt.close(figure)


def table(rows: list[dict], methods: list[str], baseline_trials: int) -> str:
    """The markdown table: a line per case and method: dpcn_med, its refinement from the truth, dpcn_med on the
    baselines' poses, the baselines."""
    header = (f"| case | method | poses | success (TRE < {SUCCESS_MM:g} mm) | median TRE (mm) | median s | "
              "flagged as likely wrong |")
    lines = [header, "|---|---|---|---|---|---|---|"]
    shown = [("dpcn", "dpcn_med (defaults)")]
    if FROM_TRUTH in methods:
        shown.append((FROM_TRUTH, "dpcn_med's refinement alone, from the true pose"))
    baselines = [m for m in methods if m not in ("dpcn", FROM_TRUTH)]
    if baselines:
        shown.append((SAME_POSES, f"dpcn_med, on the baselines' {baseline_trials} poses"))
    shown += [(m, METHODS[m][0]) for m in baselines]
    for case in dict.fromkeys(r["case"] for r in rows):
        for method, label in shown:
            if method == SAME_POSES:
                chosen = [r for r in rows if r["case"] == case and r["method"] == "dpcn"
                          and r["trial"] < baseline_trials]
            else:
                chosen = [r for r in rows if r["case"] == case and r["method"] == method]
            if not chosen:
                continue
            errors = [r["tre_mm"] for r in chosen]
            success = sum(e < SUCCESS_MM for e in errors)
            flags = [r.get("flagged") for r in chosen if r.get("flagged") not in (None, "")]
            flagged = "" if not flags else f"{sum(flag in (True, 'True') for flag in flags)} of {len(flags)}"
            lines.append(f"| {case} | {label} | {len(chosen)} | {success} of {len(chosen)} "
                         f"({100 * success / len(chosen):.0f}%) | {statistics.median(errors):.1f} | "
                         f"{statistics.median(r['seconds'] for r in chosen):.1f} | {flagged} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    parser.add_argument("--trials", type=count_type(), default=20, help="poses (and cones) per case")
    parser.add_argument("--baseline-trials", type=count_type(0), default=5,
                        help="the baselines run on the first this many poses")
    parser.add_argument("--methods", nargs="+", choices=[*METHODS, FROM_TRUTH],
                        default=["dpcn", FROM_TRUTH, *BASELINES],
                        help=f"{FROM_TRUTH}: dpcn_med's refinement alone from the true pose, on every pose")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "ultrasound.md")
    args = parser.parse_args(argv)
    if not DATA.exists():
        parser.error(f"{DATA}: not found; the ultrasound cases need ../shared/data beside the checkout")
    installed = available_methods()
    methods = ["dpcn"] + [m for m in args.methods if (m in installed or m == FROM_TRUTH) and m != "dpcn"]
    missing = [m for m in args.methods if m not in installed and m != FROM_TRUTH]
    rows = run(args.cases, args.trials, args.seed, methods, min(args.baseline_trials, args.trials),
               args.output.with_suffix(".png"))
    write_csv(rows, args.output.with_suffix(".csv"), ROW_FIELDS)
    settings = ", ".join(f"{key} {value}" for key, value in asdict(SIMULATOR).items())
    text = (f"# Ultrasound cone against the whole MR or CT\n\n{generated_by(__file__, argv)}, one process on this "
            f"machine's CPU. Cases: " + "; ".join(f"`{c}` {CASES[c][0]}" for c in args.cases) + ". "
            f"Rotation uniform over SO(3), shift up to {MAX_SHIFT_MM:g} mm, TRE over the corners of the cone's "
            f"bounding box. Simulator: {settings}; craniotomy radius {CRANIOTOMY_MM[0]:g}-{CRANIOTOMY_MM[1]:g} mm, "
            f"probe within {MAX_TILT_DEGREES:g} degrees of the vertex; echoes log-compressed over "
            f"{DYNAMIC_RANGE_DB:g} dB (B-mode, as a scanner exports them). No model is trained on ultrasound yet: "
            "dpcn_med runs learning-free, and refines with LC2 on the cone (one image is ultrasound)."
            + (f" Not installed, not run: {', '.join(missing)}." if missing else "")
            + "\n\n![the first trial's cone](ultrasound.png)\n\n" + table(rows, methods, args.baseline_trials)
            + f"\nPer pose: [{args.output.with_suffix('.csv').name}]({args.output.with_suffix('.csv').name}).\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
