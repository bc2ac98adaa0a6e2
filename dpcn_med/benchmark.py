"""``dpcn-med benchmark``: dpcn_med against SimpleITK, ANTs and elastix on the same pairs, binned by initial rotation.

Every pair is a real volume and a copy of it (or of another contrast of the same anatomy, aligned voxel for voxel)
moved by a known rigid transform: a rotation by an angle drawn uniformly inside the bin about a uniformly random axis,
and a translation of uniform direction and length up to ``max_shift_mm``. Every method registers the same pairs in
the same process; success is a target registration error under 2 mm over the corners of the fixed foreground's box.

Methods (``METHODS``): dpcn_med learning-free with and without its refinement; SimpleITK Mattes mutual information
(the same multi-resolution optimiser dpcn_med refines with) started from ``CenteredTransformInitializer`` GEOMETRY
or MOMENTS, or from an exhaustive search over Euler angles as in SimpleITK's registration-initialisation notebook;
ANTs ``Rigid``, alone and after its multi-start ``affine_initializer``; elastix's default rigid map. ANTs and elastix
come with the ``benchmark`` extra (``pip install 'dpcn_med[benchmark]'``); a run that asks for them without it is
refused, and the command line's default methods leave them out.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import json
import math
import os
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med import io
from dpcn_med.errors import InputError
from dpcn_med.evaluation import foreground_corners, moved_copy, target_registration_error
from dpcn_med.preprocess import foreground_box, foreground_mask
from dpcn_med.refine import Refinement, refine_transform
from dpcn_med.registration import register

SUCCESS_MM = 2.0
BIN_DEGREES = 30
JOURNAL = "results.partial.jsonl"
"""The output folder's record of an unfinished run (:class:`Journal`); removed once ``results.csv`` holds all of
it."""
SETTINGS = "settings.json"
"""Beside ``results.csv``: the settings its poses follow from (:func:`pose_settings`), which ``--combine`` compares."""
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@dataclass(frozen=True)
class BenchmarkConfig:
    """What to run.

    Attributes:
        cases: keys of :data:`CASES`.
        methods: keys of :data:`METHODS`; every installed one when empty.
        bins: initial-rotation bins in degrees, ``(low, high)``.
        trials: pairs per case and bin.
        max_shift_mm: translation length up to this.
        seed: of the poses.
        run_bins: names (``"90-120"``) of the bins to register, all when empty; a pose follows from the case, the
            seed, the trials and the bins (one random stream per case, drawn bin after bin, ``trials`` poses each),
            so a run split over processes by bin registers the same poses as one run with the same trials.
    """

    cases: tuple[str, ...] = ("mni", "mni-pseudo-ct")
    methods: tuple[str, ...] = ()
    bins: tuple[tuple[int, int], ...] = tuple((low, low + BIN_DEGREES) for low in range(0, 180, BIN_DEGREES))
    trials: int = 1
    max_shift_mm: float = 60.0
    seed: int = 0
    run_bins: tuple[str, ...] = ()


QUICK = BenchmarkConfig(methods=("dpcn", "dpcn-global", "sitk-geometry", "sitk-moments", "sitk-exhaustive",
                                 "ants-rigid", "elastix-rigid"))
"""A few minutes on a CPU: the built-in volumes, one pose per bin, every method but ANTs' multi-start (30 s
a pose on the MNI pairs)."""
FULL = BenchmarkConfig(cases=("mni", "mni-pseudo-ct", "seg3d", "seg3d-pseudo-ct", "t1-flair"), trials=10)
"""The documented run (docs/benchmarks.md): the shared real volumes too, ten poses per bin."""


# ------------------------------------------------------------------------------------------------------------ pairs
def _shared(relative: str) -> sitk.Image:
    path = SHARED_DATA / relative
    if not path.exists():
        raise InputError(f"{path}: not found; this case needs ../shared/data beside the checkout")
    return sitk.ReadImage(str(path))


def _seg3d_pseudo_ct() -> tuple[sitk.Image, sitk.Image]:
    from dpcn_med.synth import pseudo_ct

    mr = _shared("seg3d/MR.nii.gz")
    return mr, pseudo_ct(mr, bone=_shared("seg3d/skull_mask.nii.gz"), brain=_shared("seg3d/brain_mask.nii.gz"))


def _mni_pair(moving: str) -> tuple[sitk.Image, sitk.Image]:
    from dpcn_med import samples

    if moving == "mni":
        image = sitk.BinShrink(samples.mni152_t1(), [2, 2, 2])
        return image, image
    return (sitk.BinShrink(samples.mni152_head_t1(), [2, 2, 2]),
            sitk.BinShrink(samples.mni152_pseudo_ct(), [2, 2, 2]))


CASES: dict[str, tuple[str, bool, Callable[[], tuple[sitk.Image, sitk.Image]]]] = {
    "mni": ("MNI152 T1 (2 mm) to itself", True, lambda: _mni_pair("mni")),
    "mni-pseudo-ct": ("MNI152 head T1 to its pseudo-CT (2 mm)", False, lambda: _mni_pair("pseudo-ct")),
    "seg3d": ("seg3d head T1 to itself", True, lambda: (_shared("seg3d/MR.nii.gz"),) * 2),
    "seg3d-pseudo-ct": ("seg3d head T1 to its pseudo-CT", False, _seg3d_pseudo_ct),
    "t1-flair": ("stroke T1 to FLAIR", False, lambda: (_shared("stroke/T1.nii.gz"), _shared("stroke/FLAIR.nii.gz"))),
}
"""name: (description, homogeneous, loader of the aligned ``(fixed, moving)`` images)."""


def rotation_in_bin(rng: np.random.Generator, low: float, high: float, centre: np.ndarray,
                    max_shift_mm: float) -> sitk.VersorRigid3DTransform:
    """A fixed-to-moving rigid transform about ``centre``: angle uniform in ``[low, high)`` degrees about a uniform
    axis, shift of uniform direction and length up to ``max_shift_mm``."""
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    transform = sitk.VersorRigid3DTransform()
    transform.SetCenter(centre.tolist())
    transform.SetRotation((axis / np.linalg.norm(axis)).tolist(), math.radians(rng.uniform(low, high)))
    transform.SetTranslation((direction / np.linalg.norm(direction) * rng.uniform(0, max_shift_mm)).tolist())
    return transform


# ---------------------------------------------------------------------------------------------------------- methods
BASELINE_REFINEMENT = Refinement(max_step_mm=2.0)
"""The SimpleITK baselines' local optimiser: dpcn_med's refinement as one SimpleITK run, every level's first step
2 mm, as measured in docs/benchmarks.md (dpcn_med's own default first step changed after, to 4 mm)."""


def _mask(fixed: sitk.Image) -> sitk.Image:
    return sitk.BinaryDilate(foreground_mask(fixed), [Refinement().mask_margin_voxels] * 3)


def _sitk_initialised(kind: int) -> Callable[[sitk.Image, sitk.Image, Path], sitk.Transform]:
    def run(fixed: sitk.Image, moving: sitk.Image, folder: Path) -> sitk.Transform:
        fixed, moving = sitk.Cast(fixed, sitk.sitkFloat32), sitk.Cast(moving, sitk.sitkFloat32)
        start = sitk.CenteredTransformInitializer(fixed, moving, sitk.VersorRigid3DTransform(), kind)
        return refine_transform(fixed, moving, start, (_mask(fixed), None), BASELINE_REFINEMENT)
    return run


def _sitk_exhaustive(fixed: sitk.Image, moving: sitk.Image, folder: Path) -> sitk.Transform:
    """Mattes MI over a grid of Euler angles (45-degree steps, 4x shrunk), then the local optimiser from the best."""
    fixed, moving = sitk.Cast(fixed, sitk.sitkFloat32), sitk.Cast(moving, sitk.sitkFloat32)
    start = sitk.CenteredTransformInitializer(fixed, moving, sitk.Euler3DTransform(),
                                              sitk.CenteredTransformInitializerFilter.GEOMETRY)
    method = sitk.ImageRegistrationMethod()
    method.SetMetricAsMattesMutualInformation(32)
    method.SetMetricSamplingStrategy(method.RANDOM)
    # The baselines' seed, not 0: SimpleITK takes 0 for the wall clock, a new sample (and result) on every run.
    method.SetMetricSamplingPercentage(0.05, BASELINE_REFINEMENT.seed)
    method.SetInterpolator(sitk.sitkLinear)
    method.SetShrinkFactorsPerLevel([4])
    method.SetSmoothingSigmasPerLevel([2.0])
    method.SmoothingSigmasAreSpecifiedInPhysicalUnitsOn()
    method.SetOptimizerAsExhaustive(numberOfSteps=[4, 2, 4, 0, 0, 0], stepLength=math.pi / 4)
    method.SetOptimizerScales([1, 1, 1, 1, 1, 1])
    method.SetInitialTransform(start, inPlace=True)
    method.Execute(fixed, moving)
    rigid = sitk.VersorRigid3DTransform()
    rigid.SetCenter(start.GetCenter())
    rigid.SetMatrix(start.GetMatrix())
    rigid.SetTranslation(start.GetTranslation())
    return refine_transform(fixed, moving, rigid, (_mask(fixed), None), BASELINE_REFINEMENT)


def _dpcn(refine: bool) -> Callable[[sitk.Image, sitk.Image, Path], sitk.Transform]:
    def run(fixed: sitk.Image, moving: sitk.Image, folder: Path) -> sitk.Transform:
        return register(fixed, moving, refine=refine).fixed_to_moving
    return run


def _ants(multistart: bool) -> Callable[[sitk.Image, sitk.Image, Path], sitk.Transform]:
    def run(fixed: sitk.Image, moving: sitk.Image, folder: Path) -> sitk.Transform:
        import ants

        sitk.WriteImage(fixed, str(folder / "fixed.nii.gz"))
        sitk.WriteImage(moving, str(folder / "moving.nii.gz"))
        fixed_ants = ants.image_read(str(folder / "fixed.nii.gz"))
        moving_ants = ants.image_read(str(folder / "moving.nii.gz"))
        options = {"outprefix": str(folder / "ants_")}
        if multistart:
            options["initial_transform"] = ants.affine_initializer(fixed_ants, moving_ants,
                                                                   txfn=str(folder / "initial.mat"))
        result = ants.registration(fixed_ants, moving_ants, type_of_transform="Rigid", **options)
        # ANTs' forward transforms map fixed points to moving ones (ITK's direction); the last is the rigid one.
        return sitk.ReadTransform(result["fwdtransforms"][-1])
    return run


def _elastix(fixed: sitk.Image, moving: sitk.Image, folder: Path) -> sitk.Transform:
    import itk

    sitk.WriteImage(fixed, str(folder / "fixed.nii.gz"))
    sitk.WriteImage(moving, str(folder / "moving.nii.gz"))
    parameters = itk.ParameterObject.New()
    parameters.AddParameterMap(parameters.GetDefaultParameterMap("rigid"))
    _, result = itk.elastix_registration_method(itk.imread(str(folder / "fixed.nii.gz"), itk.F),
                                                itk.imread(str(folder / "moving.nii.gz"), itk.F),
                                                parameter_object=parameters, log_to_console=False,
                                                output_directory=str(folder))
    found = result.GetParameterMap(0)
    values = [float(v) for v in found["TransformParameters"]]
    # elastix's EulerTransform maps fixed points to moving ones: angles (x, y, z) in radians, then the translation.
    transform = sitk.Euler3DTransform()
    transform.SetCenter([float(v) for v in found["CenterOfRotationPoint"]])
    transform.SetComputeZYX(found["ComputeZYX"][0] == "true" if "ComputeZYX" in found else False)
    transform.SetRotation(*values[:3])
    transform.SetTranslation(values[3:])
    return transform


DPCN_METHODS = ("dpcn", "dpcn-global")
"""dpcn_med's own methods: an error of theirs stops the run (a bug to see), where a baseline's scores a failure."""

METHODS: dict[str, tuple[str, str | None, Callable[[sitk.Image, sitk.Image, Path], sitk.Transform]]] = {
    "dpcn": ("dpcn_med learning-free + refinement (defaults)", None, _dpcn(True)),
    "dpcn-global": ("dpcn_med learning-free, global estimate only", None, _dpcn(False)),
    "sitk-geometry": ("SimpleITK MI from GEOMETRY initialiser", None,
                      _sitk_initialised(sitk.CenteredTransformInitializerFilter.GEOMETRY)),
    "sitk-moments": ("SimpleITK MI from MOMENTS initialiser", None,
                     _sitk_initialised(sitk.CenteredTransformInitializerFilter.MOMENTS)),
    "sitk-exhaustive": ("SimpleITK MI after an exhaustive Euler-angle search", None, _sitk_exhaustive),
    "ants-rigid": ("ANTs Rigid", "antspyx", _ants(False)),
    "ants-multistart": ("ANTs Rigid after affine_initializer", "antspyx", _ants(True)),
    "elastix-rigid": ("elastix rigid (default map)", "itk-elastix", _elastix),
}
"""name: (description, distribution it needs beyond dpcn_med's, ``(fixed, moving, folder) -> fixed_to_moving``)."""


def available_methods() -> tuple[str, ...]:
    """The methods whose packages are installed."""
    from importlib.metadata import PackageNotFoundError, version

    def installed(distribution: str | None) -> bool:
        if distribution is None:
            return True
        try:
            version(distribution)
        except PackageNotFoundError:
            return False
        return True

    return tuple(name for name, (_, distribution, _) in METHODS.items() if installed(distribution))


# ------------------------------------------------------------------------------------------------------ measuring
@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``, ``None`` where the C library has none (macOS, musl, Windows)."""
    name = ctypes.util.find_library("c")
    try:
        return getattr(ctypes.CDLL(name), "malloc_trim", None) if name else None
    except OSError:
        return None


def reset_peak_rss() -> float | None:
    """Reset this process's resident-set high-water mark (Linux ``clear_refs``) and return the current RSS in MiB;
    ``None`` where the system does not offer it. Loading inputs often peaks higher than the call measured after it,
    so without the reset the peak would say nothing about that call.

    The C heap's free pages are handed back to the system first (glibc ``malloc_trim``, where there is one): heap
    that an earlier call freed stays resident, and a later call reusing it would not grow the RSS, so its peak would
    depend on which methods ran before it in the process."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return status_mib("VmRSS")
    except OSError:
        return None


def status_mib(field: str) -> float:
    """A memory line of ``/proc/self/status`` (``VmRSS``, ``VmHWM``) in MiB.

    Raises:
        OSError: no such file or line (not Linux).
    """
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise OSError(f"/proc/self/status has no {field} line")


def run_benchmark(config: BenchmarkConfig, progress: Callable[[str], None] | None = None,
                  showcase: dict | None = None, *, skip_missing: bool = False, journal: Journal | None = None
                  ) -> list[dict]:
    """Every method on every pair: one row per (case, bin, trial, method) with TRE (mm), seconds and peak MiB.

    ``showcase``, when given, receives one dpcn registration to render (:func:`write_outputs`): the first
    heterogeneous case's (else the first case's) first pose in the largest-rotation bin, as ``case``, ``bin``,
    ``fixed``, ``moving`` and ``estimate``. ``skip_missing`` leaves out (and reports through ``progress``) the methods
    whose packages are not installed, rather than refusing them. ``journal``, when given, receives every
    registration as it finishes, and those it already holds are not registered again.

    Raises:
        InputError: an unknown or repeated case, method or bin; a method whose package is missing; no case; fewer
            than one trial; a journal of other settings (:meth:`Journal.rows`).
    """
    installed = available_methods()
    methods = config.methods or installed
    bins = [f"{low}-{high}" for low, high in config.bins]
    for kind, names, known in (("case", config.cases, CASES), ("method", methods, METHODS),
                               ("bin", config.run_bins, bins)):
        unknown = [name for name in names if name not in known]
        if unknown:
            raise InputError(f"unknown {kind} {', '.join(unknown)}; use one of {', '.join(known)}")
        repeated = [name for name in dict.fromkeys(names) if names.count(name) > 1]
        if repeated:
            raise InputError(f"{kind} {', '.join(repeated)} given more than once")
    if not config.cases or config.trials < 1:
        raise InputError(f"nothing to register: {len(config.cases)} case(s), {config.trials} trial(s) per bin; give at "
                         "least one of each")
    missing = [f"{name} needs {METHODS[name][1]}" for name in methods if name not in installed]
    if missing and not skip_missing:
        raise InputError(f"{'; '.join(missing)} (pip install 'dpcn_med[benchmark]')")
    if missing and progress is not None:
        progress(f"left out: {'; '.join(missing)} (pip install 'dpcn_med[benchmark]')")
    methods = tuple(name for name in methods if name in installed)
    shown = next((case for case in config.cases if not CASES[case][1]), config.cases[0])
    earlier = journal.rows() if journal is not None else {}
    if earlier and progress is not None:
        progress(f"going on from {journal.path}: {len(earlier)} registration(s) of an interrupted run")
    rows = []
    folder = Path(tempfile.mkdtemp(prefix="dpcn-med-benchmark-"))
    try:
        for case in config.cases:
            fixed, moving_whole = CASES[case][2]()
            corners, centre = foreground_corners(fixed), foreground_box(fixed)[0]
            rng = np.random.default_rng([config.seed, list(CASES).index(case)])
            for low, high in config.bins:
                for trial in range(config.trials):
                    truth = rotation_in_bin(rng, low, high, centre, config.max_shift_mm)
                    if config.run_bins and f"{low}-{high}" not in config.run_bins:
                        continue
                    moving = None
                    for method in methods:
                        key = (case, f"{low}-{high}", trial, method)
                        shows = showcase is not None and (case, method, trial, (low, high)) == (
                            shown, "dpcn", 0, config.bins[-1])
                        if key in earlier and not shows:  # the showcase is registered again: its render needs it
                            rows.append(earlier[key])
                            continue
                        moving = moved_copy(moving_whole, truth) if moving is None else moving
                        before = reset_peak_rss()
                        started = time.perf_counter()
                        try:
                            estimate = METHODS[method][2](fixed, moving, folder)
                        except Exception as failure:  # a tool's own error ("outside moving image buffer"), not ours
                            if method in DPCN_METHODS:
                                raise
                            # It gave up: the volumes stay where they were, and the pose counts as a failure instead
                            # of stopping the run at the same pose on every rerun.
                            estimate = sitk.Transform(3, sitk.sitkIdentity)
                            if progress is not None:
                                progress(f"{case} {low}-{high} deg #{trial + 1} {method}: raised "
                                         f"{type(failure).__name__} ({failure}); scored at the starting pose")
                        seconds = time.perf_counter() - started
                        peak = status_mib("VmHWM") - before if before is not None else float("nan")
                        error = target_registration_error(estimate, truth, corners)
                        if shows:
                            showcase.update(case=case, bin=f"{low}-{high}", fixed=fixed, moving=moving,
                                            estimate=estimate)
                        rows.append({"case": case, "bin": f"{low}-{high}", "trial": trial, "method": method,
                                     "tre_mm": error, "seconds": seconds, "peak_mib": peak})
                        if journal is not None:
                            journal.append(rows[-1])
                        if progress is not None:
                            progress(f"{case} {low}-{high} deg #{trial + 1} {method}: {error:.2f} mm, {seconds:.1f} s")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return rows


class Journal:
    """The registrations of a run so far, one JSON object a line, so an interrupted run goes on where it stopped.

    The first line holds the settings that fix the poses (seed, trials, bins, largest shift) and the version; a run
    with other settings is refused rather than mixed in. Each registration is appended and flushed to disk as it
    finishes; a last line cut by the interruption is dropped.
    """

    def __init__(self, path: str | os.PathLike, config: BenchmarkConfig) -> None:
        from dpcn_med import __version__

        self.path = Path(path)
        self.settings = {"version": __version__, **pose_settings(config)}

    def rows(self) -> dict[tuple[str, str, int, str], dict]:
        """The registrations written so far, by ``(case, bin, trial, method)`` (a later line wins).

        Raises:
            InputError: the file is not a journal, was written with other settings, or holds a malformed row.
        """
        if not self.path.exists():
            return {}
        lines = io.read_text(self.path).split("\n")
        complete = lines[:-1]  # text after the last line end was cut by the interruption
        if not complete:  # empty, or its settings line cut: nothing registered yet (append writes them again)
            return {}
        try:
            settings = json.loads(complete[0])["settings"]
        except (json.JSONDecodeError, KeyError, TypeError):
            raise InputError(f"{self.path}: not a journal of dpcn-med benchmark (its first line holds no settings); "
                             "move it away, or choose another output folder") from None
        if settings != self.settings:
            raise InputError(f"{self.path}: holds an interrupted run with other settings ({settings}, this run "
                             f"{self.settings}); rerun with that run's options, or choose another output folder")
        found: dict[tuple[str, str, int, str], dict] = {}
        for line, text in enumerate(complete[1:], start=2):
            try:
                record = json.loads(text)
                row = {field: kind(record[field]) for field, kind in RESULT_FIELDS.items()}
            except (json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
                raise InputError(f"{self.path}: line {line}: not a registration ({type(error).__name__}: {error})"
                                 ) from None
            found[_checked_row(row, self.path, line)] = row
        return found

    def append(self, row: dict) -> None:
        """Append ``row`` (one of :data:`RESULT_FIELDS`), starting the file with the settings if it is new."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a+b") as stream:
            stream.seek(0)
            text = stream.read()
            if not text.endswith(b"\n"):  # cut by an interruption: drop the partial line
                text = text[:text.rfind(b"\n") + 1]
                stream.truncate(len(text))
            if not text:  # new, or its settings line was cut
                stream.write((json.dumps({"settings": self.settings}) + "\n").encode())
            stream.write((json.dumps({field: row[field] for field in RESULT_FIELDS}) + "\n").encode())
            stream.flush()
            os.fsync(stream.fileno())


def pose_settings(config: BenchmarkConfig) -> dict:
    """The settings a run's poses follow from, besides the case: seed, trials, largest shift and bins."""
    return {"seed": config.seed, "trials": config.trials, "max_shift_mm": config.max_shift_mm,
            "bins": [f"{low}-{high}" for low, high in config.bins]}


def summarise(rows: list[dict]) -> list[dict]:
    """Per (case, method, bin): trials, success rate, median TRE, median seconds, median peak MiB."""
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["case"], row["method"], row["bin"]), []).append(row)
    return [{"case": case, "method": method, "bin": bin_, "trials": len(group),
             "success": sum(r["tre_mm"] < SUCCESS_MM for r in group) / len(group),
             "median_tre_mm": statistics.median(r["tre_mm"] for r in group),
             "median_seconds": statistics.median(r["seconds"] for r in group),
             "median_peak_mib": statistics.median(r["peak_mib"] for r in group)}
            for (case, method, bin_), group in groups.items()]


def markdown(rows: list[dict], config: BenchmarkConfig) -> str:
    """Tables per case: success by rotation bin for every method, then the medians over all its registrations of
    the case (not of the bins' medians, which weigh a bin of one pose like one of ten) of TRE, seconds and peak MiB."""
    bins = [f"{low}-{high}" for low, high in config.bins]
    success = {(r["case"], r["method"], r["bin"]): r["success"] for r in summarise(rows)}
    lines = []
    for case in dict.fromkeys(r["case"] for r in rows):
        lines += [f"### {CASES[case][0]}", "",
                  "| method | " + " | ".join(f"{b} deg" for b in bins)
                  + " | median TRE (mm) | median s | median peak MiB |",
                  "|---|" + "---|" * (len(bins) + 3)]
        for method in dict.fromkeys(r["method"] for r in rows):
            mine = [r for r in rows if (r["case"], r["method"]) == (case, method)]
            if not mine:
                continue
            lines.append(f"| {METHODS[method][0]} | "
                         + " | ".join(f"{100 * success[(case, method, b)]:.0f}%" if (case, method, b) in success
                                      else "-" for b in bins)
                         + f" | {statistics.median(r['tre_mm'] for r in mine):.2f}"
                         + f" | {statistics.median(r['seconds'] for r in mine):.1f}"
                         + f" | {statistics.median(r['peak_mib'] for r in mine):.0f} |")
        lines.append("")
    return "\n".join(lines)


def figure(summary: list[dict], config: BenchmarkConfig, path: Path) -> None:
    """Success rate against initial rotation, one panel per case, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dpcn_med import io

    cases = list(dict.fromkeys(r["case"] for r in summary))
    centres = [(low + high) / 2 for low, high in config.bins]
    bins = [f"{low}-{high}" for low, high in config.bins]
    figure_, axes = plt.subplots(1, len(cases), figsize=(4.5 * len(cases), 4.2), squeeze=False,
                                 constrained_layout=True)
    for ax, case in zip(axes[0], cases):
        for method in dict.fromkeys(r["method"] for r in summary):
            cells = {r["bin"]: r for r in summary if r["case"] == case and r["method"] == method}
            ax.plot(centres, [100 * cells[b]["success"] if b in cells else np.nan for b in bins], "o-",
                    label=METHODS[method][0], lw=2.5 if method == "dpcn" else 1.2)
        ax.set(title=CASES[case][0], xlabel="initial rotation (deg)", ylabel=f"success (TRE < {SUCCESS_MM:g} mm), %",
               ylim=(-5, 105), xticks=[b[0] for b in config.bins] + [config.bins[-1][1]])
    # Below the panels: inside one, eight methods' labels hide its curves.
    figure_.legend(*axes[0][0].get_legend_handles_labels(), loc="outside lower center", ncols=4, fontsize=7)
    with io.atomic_output(path) as staged:
        figure_.savefig(staged, dpi=110)
    plt.close(figure_)


def write_outputs(rows: list[dict], config: BenchmarkConfig, output: str | os.PathLike, *, command: str,
                  showcase: dict | None = None, settings: dict | None = None) -> str:
    """``results.csv`` (every registration), ``summary.md`` and ``success.png`` in ``output``, ``render.png``
    (:func:`dpcn_med.render.before_after`) of the ``showcase`` from :func:`run_benchmark` where pyvista is
    installed, and :data:`SETTINGS` holding ``settings`` (:func:`pose_settings`) when given; returns the summary's
    text."""
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    io.write_csv(rows, output / "results.csv")
    if settings is None:
        (output / SETTINGS).unlink(missing_ok=True)  # a run's before, in a folder --combine writes over
    else:
        io.write_json(settings, output / SETTINGS)
    summary = summarise(rows)
    counts = sorted({r["trials"] for r in summary})
    poses = f"{counts[0]}" if len(counts) == 1 else f"{counts[0]}-{counts[-1]}"
    text = (f"# dpcn_med against SimpleITK, ANTs and elastix\n\nGenerated by `{command}` on "
            f"{time.strftime('%Y-%m-%d')}; {poses} pose(s) per case, method and bin, rotation angle uniform in the "
            f"bin about a uniform axis, translation up to {config.max_shift_mm:g} mm; success is a TRE under "
            f"{SUCCESS_MM:g} mm over the fixed foreground's box; medians over every registration of a case and "
            f"method; times on one CPU process; peak memory the resident-set growth during the call, the C heap's "
            f"free pages handed back before it, so it counts the memory the call itself touches.\n\n"
            f"![success against initial rotation](success.png)\n\n" + markdown(rows, config))
    if showcase:
        text += _render(showcase, output / "render.png")
    io.write_text(text, output / "summary.md")
    figure(summary, config, output / "success.png")
    return text


RESULT_FIELDS = {"case": str, "bin": str, "trial": int, "method": str, "tre_mm": float, "seconds": float,
                 "peak_mib": float}
"""Columns of ``results.csv`` and their types (:func:`run_benchmark`'s rows)."""


def combine_results(folders: list[str | os.PathLike]) -> list[dict]:
    """The rows of earlier runs' ``results.csv`` (say, one run per core, split by case or bin), in the folders' order.

    Raises:
        InputError: a missing or malformed file (:func:`dpcn_med.io.read_csv`), an unknown case, method or bin, a
            negative trial, a TRE or time that is negative or not finite, or a registration (case, bin, trial, method)
            found twice.
    """
    rows, seen = [], {}
    for folder in folders:
        path = Path(folder) / "results.csv"
        found = io.read_csv(path, RESULT_FIELDS)
        if found and set(found[0][1]) != set(RESULT_FIELDS):
            raise InputError(f"{path}: not a benchmark's results (columns {', '.join(RESULT_FIELDS)}, no others)")
        for line, row in found:
            key = _checked_row(row, path, line)
            if key in seen:
                raise InputError(f"{path}: line {line}: {', '.join(map(str, key))} is also in {seen[key]}")
            seen[key] = path
            rows.append(row)
    if not rows:
        raise InputError(f"{', '.join(map(str, folders))}: no registrations to combine")
    return rows


def combined_settings(folders: list[str | os.PathLike]) -> dict | None:
    """The settings the poses of earlier runs' ``results.csv`` follow from (their :data:`SETTINGS`), ``None`` where a
    folder has none (runs before it was written).

    Raises:
        InputError: two folders' settings differ (other poses: rows of one pose number would not be the same pose),
            or a settings file that cannot be read.
    """
    found: dict[Path, dict] = {}
    for folder in folders:
        path = Path(folder) / SETTINGS
        if not path.exists():
            continue
        settings = io.read_json(path)
        first, theirs = next(iter(found.items()), (path, settings))  # equal to the first, so to every other
        if settings != theirs:
            raise InputError(f"{path}: other settings than {first} ({settings}, there {theirs}): their poses "
                             "differ; combine runs with the same --seed, --trials and mode only")
        found[path] = settings
    return next(iter(found.values())) if len(found) == len(folders) else None


def _checked_row(row: dict, path: Path, line: int) -> tuple[str, str, int, str]:
    """The key ``(case, bin, trial, method)`` of a row read back from ``path``.

    Raises:
        InputError: an unknown case, method or bin, a negative trial, or a TRE or time that is negative or not finite.
    """
    bins = [f"{low}-{high}" for low, high in BenchmarkConfig().bins]
    if row["case"] not in CASES or row["method"] not in METHODS:
        raise InputError(f"{path}: line {line}: unknown case or method {row['case']!r}, {row['method']!r}")
    if row["bin"] not in bins:
        raise InputError(f"{path}: line {line}: unknown bin {row['bin']!r}; use one of {', '.join(bins)}")
    for field in ("trial", "tre_mm", "seconds"):  # peak_mib may be NaN (no /proc) or slightly negative
        if not (math.isfinite(row[field]) and row[field] >= 0):
            raise InputError(f"{path}: line {line}: {field} {row[field]}; expected a finite number >= 0")
    return row["case"], row["bin"], row["trial"], row["method"]


def _render(showcase: dict, path: Path) -> str:
    """The showcase rendered to ``path``; the summary's paragraph about it."""
    from dpcn_med import render

    what = (f"{CASES[showcase['case']][0]}, a start in the {showcase['bin']} degree bin, registered by dpcn_med with "
            "the command line's defaults")
    try:
        render.before_after(showcase["fixed"], showcase["moving"], showcase["estimate"], path, title=what)
    except InputError as error:  # pyvista is the optional mesh extra
        return f"\n3-D render skipped: {error}\n"
    return (f"\n## Before and after in 3-D\n\n{what}: the fixed volume's foreground in grey, the moving volume's "
            "brightest tissue (bone on a CT) in orange.\n\n![before and after](render.png)\n")
