"""Where batch jobs run: existing engines behind one small interface (docs/batch.md says why these two).

- ``local`` (default): the standard library's :class:`concurrent.futures.ProcessPoolExecutor` with spawned
  processes, one per core; nothing to install or start.
- ``dask``: a Dask ``distributed`` cluster: ``--address tcp://host:8786`` (any scheduler, e.g. started by
  dask-jobqueue on Slurm/PBS) or, without an address, a ``LocalCluster`` of ``--workers`` processes.
  Optional: ``pip install 'dtoc-mri[dask]'``.

Both run :func:`dtoc.batch.worker.run_job` and hand its result (the output files as bytes) back to the batch
process.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Iterable, Iterator
from typing import Any

from dtoc.errors import InputError

ENGINES = ("local", "dask")


def default_workers() -> int:
    """The cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


class LocalEngine:
    """A process pool on this machine (spawned workers; SIGINT ignored in them, see :func:`init_worker`)."""

    name = "local"

    def __init__(self, workers: int, threads: int) -> None:
        from concurrent.futures import ProcessPoolExecutor

        from dtoc.batch.worker import init_worker

        self.workers = workers
        self.pool = ProcessPoolExecutor(
            workers, mp_context=multiprocessing.get_context("spawn"), initializer=init_worker, initargs=(threads,)
        )

    def submit(self, payload: dict) -> Any:
        from dtoc.batch.worker import run_job

        return self.pool.submit(run_job, payload)

    def as_completed(self, futures: Iterable) -> Iterator:
        from concurrent.futures import as_completed

        return as_completed(list(futures))

    def abort(self, futures: Iterable) -> None:
        """Stop the workers: their jobs are lost (nothing of them is kept) and the pool marks every job not yet
        finished as failed.  SIGKILL, not SIGTERM: a job may hold SIGTERM back (an optimization defers it while it
        writes its outputs, then ends as 'interrupted' and the worker takes the next job); a killed worker can
        leave only files in its working folder, which the batch removes.  No future is cancelled here: the pool's
        own clean-up after its workers died sets an exception on each pending one, which fails on a cancelled
        future (CPython 3.11)."""
        children = multiprocessing.active_children()
        for p in children:
            p.kill()
        for p in children:  # gone before the batch removes their working folders
            p.join(timeout=10)
        self.pool.shutdown(wait=True)

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


class DaskEngine:
    """A Dask distributed cluster: the scheduler at ``address``, or a LocalCluster of ``workers`` processes with
    one thread each (the job sets its torch threads itself)."""

    name = "dask"

    def __init__(self, workers: int, threads: int, address: str | None) -> None:
        try:
            import logging

            from distributed import Client, LocalCluster
        except ImportError:
            raise InputError("--engine dask needs Dask: pip install 'dtoc-mri[dask]'") from None
        self.cluster = None
        if address:
            try:
                self.client = Client(address, timeout="20s")
            except OSError as e:
                raise InputError(f"--address {address}: no Dask scheduler reachable ({e})") from None
        else:
            from dtoc.batch.worker import THREAD_ENV

            env = {k: str(threads) for k in THREAD_ENV}
            self.cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                silence_logs=logging.ERROR,
                env=env,
            )
            self.client = Client(self.cluster)
        self.workers = len(self.client.scheduler_info().get("workers", {})) or workers

    def submit(self, payload: dict) -> Any:
        from dtoc.batch.worker import run_job

        return self.client.submit(run_job, payload, pure=False, key=f"dtoc-job-{payload['key'][:20]}")

    def as_completed(self, futures: Iterable) -> Iterator:
        from distributed import as_completed

        return iter(as_completed(list(futures)))

    def abort(self, futures: Iterable) -> None:
        self.client.cancel(list(futures), force=True)

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def make_engine(name: str, workers: int | None, threads: int, address: str | None):
    """The engine ``name`` with ``workers`` workers (default: the cores of this machine)."""
    if name not in ENGINES:
        raise InputError(f"--engine {name!r}: expected one of {', '.join(ENGINES)}")
    if workers is not None and workers < 1:
        raise InputError(f"--workers {workers}: must be at least 1")
    n = workers or default_workers()
    if name == "local":
        if address:
            raise InputError("--address is for --engine dask")
        return LocalEngine(n, threads)
    return DaskEngine(n, threads, address)
