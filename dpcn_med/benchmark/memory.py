"""Peak memory of one call: the resident-set growth during it, Linux only (``/proc/self``).

Why the high-water mark is reset and the C heap trimmed first: docs/design_notes/benchmark.md.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable
from pathlib import Path


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``, ``None`` where the C library has none (macOS, musl, Windows)."""
    name = ctypes.util.find_library("c")
    try:
        return getattr(ctypes.CDLL(name), "malloc_trim", None) if name else None
    except OSError:
        return None


def reset_peak_rss() -> float | None:
    """Reset this process's resident-set high-water mark (Linux ``clear_refs``), after handing the C heap's free pages
    back to the system (glibc ``malloc_trim``, where there is one); return the current RSS in MiB, ``None`` where the
    system does not offer it."""
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

