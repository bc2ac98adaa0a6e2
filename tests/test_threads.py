"""Two pieces of work at once (dpcn_med.threads)."""

from __future__ import annotations

import threading

import pytest
import torch

from dpcn_med.errors import InputError
from dpcn_med.threads import side_by_side


@pytest.fixture
def two_threads():
    """torch on two threads, as on the 2-core machines these run on by default, whatever the machine has."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(threads)


def test_both_run_at_once_and_return_in_order(two_threads):
    second_started = threading.Event()

    def first() -> str:
        # One after the other, the second would start only after this returned: the wait would time out.
        assert second_started.wait(timeout=10), "the second call did not run beside the first"
        return "first"

    def second() -> int:
        second_started.set()
        return 2

    assert side_by_side(first, second) == ("first", 2)


def test_the_first_error_wins_even_when_the_second_fails_sooner(two_threads):
    second_failed = threading.Event()

    def first() -> None:
        second_failed.wait(timeout=10)
        raise InputError("fixed.nii.gz: is truncated")

    def second() -> None:
        try:
            raise InputError("moving.nii.gz: not found")
        finally:
            second_failed.set()

    with pytest.raises(InputError, match="fixed.nii.gz"):
        side_by_side(first, second)


def test_the_second_error_when_the_first_succeeds(two_threads):
    def second() -> None:
        raise InputError("moving.nii.gz: not found")

    with pytest.raises(InputError, match="moving.nii.gz"):
        side_by_side(lambda: 1, second)


def test_one_after_the_other_where_torch_runs_on_one_thread():
    """As a Dask worker of register-batch does (dpcn_med.cluster.WORKER_THREADS): no second thread of its own."""
    threads = torch.get_num_threads()
    first_done = threading.Event()
    try:
        torch.set_num_threads(1)
        assert side_by_side(lambda: first_done.set() or "first", lambda: first_done.is_set()) == ("first", True)
    finally:
        torch.set_num_threads(threads)
