"""Text, JSON and CSV files: read with errors that name the file, written atomically."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
from collections.abc import Callable, Collection
from typing import Any

import numpy as np

from dpcn_med.errors import InputError, InputNotFoundError
from dpcn_med.io._common import _GZIP_MAGIC
from dpcn_med.io.atomic import atomic_output


def read_text(path: str | os.PathLike, *, encoding: str = "utf-8") -> str:
    """The content of a text file (``latin-1`` decodes any bytes, for formats whose encoding is not stated).

    Raises:
        InputNotFoundError: the file is missing.
        InputError: not decodable as ``encoding``.
    """
    name = _existing_file(path)
    try:
        with open(name, encoding=encoding) as stream:
            return stream.read()
    except UnicodeDecodeError as error:
        kind = _binary_kind(name)
        raise InputError(f"{name}: {f'is a {kind} file, not text' if kind else f'not a {encoding} text file ({error})'}"
                         ) from None


def write_text(text: str, path: str | os.PathLike) -> None:
    """Write ``text`` as UTF-8, newlines untranslated, atomically."""
    with atomic_output(path) as temporary, open(temporary, "w", encoding="utf-8", newline="") as stream:
        stream.write(text)


def read_json(path: str | os.PathLike) -> Any:
    """The content of a JSON file.

    Raises:
        InputNotFoundError: the file is missing.
        InputError: not UTF-8 JSON, or JSON that Python cannot hold (nested too deeply, an integer of more digits
            than Python converts).
    """
    name = _existing_file(path)
    try:
        with open(name, encoding="utf-8") as stream:
            return json.load(stream)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{name}: not a JSON file ({error})") from None
    except RecursionError:
        raise InputError(f"{name}: JSON nested too deeply to read (beyond Python's recursion limit)") from None
    except ValueError as error:  # the limit on the digits of an integer (Python >= 3.11)
        raise InputError(f"{name}: unreadable JSON ({error})") from None


def write_json(data: Any, path: str | os.PathLike) -> None:
    """Write ``data`` as indented JSON (numpy scalars and arrays, and paths, converted), atomically."""
    write_text(json.dumps(data, indent=2, default=_json_value) + "\n", path)


def _json_value(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def read_csv(path: str | os.PathLike, columns: dict[str, Callable[[str], Any]], *,
             allowed: Collection[str] | None = None) -> list[tuple[int, dict]]:
    """The rows of a CSV table with a header (as :func:`write_csv` writes it), each with the line it ends on, each
    value of ``columns`` converted by its type (``{"trial": int, "tre_mm": float}``); other columns stay strings, and
    a short row's missing cells are ``None``. Blank lines are skipped, before the header too.

    Args:
        allowed: the only columns the table may have (with ``columns``); ``None``: any.

    Raises:
        InputNotFoundError: the file is missing.
        InputError: not CSV, a column of ``columns`` is missing, a column is named twice or is not ``allowed``, a
            row has more cells than the header (an unquoted comma), or a value does not convert (the message names
            the line).
    """
    name = os.fspath(path)
    try:
        # utf-8-sig: spreadsheets save "CSV UTF-8" with a byte-order mark
        reader = csv.reader(io.StringIO(read_text(name, encoding="utf-8-sig"), newline=""))
        lines = [(reader.line_num, cells) for cells in reader if any(cell.strip() for cell in cells)]
    except csv.Error as error:
        raise InputError(f"{name}: not a readable CSV file ({error})") from None
    header = [field.strip() for field in lines[0][1]] if lines else []
    repeated = sorted({field for field in header if header.count(field) > 1})
    if repeated:
        raise InputError(f"{name}: column {', '.join(map(repr, repeated))} appears more than once in the header")
    missing = [column for column in columns if column not in header]
    if missing:
        found = f"its header row is {','.join(header)[:80]!r}" if header else "it holds no rows"
        raise InputError(f"{name}: no column {', '.join(missing)}: {found}; expected a header row naming "
                         f"{', '.join(columns)}, cells separated by commas")
    unknown = [field for field in header if allowed is not None and field not in {*columns, *allowed}]
    if unknown:
        raise InputError(f"{name}: unknown column {', '.join(map(repr, unknown))} (the columns are "
                         f"{', '.join(dict.fromkeys([*columns, *allowed]))})")
    rows = []
    for line, cells in lines[1:]:
        if len(cells) > len(header):
            raise InputError(f"{name}: line {line}: {len(cells)} cells under {len(header)} columns (a comma in a "
                             "value needs the value in double quotes)")
        row = dict(zip(header, [*cells, *[None] * (len(header) - len(cells))]))
        try:
            rows.append((line, {**row, **{column: kind(row[column]) for column, kind in columns.items()}}))
        except (TypeError, ValueError) as error:
            raise InputError(f"{name}: line {line}: {error}") from None
    return rows


def write_csv(rows: list[dict], path: str | os.PathLike, columns: list[str] | None = None) -> None:
    """``rows`` as a CSV table with a header, ``\n`` line ends, atomically: the columns are ``columns`` (other keys
    ignored) or the first row's keys.

    Raises:
        ValueError: no ``rows`` and no ``columns``: there is no header to write.
    """
    if not rows and not columns:
        raise ValueError(f"{path}: no rows and no columns: nothing to write a header from")
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns or list(rows[0]), lineterminator="\n",
                            extrasaction="ignore" if columns else "raise")
    writer.writeheader()
    writer.writerows(rows)
    write_text(buffer.getvalue(), path)


_MAGIC = {_GZIP_MAGIC: "gzip-compressed (.gz)", b"PK\x03\x04": "zip", b"\x89HDF": "HDF5",
          b"\x89PNG": "PNG image"}
"""Leading bytes of binary files a text reader may be handed by mistake (a .nii.gz for a pairs file)."""


def _binary_kind(name: str) -> str | None:
    """What ``name`` is when its first bytes say so (:data:`_MAGIC`), else ``None``."""
    with contextlib.suppress(OSError), open(name, "rb") as stream:
        start = stream.read(8)
        return next((kind for magic, kind in _MAGIC.items() if start.startswith(magic)), None)
    return None


def _existing_file(path: str | os.PathLike) -> str:
    """``path`` as a string if it names a file; else the error a reader raises."""
    name = os.fspath(path)
    if os.path.isdir(name):
        raise InputError(f"{name}: is a folder; expected a file")
    if not os.path.isfile(name):
        raise InputNotFoundError(f"{name}: not found (no such file); check the path")
    return name
