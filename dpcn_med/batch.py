"""Cohorts: every pair of a pairs file registered into its own folder, with a summary table, resumable.

``plan_batch`` reads the pairs file and checks everything that can be checked before the first registration (ids,
output folders, options, inputs that outputs would overwrite) and finds the pairs an earlier run already answered
(their report.json records the same request). ``run_batch`` registers the rest one after another, or on a Dask
cluster (:mod:`dpcn_med.cluster`), and rewrites ``summary.csv`` after every pair, so an interrupted batch resumes
with the same command.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from dpcn_med import io
from dpcn_med.errors import InputError
from dpcn_med.outputs import (
    OUTPUT_NAMES,
    RegistrationSettings,
    check_output_folder,
    make_folder,
    model_identity,
    refuse_overwriting_inputs,
    register_to_folder,
    registration_request,
)

if TYPE_CHECKING:
    from dpcn_med.registration import Progress

PAIR_COLUMNS = ("id", "fixed", "moving", "fixed_mask", "moving_mask")
"""The columns of a pairs file; fixed and moving are required."""

SUMMARY_COLUMNS = ("id", "status", "success_probability", "confidence", "rotation_deg", "seconds", "message")
"""The columns of summary.csv."""

FAILED = ("bad input", "internal error")
"""The statuses of pairs that have no result: an input error, and any other error."""

_PATHS = ("fixed", "moving", "fixed_mask", "moving_mask")


@dataclass
class PairJob:
    """One pair of a batch.

    Attributes:
        index: 1-based place in the pairs file.
        pair: ``id`` and the input paths (``fixed``, ``moving``, ``fixed_mask``, ``moving_mask``; masks may be None).
        folder: the pair's output folder.
        request: what its report.json must record for an earlier result to be reused.
        earlier: the earlier run's report that answers this request, or ``None``.
        note: why an earlier report in ``folder`` is not reused ("" if none).
    """

    index: int
    pair: dict[str, str | None]
    folder: Path
    request: dict
    earlier: dict | None = None
    note: str = ""

    @property
    def id(self) -> str:
        return self.pair["id"]


@dataclass
class Batch:
    """A checked batch, ready to run.

    Attributes:
        output: the batch's output folder (one folder per pair id, and summary.csv).
        settings: what every registration is asked to do and write.
        jobs: the pairs, in the pairs file's order.
        missing: ``"ID: PATH"`` for each input path that does not exist (those pairs will fail as bad input).
        model: :func:`dpcn_med.outputs.model_identity` of the settings' model, as this machine reads it.
    """

    output: Path
    settings: RegistrationSettings
    jobs: list[PairJob]
    missing: list[str] = field(default_factory=list)
    model: str | dict[str, str] = "none"

    @property
    def summary(self) -> Path:
        return self.output / "summary.csv"

    @property
    def pending(self) -> list[PairJob]:
        """The jobs that no earlier result answers."""
        return [job for job in self.jobs if job.earlier is None]


def read_pairs(path: Path) -> list[dict[str, str | None]]:
    """The pairs of a pairs file.

    Paths are resolved against the file's folder (``~`` is the home folder, as in a shell); a row without an id gets
    ``NNN-STEM`` (its place among the rows and the moving file's name up to its first dot).

    Raises:
        InputError: naming the file and line: a missing path, an unknown column or an extra cell, a NUL character in
            a path, or an id that is repeated (case aside) or is not a folder name (empty, '.', '..', 'summary.csv',
            a slash, a control character, over 255 bytes).
    """
    rows = io.read_csv(path, {"fixed": _path_cell, "moving": _path_cell}, allowed=PAIR_COLUMNS)
    if not rows:
        raise InputError(f"{path}: no pairs (a header row with at least the columns fixed,moving, then a row a pair)")
    pairs, seen = [], {}
    for index, (line, row) in enumerate(rows, start=1):
        pair_id = (row.get("id") or f"{index:03d}-{Path(row['moving']).name.split('.')[0]}").strip()
        _check_pair_id(path, line, pair_id, seen)
        seen[pair_id.casefold()] = (line, pair_id)
        cells = {key: (row.get(key) or "").strip() for key in _PATHS}
        if any("\0" in value for value in cells.values()):
            raise InputError(f"{path}: line {line}: a path holds a NUL character")
        pairs.append({"id": pair_id, **{key: str(path.parent / os.path.expanduser(value)) if value else None
                                        for key, value in cells.items()}})
    return pairs


def _path_cell(value: str | None) -> str:
    """A pairs-file cell that must hold a path (a short row leaves ``None``)."""
    if not value or not value.strip():
        raise ValueError("a fixed or moving path is missing")
    return value.strip()


def _check_pair_id(path: Path, line: int, pair_id: str, seen: dict[str, tuple[int, str]]) -> None:
    if pair_id.casefold() in seen:  # Sub01 and sub01 would share one folder on macOS and Windows
        first_line, first = seen[pair_id.casefold()]
        alike = ("" if first == pair_id
                 else f" ({first!r}: ids that differ only in case share a folder on macOS and Windows)")
        raise InputError(f"{path}: line {line}: id {pair_id!r} is repeated (case aside): line {first_line} has "
                         f"it{alike}; give every pair its own id")
    if (pair_id in ("", ".", "..", "summary.csv") or any(c in pair_id for c in "/\\")
            or any(ord(c) < 32 for c in pair_id) or len(pair_id.encode()) > 255):
        raise InputError(f"{path}: line {line}: id {pair_id!r} is not a folder name inside the output folder "
                         "(empty, '.', '..', 'summary.csv', a slash, a control character, or over 255 bytes)")


def earlier_report(folder: Path, request: dict, outputs: tuple[str, ...]) -> tuple[dict | None, str]:
    """The report.json a finished earlier run left in ``folder`` for this ``request`` and at least these ``outputs``.

    Returns:
        ``(report, "")`` where it answers the request; else ``(None, why)``, ``why`` being "" when there is no
        readable report (the pair is then registered again).
    """
    if not (folder / "report.json").exists():
        return None, ""
    try:
        report = io.read_json(folder / "report.json")
        float(report["confidence"]), float(report["final"]["rotation_degrees"]), float(report["timings_s"]["total"])
    except (InputError, KeyError, TypeError, ValueError):
        return None, ""
    if report.get("request") != request:
        return None, "replaced an earlier result of other inputs or settings"
    missing = [name for name in outputs if name not in report.get("outputs", ())]
    if missing:
        return None, f"registered again: the earlier result lacks {', '.join(missing)}"
    return report, ""


def plan_batch(pairs_file: Path, output: Path, *, settings: RegistrationSettings) -> Batch:
    """Read and check a batch before its first registration.

    Args:
        pairs_file: CSV with the columns of :data:`PAIR_COLUMNS` (fixed and moving required).
        output: the batch's output folder.
        settings: what every registration is asked to do and write.

    Raises:
        InputError: a bad pairs file, output folder or option, or an output that would replace an input.
    """
    from dpcn_med.options import check_options

    pairs = read_pairs(pairs_file)
    summary = output / "summary.csv"
    if os.path.lexists(summary) and not summary.is_file():
        raise InputError(f"{summary}: exists and is not a file; choose another output folder")
    check_output_folder(output)
    _, bandwidth, _, _ = check_options(mode=settings.mode, model=settings.model, bandwidth=settings.bandwidth,
                                       device=settings.device, fixed_modality=settings.fixed_modality,
                                       moving_modality=settings.moving_modality)
    model = model_identity(settings.model)
    jobs = []
    for index, pair in enumerate(pairs, start=1):
        request = registration_request(pair["fixed"], pair["moving"], fixed_mask=pair["fixed_mask"],
                                       moving_mask=pair["moving_mask"], settings=settings, bandwidth=bandwidth,
                                       model=model)
        folder = output / pair["id"]
        jobs.append(PairJob(index, pair, folder, request, *earlier_report(folder, request, settings.outputs)))
    batch = Batch(output, settings, jobs, model=model)
    _refuse_overwriting(batch, pairs_file)
    batch.missing = [f"{job.id}: {job.pair[key]}" for job in batch.pending for key in _PATHS
                     if job.pair[key] is not None and not os.path.exists(_split_series_folder(job.pair[key]))]
    return batch


def _refuse_overwriting(batch: Batch, pairs_file: Path) -> None:
    """One pair's output must not replace another pair's input either: the second would read the first's result."""
    inputs = {str(pairs_file): "this run's pairs file"}
    for job in batch.jobs:
        for key in _PATHS:
            if job.pair[key] is not None:
                inputs.setdefault(job.pair[key], f"the {key.replace('_', ' ')} of pair {job.id!r}")
    refuse_overwriting_inputs(inputs, [batch.summary, *(job.folder / name for job in batch.pending
                                                         for name in OUTPUT_NAMES)])


def _split_series_folder(path: str) -> str:
    """The folder of a ``FOLDER@SERIES_UID`` path (as :func:`dpcn_med.io.read_image` splits it), else ``path``."""
    folder, _, uid = path.rpartition("@")
    return folder if uid and not os.path.exists(path) and os.path.isdir(folder) else path


def report_row(pair_id: str, report: dict, status: str, message: str = "") -> dict[str, str]:
    """A summary row of a finished registration's report."""
    probability = report.get("success_probability")
    return {"id": pair_id, "status": status, "confidence": f"{report['confidence']:.4f}",
            "success_probability": "" if probability is None else f"{probability:.3f}",
            "rotation_deg": f"{report['final']['rotation_degrees']:.1f}",
            "seconds": f"{report['timings_s']['total']:.1f}", "message": message}


def error_row(pair_id: str, status: str, message: str) -> dict[str, str]:
    """A summary row of a pair that failed (``bad input`` or ``internal error``)."""
    return {"id": pair_id, "status": status, "success_probability": "", "confidence": "", "rotation_deg": "", "seconds": "", "message": message}


def earlier_row(job: PairJob, settings: RegistrationSettings) -> dict[str, str]:
    """The summary row of a pair an earlier run answered."""
    low = settings.flagged(job.earlier)
    return report_row(job.id, job.earlier, "done earlier" + (", low confidence" if low else ""))


def register_job(job: PairJob, settings: RegistrationSettings, *, model: str | dict[str, str] | None = None,
                 progress: Progress | None = None) -> tuple[dict[str, str], Exception | None]:
    """Register one pair of a batch into its folder.

    Returns:
        ``(summary row, error)``: ``error`` is the exception of an internal error (the row says ``internal error``),
        else ``None``. A bad input gives a ``bad input`` row; an interrupt propagates.
    """
    try:
        report = register_to_folder(job.pair["fixed"], job.pair["moving"], job.folder, settings=settings,
                                    fixed_mask=job.pair["fixed_mask"], moving_mask=job.pair["moving_mask"],
                                    progress=progress, model=model)
    except InputError as error:
        return error_row(job.id, "bad input", str(error)), None
    except Exception as error:  # one broken pair must not stop a cohort; it is reported and counted
        return error_row(job.id, "internal error", f"{type(error).__name__}: {error}"), error
    status = "low confidence" if settings.flagged(report) else "ok"
    return report_row(job.id, report, status, job.note), None


RowCallback = Callable[[PairJob, dict, "Exception | None"], None]
"""``on_row(job, row, error)``: called on the client as each pair's row is known (``error`` as :func:`register_job`)."""


def run_batch(batch: Batch, *, on_row: RowCallback | None = None,
              progress_for: Callable[[PairJob], Progress | None] | None = None,
              workers: int | None = None, scheduler: str | None = None,
              status: Callable[[str], None] | None = None) -> list[dict[str, str]]:
    """Register a batch's pending pairs and keep ``summary.csv`` current.

    Args:
        batch: from :func:`plan_batch`.
        on_row: called as each row is known (earlier results first, in order; then as pairs finish).
        progress_for: a progress callback per pair (sequential runs only).
        workers: register on a local Dask cluster of this many single-threaded worker processes.
        scheduler: register on the running Dask cluster at this address (``tcp://host:8786``).
        status: called with a progress line after each pair (Dask runs only).

    Returns:
        The summary rows, in the pairs file's order, of the pairs finished (all of them unless interrupted).
    """
    rows: dict[int, dict[str, str]] = {}

    def write_summary() -> None:
        make_folder(batch.output)
        io.write_csv([rows[index] for index in sorted(rows)], batch.summary, columns=list(SUMMARY_COLUMNS))

    def record(job: PairJob, row: dict[str, str], error: Exception | None) -> None:
        rows[job.index] = row
        write_summary()  # after every pair: an interrupted run's summary lists what it finished
        if on_row is not None:
            on_row(job, row, error)

    for job in batch.jobs:  # the pairs done earlier, with one write of the summary for all of them
        if job.earlier is not None:
            rows[job.index] = earlier_row(job, batch.settings)
            if on_row is not None:
                on_row(job, rows[job.index], None)
    if rows:
        write_summary()
    if workers is not None or scheduler is not None:
        from dpcn_med.cluster import run_on_dask

        run_on_dask(batch, record, workers=workers, scheduler=scheduler, status=status)
    else:
        for job in batch.pending:
            record(job, *register_job(job, batch.settings, model=batch.model,
                                      progress=None if progress_for is None else progress_for(job)))
    return [rows[index] for index in sorted(rows)]
