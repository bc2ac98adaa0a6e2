"""A benchmark run: every method on every pose of every case, timed and scored, in one process."""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med.benchmark.cases import CASES, rotation_in_bin
from dpcn_med.benchmark.config import BenchmarkConfig
from dpcn_med.benchmark.memory import reset_peak_rss, status_mib
from dpcn_med.benchmark.methods import DPCN_METHODS, METHODS, available_methods
from dpcn_med.benchmark.results import Journal
from dpcn_med.errors import InputError
from dpcn_med.evaluation import foreground_corners, moved_copy, rotation_error, target_registration_error
from dpcn_med.preprocess import foreground_box, pair_grids, prepare
from dpcn_med.solver.config import DEFAULT_BANDWIDTH


def run_benchmark(config: BenchmarkConfig, progress: Callable[[str], None] | None = None,
                  showcase: dict | None = None, *, skip_missing: bool = False, journal: Journal | None = None
                  ) -> list[dict]:
    """Every method on every pair: one row per (case, bin, trial, method) with TRE (mm), seconds and peak MiB.

    Args:
        config: what to register.
        progress: receives a line per registration (and per method left out, per baseline that raised).
        showcase: when given, receives one dpcn registration to render (:func:`~dpcn_med.benchmark.write_outputs`):
            the first heterogeneous case's (else the first case's) first pose in the largest-rotation bin, as
            ``case``, ``bin``, ``fixed``, ``moving`` and ``estimate``.
        skip_missing: leave out (and report through ``progress``) the methods whose packages are not installed,
            rather than refusing them.
        journal: when given, receives every registration as it finishes, and those it already holds are not
            registered again.

    Returns:
        The rows, keyed as :data:`~dpcn_med.benchmark.RESULT_FIELDS`, case after case, bin after bin, trial after
        trial, method after method.

    Raises:
        InputError: an unknown or repeated case, method or bin; a method whose package is missing; no case; fewer
            than one trial; a journal of other settings (:meth:`Journal.rows`).
    """
    methods = _methods_to_run(config, progress, skip_missing)
    shown = next((case for case in config.cases if not CASES[case][1]), config.cases[0])
    earlier = journal.rows() if journal is not None else {}
    if earlier and progress is not None:
        progress(f"going on from {journal.path}: {len(earlier)} registration(s) of an interrupted run")
    folder = Path(tempfile.mkdtemp(prefix="dpcn-med-benchmark-"))
    run = _Run(config, methods, progress, showcase, shown, earlier, journal, folder)
    try:
        for case in config.cases:
            _run_case(run, case)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return run.rows


def _methods_to_run(config: BenchmarkConfig, progress: Callable[[str], None] | None, skip_missing: bool
                    ) -> tuple[str, ...]:
    """The installed methods of ``config`` (every installed one when it names none), its names checked.

    Raises:
        InputError: as :func:`run_benchmark`, but for the journal.
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
    return tuple(name for name in methods if name in installed)


@dataclass
class _Run:
    """What every registration of one :func:`run_benchmark` call shares, and the rows so far.

    Attributes:
        config, methods, progress, showcase, journal: as :func:`run_benchmark` takes them (``methods`` checked).
        shown: the case whose pose is the showcase.
        earlier: the journal's registrations, by ``(case, bin, trial, method)``.
        folder: the methods' scratch folder.
        rows: the rows so far, in :func:`run_benchmark`'s order.
    """

    config: BenchmarkConfig
    methods: tuple[str, ...]
    progress: Callable[[str], None] | None
    showcase: dict | None
    shown: str
    earlier: dict[tuple[str, str, int, str], dict]
    journal: Journal | None
    folder: Path
    rows: list[dict] = field(default_factory=list)


def _run_case(run: _Run, case: str) -> None:
    """Every pose of ``case``: one random stream per case, drawn bin after bin, ``trials`` poses each (a skipped
    bin's poses are drawn too, so the others stay the same)."""
    config = run.config
    fixed, moving_whole = CASES[case][2]()
    corners, centre = foreground_corners(fixed), foreground_box(fixed)[0]
    canonical = canonical_voxel(fixed, moving_whole)
    rng = np.random.default_rng([config.seed, list(CASES).index(case)])
    for low, high in config.bins:
        for trial in range(config.trials):
            truth = rotation_in_bin(rng, low, high, centre, config.max_shift_mm)
            if config.run_bins and f"{low}-{high}" not in config.run_bins:
                continue
            _run_pose(run, case, (low, high), trial, fixed, moving_whole, truth, corners, canonical)


def canonical_voxel(fixed: sitk.Image, moving: sitk.Image) -> tuple[np.ndarray, float]:
    """The fixed canonical grid's centre (LPS mm) and the pair's canonical voxel (mm) at the default bandwidth, as
    :func:`dpcn_med.register` makes them for the pair as stored.

    Measured on the moving volume as stored, not as turned: a turned volume's foreground box, and with it the voxel,
    differs a little from pose to pose; one voxel per case keeps the criterion the same for every pose
    (:data:`~dpcn_med.evaluation.SUCCESS_VOXELS` of them).
    """
    fixed_grid, _ = pair_grids(prepare(fixed), prepare(moving), 2 * DEFAULT_BANDWIDTH)
    return np.asarray(fixed_grid.centre), fixed_grid.spacing


def _run_pose(run: _Run, case: str, bin_: tuple[int, int], trial: int, fixed: sitk.Image, moving_whole: sitk.Image,
              truth: sitk.Transform, corners: np.ndarray, canonical: tuple[np.ndarray, float]) -> None:
    """Every method on one pose (those the journal holds taken from it), each row journalled as it comes; the
    criterion of a global estimate is measured at ``canonical`` (:func:`canonical_voxel`)."""
    low, high = bin_
    moving = None
    for method in run.methods:
        key = (case, f"{low}-{high}", trial, method)
        shows = run.showcase is not None and (case, method, trial, (low, high)) == (
            run.shown, "dpcn", 0, run.config.bins[-1])
        if key in run.earlier and not shows:  # the showcase is registered again: its render needs it
            run.rows.append(run.earlier[key])
            continue
        moving = moved_copy(moving_whole, truth) if moving is None else moving
        label = f"{case} {low}-{high} deg #{trial + 1} {method}"
        estimate, seconds, peak = _timed_registration(method, fixed, moving, run.folder, run.progress, label)
        error = target_registration_error(estimate, truth, corners)
        if shows:
            run.showcase.update(case=case, bin=f"{low}-{high}", fixed=fixed, moving=moving, estimate=estimate)
        run.rows.append({"case": case, "bin": f"{low}-{high}", "trial": trial, "method": method,
                         "tre_mm": error, "seconds": seconds, "peak_mib": peak,
                         "rotation_error_deg": rotation_error(estimate, truth),
                         "centre_error_mm": target_registration_error(estimate, truth, canonical[0][None]),
                         "canonical_voxel_mm": canonical[1]})
        if run.journal is not None:
            run.journal.append(run.rows[-1])
        if run.progress is not None:
            run.progress(f"{label}: {error:.2f} mm, {seconds:.1f} s")


def _timed_registration(method: str, fixed: sitk.Image, moving: sitk.Image, folder: Path,
                        progress: Callable[[str], None] | None, label: str) -> tuple[sitk.Transform, float, float]:
    """``(fixed_to_moving, seconds, peak MiB)`` of one method on one pair; a baseline that raises is scored at the
    starting pose (the identity), saying so through ``progress``; dpcn_med's own methods raise."""
    before = reset_peak_rss()
    started = time.perf_counter()
    try:
        estimate = METHODS[method][2](fixed, moving, folder)
    except Exception as failure:  # a tool's own error ("outside moving image buffer"), not ours
        if method in DPCN_METHODS:
            raise
        # It gave up: the volumes stay where they were, and the pose counts as a failure instead of stopping the run
        # at the same pose on every rerun.
        estimate = sitk.Transform(3, sitk.sitkIdentity)
        if progress is not None:
            progress(f"{label}: raised {type(failure).__name__} ({failure}); scored at the starting pose")
    seconds = time.perf_counter() - started
    peak = status_mib("VmHWM") - before if before is not None else float("nan")
    return estimate, seconds, peak
