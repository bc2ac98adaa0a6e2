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
    """``(first(), second())``: on two threads at once where this process runs torch on more than one thread, else
    one after the other (a worker of ``dpcn-med register-batch --workers`` runs on one: ``dpcn_med.cluster``).

    Raises:
        What ``first`` raised, else what ``second`` raised: the order of a call of one after the other, whichever
        fails sooner.
    """
    import torch  # here: the modules that call this import it already, and this layer need not

    if torch.get_num_threads() < 2:
        return first(), second()
    with ThreadPoolExecutor(max_workers=2, thread_name_prefix="dpcn-med-side") as pool:
        futures = pool.submit(first), pool.submit(second)
        return futures[0].result(), futures[1].result()
