"""Writing files atomically: a file appears under its final name complete or not at all, and what ITK's writers
wrote is read back before it replaces anything."""

from __future__ import annotations

import contextlib
import math
import os
import secrets
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from dpcn_med.errors import InputError
from dpcn_med.io._common import _sitk_reason

_NAME_BYTES = 255
"""Longest file name most file systems take (ext4, XFS, APFS, NTFS in UTF-16 units)."""


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` that becomes ``path`` when the block succeeds.

    The temporary name keeps the full suffix (``x.nii.gz`` -> ``.x.tmp1a2b3c4d.nii.gz``), so writers that choose the
    format by extension work on it. On success it is renamed onto ``path`` (``os.replace``, atomic within one
    folder); on any exception, Ctrl-C included, it is removed and ``path`` is left as it was.

    Raises:
        InputError: the folder of ``path`` does not exist (creating it is the caller's choice).

    Example:
        >>> with atomic_output("out/report.png") as temporary:  # doctest: +SKIP
        ...     figure.savefig(temporary)
    """
    target = Path(path)
    if not target.parent.is_dir():
        raise InputError(f"{target}: folder {target.parent} does not exist; create it first")
    suffix = _full_suffix(target.name)
    stem = target.name[:len(target.name) - len(suffix)]
    # The stem shortened as needed: a target name within the file system's 255 bytes gave a temporary name beyond
    # them (its 14 more bytes), and the write failed with "File name too long".
    room = _NAME_BYTES - len(f"..tmp{secrets.token_hex(4)}{suffix}".encode())
    stem = stem.encode()[:max(room, 1)].decode(errors="ignore")
    temporary = target.with_name(f".{stem}.tmp{secrets.token_hex(4)}{suffix}")
    try:
        yield temporary
        os.replace(temporary, target)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM (which the command line turns into ``KeyboardInterrupt``) until the block ends, then
    raise: for outputs that must change together (a checkpoint's two files, a registration's set of files). Outside
    the main thread, where Python delivers no signal and handlers cannot be set, the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    signals = (signal.SIGINT, signal.SIGTERM)
    previous = [signal.signal(number, lambda number, frame: received.append(number)) for number in signals]
    try:
        yield
    finally:
        for number, handler in zip(signals, previous, strict=True):
            signal.signal(number, handler)
    if received:
        raise KeyboardInterrupt


def _full_suffix(name: str) -> str:
    """``.nii.gz`` for ``x.nii.gz``, ``.tfm`` for ``a.b.tfm``: the suffix a writer picks its format by."""
    suffixes = Path(name).suffixes
    if len(suffixes) >= 2 and suffixes[-1].lower() == ".gz":
        return "".join(suffixes[-2:])
    return suffixes[-1] if suffixes else ""


def _check_write_suffix(target: Path, suffixes: tuple[str, ...], what: str, note: str = "") -> None:
    """Refuse a suffix SimpleITK has no writer for; it picks the writer by the suffix as spelt (``.MHA`` has none)."""
    if not target.name.endswith(suffixes):
        case = " in lower case" if target.name.lower().endswith(suffixes) else ""
        raise InputError(f"{target}: cannot write {what} with this suffix; use {', '.join(suffixes)}{case}{note}")


def _check_written(target: Path, check: Callable[[], None]) -> None:
    """Run ``check`` on the file just written for ``target``; raise ``OSError`` if it finds the file short.

    See docs/design_notes/io.md.
    """
    try:
        check()
    except InputError as error:
        raise OSError(f"{target}: writing it failed: the file came out incomplete (is the disk full, or a file-size "
                      "limit set?); nothing was written") from error


def _check_nifti_length(path: Path) -> None:
    """Raise ``InputError`` if a NIfTI file just written holds fewer bytes than its header needs; other files pass.

    A .nii.gz is judged by its gzip trailer (its last 4 bytes: the inflated length modulo 2^32), not inflated again.
    See docs/design_notes/io.md.
    """
    lower = path.name.lower()
    if not lower.endswith((".nii", ".nii.gz")):
        return
    import nibabel  # imported here: only NIfTI files need it

    try:
        proxy = nibabel.load(path).dataobj  # the header only
        needed = int(proxy.offset) + math.prod(proxy.shape) * proxy.dtype.itemsize
        if lower.endswith(".nii"):
            complete = path.stat().st_size >= needed
        else:
            with open(path, "rb") as stream:
                stream.seek(-4, os.SEEK_END)
                complete = int.from_bytes(stream.read(4), "little") == needed % 2 ** 32
    except (nibabel.filebasedimages.ImageFileError, OSError, ValueError, EOFError) as error:
        raise InputError(f"{path}: its header does not read back ({error})") from None
    if not complete:
        raise InputError(f"{path}: holds fewer bytes than its header needs ({needed:,})")


def _check_same_transform(path: Path, transform: sitk.Transform) -> None:
    """Raise ``InputError`` if ``path`` does not read back as ``transform``'s parameters (to text precision)."""
    try:
        written = sitk.ReadTransform(str(path))
    except RuntimeError as error:
        raise InputError(f"{path}: unreadable ({_sitk_reason(error)})") from None
    for found, expected in ((written.GetParameters(), transform.GetParameters()),
                            (written.GetFixedParameters(), transform.GetFixedParameters())):
        if len(found) != len(expected) or not np.allclose(found, expected, rtol=1e-9, atol=1e-12):
            raise InputError(f"{path}: holds other parameters than the transform written")


def _umask() -> int:
    """The process's umask (which can only be read by setting it)."""
    mask = os.umask(0o077)
    os.umask(mask)
    return mask
