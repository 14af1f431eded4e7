"""Dask on this machine: the local cluster every CPU Monte Carlo of gyrojax runs on.

One Python process runs a Monte Carlo trial's graph (a vmapped ODE solve, then small batched
LAPACK least-squares problems) on one core, and several host devices in one process deadlock
jaxlib 0.10.2's batched LAPACK (docs/decisions/0007-monte-carlo-worker-processes.md). So a CPU
Monte Carlo uses the other cores through worker processes: a Dask cluster of single-threaded
workers, one per core, each pinned to its core. :func:`local_cluster` makes one;
:func:`pool_client` keeps one for the life of the process (so a second call reuses the workers'
compiled programs), :func:`shutdown_pool` closes it. Any other Dask cluster (a scheduler
address, ``dask-jobqueue`` on SLURM or PBS) runs the same tasks.

The workers are fresh interpreters started as ``python -m dask spec``, each under a nanny that
restarts it if it dies: unlike a plain ``distributed.LocalCluster`` (``multiprocessing``'s spawn)
the caller's script is not imported again in them, so a script needs no
``if __name__ == "__main__"`` guard. The scheduler and its dashboard run in this process.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import sys

from distributed import Client, Scheduler, SpecCluster, WorkerPlugin
from distributed.deploy.subprocess import SubprocessWorker

__all__ = ["local_cluster", "available_cores", "pool_client", "shutdown_pool", "WORKER_ENV"]

WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}
"""The environment of :func:`local_cluster`'s workers: one thread for BLAS and XLA's Eigen (a
trial's least-squares problems are small; threads on top of one process per core contend)."""


def available_cores() -> list[int]:
    """The CPU cores this process may run on (its affinity set), sorted."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:  # no affinity API (macOS): all cores, unpinned
        return list(range(os.cpu_count() or 1))


class _Cluster(SpecCluster):
    """A ``SpecCluster`` that asks its workers to close before it stops their processes (no
    errors logged by workers killed in the middle of a conversation)."""

    async def _close(self):
        sched = self.scheduler  # the in-process Scheduler of local_cluster's spec
        if sched is not None and sched.workers:
            for w in list(sched.workers):
                sched.close_worker(w)
            for _ in range(50):  # up to 5 s
                if not sched.workers:
                    break
                await asyncio.sleep(0.1)
        await super()._close()


def local_cluster(n_workers: int | None = None, *, pin: bool = True) -> SpecCluster:
    """A Dask cluster on this machine: `n_workers` single-threaded worker processes (default:
    one per core this process may use) with :data:`WORKER_ENV`, each under a nanny that
    restarts it if it dies. Close it (or use it as a context manager) when done.

    The workers get this process's ``sys.path`` (as ``multiprocessing`` children do). `pin`:
    worker ``i`` and every thread it starts run on the ``i``-th core of this process's
    affinity set (Linux, while there are at least as many cores as workers).

    **Raises:** ``ValueError`` for an `n_workers` that is not a positive int."""
    cores = available_cores()
    if n_workers is None:
        n_workers = len(cores)
    if isinstance(n_workers, bool) or not isinstance(n_workers, int) or n_workers < 1:
        raise ValueError(f"local_cluster: n_workers={n_workers!r}; give a positive int")
    workers = {i: {"cls": SubprocessWorker, "options": {
        "worker_class": "distributed.Nanny",
        "worker_kwargs": {"name": i, "nthreads": 1, "env": WORKER_ENV, "host": "127.0.0.1",
                          "silence_logs": logging.ERROR}}} for i in range(n_workers)}
    cluster = _Cluster(workers=workers, name="gyrojax", silence_logs=logging.ERROR,
                       scheduler={"cls": Scheduler, "options": {
                           "dashboard_address": ":0", "host": "127.0.0.1"}})
    pin = pin and n_workers <= len(cores) and hasattr(os, "sched_setaffinity")
    with Client(cluster) as client:
        client.register_plugin(_WorkerSetup(cores if pin else None, sys.path))
    return cluster


class _WorkerSetup(WorkerPlugin):
    """Readies a local worker as ``multiprocessing`` would a child: the caller's ``sys.path``
    (so functions of the caller's modules, e.g. a test file or a script's neighbours, unpickle
    there), and, given `cores`, every thread of worker ``i`` (its name) pinned to ``cores[i]``
    (the threads it starts later, XLA's pool, inherit the affinity). Kept by the scheduler: a
    restarted worker gets it too."""

    name = "gyrojax-worker-setup"

    def __init__(self, cores, sys_path):
        self.cores = None if cores is None else list(cores)
        self.sys_path = [p for p in sys_path if p]

    def setup(self, worker):
        sys.path.extend(p for p in self.sys_path if p not in sys.path)
        if self.cores is None:
            return
        core = self.cores[int(worker.name) % len(self.cores)]
        for tid in os.listdir("/proc/self/task"):
            with contextlib.suppress(OSError):  # a thread that ended meanwhile
                os.sched_setaffinity(int(tid), {core})


_POOL: dict = {}


def pool_client(n_workers: int) -> Client:
    """A client of this process's kept :func:`local_cluster` of `n_workers` workers (started
    on first use and again with another size; kept so that a second call reuses the workers'
    compiled programs; :func:`shutdown_pool` closes it, as does the end of Python)."""
    if _POOL.get("n") != n_workers or _POOL["client"].status != "running":
        shutdown_pool()
        cluster = local_cluster(n_workers)
        _POOL.update(n=n_workers, cluster=cluster, client=Client(cluster))
        _POOL["client"].wait_for_workers(n_workers)
    return _POOL["client"]


def shutdown_pool() -> None:
    """Close the kept local cluster of :func:`pool_client` (a later call starts another)."""
    client, cluster = _POOL.pop("client", None), _POOL.pop("cluster", None)
    _POOL.clear()
    if client is not None:
        client.close()
    if cluster is not None:
        cluster.close()


def client_for(scheduler: str | None, client: Client | None) -> tuple[Client, SpecCluster | None]:
    """The client to run on and the cluster to close after: `client` as given; a fresh
    :func:`local_cluster` for ``"local"`` / ``"local:N"``; else a client of the scheduler at
    the address `scheduler`."""
    if client is not None:
        return client, None
    if scheduler == "local" or str(scheduler).startswith("local:"):
        cluster = local_cluster(None if scheduler == "local" else int(scheduler.split(":", 1)[1]))
        return Client(cluster), cluster
    return Client(scheduler), None
