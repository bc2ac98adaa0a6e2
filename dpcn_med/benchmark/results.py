"""A benchmark's results on disk: ``results.csv`` read back for ``--combine``, the settings its poses follow from,
and the journal an interrupted run goes on from."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from dpcn_med import io
from dpcn_med.benchmark.cases import CASES
from dpcn_med.benchmark.config import BenchmarkConfig
from dpcn_med.benchmark.methods import METHODS
from dpcn_med.errors import InputError

JOURNAL = "results.partial.jsonl"
"""The output folder's record of an unfinished run (:class:`Journal`); removed once ``results.csv`` holds all of
it."""
SETTINGS = "settings.json"
"""Beside ``results.csv``: the settings its poses follow from (:func:`pose_settings`), which ``--combine`` compares."""
RESULT_FIELDS = {"case": str, "bin": str, "trial": int, "method": str, "tre_mm": float, "seconds": float,
                 "peak_mib": float, "rotation_error_deg": float, "centre_error_mm": float, "canonical_voxel_mm": float}
"""Columns of ``results.csv`` and their types (:func:`~dpcn_med.benchmark.run_benchmark`'s rows)."""
GLOBAL_FIELDS = ("rotation_error_deg", "centre_error_mm", "canonical_voxel_mm")
"""The columns of the global estimate's criterion (:data:`dpcn_med.evaluation.SUCCESS_DEGREES`), added on 2026-12-07:
a ``results.csv`` written before lacks them, and reads back with them NaN."""


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
                # A journal begun before the global fields were (same version) lacks them: NaN, as combine reads them.
                row = {field: kind(record[field] if field in record or field not in GLOBAL_FIELDS else math.nan)
                       for field, kind in RESULT_FIELDS.items()}
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
        required = {name: kind for name, kind in RESULT_FIELDS.items() if name not in GLOBAL_FIELDS}
        found = io.read_csv(path, required, allowed=GLOBAL_FIELDS)
        if found and 0 < len(set(GLOBAL_FIELDS) & set(found[0][1])) < len(GLOBAL_FIELDS):
            raise InputError(f"{path}: has some of the columns {', '.join(GLOBAL_FIELDS)} but not all; a benchmark "
                             "writes all three, or (before 2026-12-07) none")
        for line, row in found:
            for name in GLOBAL_FIELDS:
                row[name] = _optional_number(row.get(name), path, line, name)
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
    for field in GLOBAL_FIELDS:  # NaN: written before they were
        if row[field] < 0 or math.isinf(row[field]):
            raise InputError(f"{path}: line {line}: {field} {row[field]}; expected a finite number >= 0, or none")
    return row["case"], row["bin"], row["trial"], row["method"]


def _optional_number(value: str | None, path: Path, line: int, name: str) -> float:
    """A cell of one of :data:`GLOBAL_FIELDS`: NaN where it is absent or empty.

    Raises:
        InputError: not a number, naming the file, line and column.
    """
    if value is None or not value.strip():
        return math.nan
    try:
        return float(value)
    except ValueError:
        raise InputError(f"{path}: line {line}: {name} {value!r} is not a number") from None
