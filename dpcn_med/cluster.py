"""A batch's registrations on Dask: a local cluster of worker processes, or a running cluster by its address.

Each pair is one task with the batch's settings; the worker reads the inputs by path (shared storage, not shipped
through the scheduler), writes the pair's folder atomically as a sequential run does, and returns its summary row.
The client records rows as they arrive. A task whose worker dies is run again elsewhere; a pair that fails twice
(its worker died twice, or it raised twice) is recorded as an internal error and the batch goes on.

Dask is optional: ``pip install 'dpcn_med[cluster]'``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import time
import uuid
from collections.abc import Callable, Iterator

from dpcn_med.batch import FAILED, Batch, PairJob, error_row, register_job
from dpcn_med.errors import InputError
from dpcn_med.outputs import model_identity

INSTALL = "pip install 'dpcn_med[cluster]'"
"""How to install what this module needs."""

ATTEMPTS = 2
"""Runs of a pair before it is recorded as failed (a worker death or an exception counts as one)."""

CONNECT_TIMEOUT_S = 20
"""How long the client waits for a ``--scheduler`` to answer."""

WORKER_THREADS = 1
"""Solver threads of each pair on a worker (torch and SimpleITK); one task at a time per worker thread."""


def require_dask() -> None:
    """Raise :class:`InputError` with the install line where dask.distributed is missing."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise InputError(f"--workers and --scheduler need Dask, which is not installed; {INSTALL}") from None


@contextlib.contextmanager
def dask_client(*, workers: int | None = None, scheduler: str | None = None) -> Iterator:
    """A ``distributed.Client`` on a new local cluster of ``workers`` processes, or on the cluster at ``scheduler``.

    A local cluster gives each worker :data:`WORKER_THREADS` threads and marks a task as failed after
    :data:`ATTEMPTS` worker deaths; a running cluster keeps its own ``distributed.scheduler.allowed-failures``.

    Raises:
        InputError: Dask is missing, or the scheduler cannot be reached.
    """
    require_dask()
    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
        except (OSError, TimeoutError, ValueError) as error:
            raise InputError(f"--scheduler {scheduler}: cannot reach a Dask scheduler there ({error}); start one "
                             "(dask scheduler, or dask-jobqueue) and give its address, tcp://HOST:8786") from None
        with client:
            yield client
        return
    with dask.config.set({"distributed.scheduler.allowed-failures": ATTEMPTS - 1}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=WORKER_THREADS, processes=True,
                               dashboard_address=None, silence_logs=logging.ERROR)
    with cluster, Client(cluster) as client:
        yield client


def run_on_dask(batch: Batch, record: Callable[[PairJob, dict, Exception | None], None], *,
                workers: int | None = None, scheduler: str | None = None,
                status: Callable[[str], None] | None = None) -> None:
    """Register ``batch.pending`` on Dask and ``record(job, row, error)`` each pair as it finishes.

    Args:
        batch: from :func:`dpcn_med.batch.plan_batch`; its ``model`` identity is checked on every worker.
        record: called on the client, in the order pairs finish.
        workers, scheduler: as :func:`dask_client`.
        status: called with a progress line (done, failed, running, time left) after each pair.
    """
    from distributed import as_completed

    pending = batch.pending
    if not pending:
        return
    run = uuid.uuid4().hex[:8]
    with dask_client(workers=workers, scheduler=scheduler) as client:
        futures = {client.submit(register_on_worker, job, batch.settings, batch.model, retries=ATTEMPTS - 1,
                                 key=f"dpcn-med-{run}-{job.index}", pure=False): job for job in pending}
        slots = sum(client.nthreads().values()) or 1
        started, done, failed = time.monotonic(), 0, 0
        try:
            for future in as_completed(futures):
                job = futures.pop(future)
                row, error = _row_of(future, job)
                done += 1
                failed += row["status"] in FAILED
                record(job, row, error)
                if status is not None:
                    status(_status_line(done, failed, len(futures), slots, time.monotonic() - started))
        finally:
            client.cancel(list(futures))  # interrupted: a running cluster must not go on with this batch's pairs


def _row_of(future, job: PairJob) -> tuple[dict, Exception | None]:
    try:
        return future.result(), None
    except Exception as error:  # it raised ATTEMPTS times, or KilledWorker: the workers running it died
        return error_row(job.id, "internal error", f"{type(error).__name__}: {error}"), error


def _status_line(done: int, failed: int, left: int, slots: int, elapsed: float) -> str:
    counts = f"done {done}, failed {failed}, running {min(left, slots)}, waiting {max(left - slots, 0)}"
    if not left:
        return counts
    seconds = elapsed / done * left  # wall seconds per pair so far, with the cluster's parallelism
    return f"{counts}; about {seconds / 60:.0f} min left" if seconds >= 60 else f"{counts}; about {seconds:.0f} s left"


_worker_ready = False


def register_on_worker(job: PairJob, settings, model: str | dict[str, str]) -> dict:
    """The task of one pair: check the model files against the client's, register, return the summary row.

    Raises:
        Exception: an internal error of the registration, so that Dask runs the pair again elsewhere.
    """
    here = model_identity(settings.model)
    if here != model:
        return error_row(job.id, "bad input", f"{settings.model}: the model on worker {socket.gethostname()} "
                         f"({here}) is not the client's ({model}); give every worker the same model files")
    _set_up_worker()
    row, error = register_job(job, settings, model=model)
    if error is not None:
        raise error
    return row


def _set_up_worker() -> None:
    """Once per worker process: :data:`WORKER_THREADS` solver threads (torch, SimpleITK)."""
    global _worker_ready
    if _worker_ready:
        return
    import SimpleITK as sitk
    import torch

    torch.set_num_threads(WORKER_THREADS)
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(WORKER_THREADS)
    os.environ.setdefault("OMP_NUM_THREADS", str(WORKER_THREADS))
    _worker_ready = True
