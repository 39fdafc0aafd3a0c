"""Where independent runs go: this process, a local process pool, or a Dask cluster.

The Monte Carlo seeds (:func:`hvo_graph.montecarlo.run_seeds`) and the sequences of
a batch (:func:`hvo_graph.batch.run_batch`) are independent jobs, each a
deterministic function of its inputs, so they can run anywhere and give the same
numbers. :func:`executor` hands out a ``concurrent.futures.Executor`` for them:

- ``scheduler=None``: a ``ProcessPoolExecutor`` of fresh ("spawn") interpreters
  started with :data:`WORKER_ENVIRONMENT` (one BLAS thread each);
- ``scheduler="tcp://HOST:PORT"``: the executor of a ``dask.distributed.Client``
  connected to an existing scheduler (docs/batch.md gives the commands that start
  one and its workers). Dask is an optional dependency (``pip install
  "hvo_graph[cluster]"``).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Iterator, Mapping
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager

from hvo_graph.errors import InputError, as_integer

#: Environment of the local worker processes: one BLAS / OpenMP thread each. The
#: parallelism is across processes; threaded BLAS in every worker oversubscribes the
#: cores, and the front end's small SVDs then ran ~10x slower on a loaded 2-core machine.
WORKER_ENVIRONMENT: dict[str, str] = {
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}

#: Seconds to wait for a Dask scheduler to answer before giving up.
CONNECT_TIMEOUT_S = 10.0

#: What to install when dask.distributed is missing.
CLUSTER_EXTRA = 'pip install "hvo_graph[cluster]"  (or: pip install "dask[distributed]")'


def resolve_workers(workers: int | None) -> int:
    """Worker processes: ``workers`` (>= 1), or ``os.cpu_count()`` when None."""
    if workers is None:
        return max(1, os.cpu_count() or 1)
    return as_integer(workers, "workers", 1)


def check_scheduler(scheduler: str | None, workers: int | None = None) -> str | None:
    """``scheduler`` as given (None: local), checked: a ``tcp://HOST:PORT`` (or
    ``tls://``, ``inproc://``) address, and no ``workers`` next to it (the cluster's
    workers run the jobs, a local count does not apply)."""
    if scheduler is None:
        return None
    if not isinstance(scheduler, str) or "://" not in scheduler:
        raise InputError(f"scheduler: expected an address like tcp://HOST:8786, got {scheduler!r}")
    if workers is not None:
        raise InputError("workers: does not apply with a scheduler (its workers run the jobs)")
    return scheduler


@contextmanager
def _environment(values: Mapping[str, str]) -> Iterator[None]:
    """Set environment variables for the duration of the block (restored after)."""
    saved = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _dask_client(scheduler: str) -> object:
    try:
        from distributed import Client
    except ImportError:
        raise InputError(
            f"scheduler: running on a Dask cluster needs dask.distributed: {CLUSTER_EXTRA}"
        ) from None
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise InputError(
            f"scheduler: cannot connect to {scheduler} ({type(exc).__name__}: {exc})"
        ) from None


@contextmanager
def executor(workers: int, scheduler: str | None = None) -> Iterator[Executor]:
    """An executor for independent jobs: ``workers`` local processes, or the workers of the
    Dask scheduler at ``scheduler``.

    Jobs must be picklable module-level functions and arguments. The local pool reads
    :data:`WORKER_ENVIRONMENT` before numpy is imported (fresh "spawn" interpreters;
    forked ones would inherit this process's BLAS threads).

    Raises:
        InputError: dask.distributed missing, or no scheduler answering at ``scheduler``.
    """
    if scheduler is not None:
        client = _dask_client(check_scheduler(scheduler))
        try:
            # pure=False: every job runs, even two with equal arguments (no result sharing).
            with client.get_executor(pure=False) as pool:  # type: ignore[attr-defined]
                yield pool
        finally:
            client.close()  # type: ignore[attr-defined]
        return
    with (
        _environment(WORKER_ENVIRONMENT),
        ProcessPoolExecutor(
            max_workers=as_integer(workers, "workers", 1),
            mp_context=multiprocessing.get_context("spawn"),
        ) as pool,
    ):
        yield pool
