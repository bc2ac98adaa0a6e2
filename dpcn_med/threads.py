"""Two pieces of work at once, on two threads: the two images of a pair, each read, checked and prepared on its own.

Decompression, SimpleITK's readers and filters, numpy and torch let go of Python's lock for most of their time, so on
two cores the second side runs beside the first (docs/design_notes/registration.md, ``dpcn_med.threads``).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
U = TypeVar("U")


def side_by_side(first: Callable[[], T], second: Callable[[], U]) -> tuple[T, U]:
    """``(first(), second())``, run on two threads at once.

    Raises:
        What ``first`` raised, else what ``second`` raised: the order of a call of one after the other, whichever
        fails sooner.
    """
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="dpcn-med-side") as pool:
        futures = pool.submit(first), pool.submit(second)
        return futures[0].result(), futures[1].result()
