"""Monte Carlo sweeps: ``vmap`` over draws, chunked for memory, sharded over all JAX devices.

``monte_carlo(fn, draws)`` evaluates ``fn`` (one draw -> a pytree of arrays) for every draw (a
pytree with a leading batch axis). Draws are processed in chunks of ``chunk_size`` (the last chunk
is padded, so the jitted batch function compiles once); each chunk is split over ``jax.devices()``
along a one-dimensional ``("batch",)`` mesh with ``jax.shard_map``, so every device runs the batch
function on its own slice with no communication (a vmapped ODE solve's while loop never waits on
another device's lanes). The same call uses every CPU device
(``XLA_FLAGS=--xla_force_host_platform_device_count=N``) or GPU of this process. On the CPU,
``processes=k`` instead hands the chunks to ``k`` Dask worker processes, one pinned to each core
(one process's graph runs on one core; :mod:`gyrojax.analysis.cluster`), and ``client=`` to any
Dask cluster. For budgets too large to keep every output,
:func:`~gyrojax.analysis.monte_carlo_stats` reduces them to statistics where they are computed.
A progress bar (tqdm) advances between chunks. During the run BLAS/LAPACK (OpenBLAS, through
``threadpoolctl``) uses one thread: a trial's least-squares problems are small, and jaxlib
already spreads a batch's LAPACK calls over XLA's threads.
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import PyTree
from threadpoolctl import threadpool_limits

__all__ = ["monte_carlo", "batch_size_of", "staged", "shutdown_processes"]


@functools.lru_cache(maxsize=64)
def _batched(fn, vectorized: bool, mesh: Mesh):
    """One compiled batch function per ``fn`` and mesh (repeated calls do not recompile)."""
    local = fn if vectorized else jax.vmap(fn)
    spec = PartitionSpec("batch")
    return eqx.filter_jit(jax.shard_map(local, mesh=mesh, in_specs=spec, out_specs=spec,
                                        check_vma=False))


def batch_size_of(draws) -> int:
    leaves = jax.tree.leaves(draws)
    if not leaves:
        raise ValueError("monte_carlo: draws is an empty pytree")
    sizes = {np.shape(x)[0] for x in leaves}
    if len(sizes) != 1:
        raise ValueError(f"monte_carlo: draws have different leading (batch) sizes {sorted(sizes)}")
    return sizes.pop()


def staged(first: Callable, second: Callable, *, batch_size: int = 8) -> Callable:
    """A batch trial function for ``monte_carlo(..., vectorized=True)`` from two stages.

    ``first(draw)`` (e.g. an ODE solve) is vmapped over the whole batch: a vmapped adaptive
    solver shares its per-step overhead among the lanes, ~2.5x cheaper per trajectory at 512
    lanes than at 32 for the ESG rig. ``second(draw, first_out)`` (e.g. a least-squares
    identification) runs under ``jax.lax.map`` in sub-batches of at most ``batch_size`` (a
    divisor of the batch, so there is no remainder pass), which keeps its designs in cache
    (~2x cheaper than one vmap over 512). Returns ``second``'s outputs stacked over the batch.

    Work whose output is as large as ``first``'s but cheap to make belongs in ``second``, e.g.
    the measurement noise added to a simulated record: drawn in ``first`` it is written for the
    whole batch and read back, drawn in ``second`` it stays in cache with its sub-batch (the
    ESG benchmark's trial ~15 % faster, docs/decisions/0006-esg-monte-carlo-hot-path.md).
    """

    def trials(draws):
        n = batch_size_of(draws)
        bs = max(b for b in range(1, min(batch_size, n) + 1) if n % b == 0)
        return jax.lax.map(lambda x: second(*x), (draws, jax.vmap(first)(draws)), batch_size=bs)

    return trials


def monte_carlo(fn: Callable, draws: PyTree, *, chunk_size: int = 1024, devices=None,
                progress: bool | str = False, vectorized: bool = False,
                blas_threads: int | None = 1, processes: int | str | None = None,
                client=None):
    """Evaluate ``fn`` on every draw; returns the stacked outputs as numpy arrays.

    **Arguments:**
    - `fn`: maps one draw (pytree without the batch axis) to a pytree of arrays. Close over
      constants (rig, sample times...). Pass the same function object again to reuse its
      compilation.
    - `draws`: a pytree whose leaves share the leading batch size ``N``.
    - `chunk_size`: draws per compiled batch (rounded up to a multiple of the device count);
      bounds memory: 100,000 draws run as ``ceil(N / chunk_size)`` chunks.
    - `devices`: devices to shard each chunk over (default all of ``jax.devices()``).
    - `progress`: show a tqdm bar (a string is used as its label).
    - `vectorized`: ``fn`` already maps a batch of draws (leading axis) to a batch of outputs, and
      is called on each device's slice of a chunk as is (not vmapped). Use it to run the stages of
      a trial at different batch sizes, e.g. :func:`staged` (simulate vmapped over the slice,
      identify in cache-sized sub-batches).
    - `blas_threads`: threads BLAS/LAPACK may use during the run (``None``: leave the setting
      alone). jaxlib's CPU LAPACK kernels (scipy's OpenBLAS) loop over a batch's small problems
      (the ESG regression's 1440 x 11 QRs) spread over XLA's threads; OpenBLAS's own threads on
      top only contend: on 2 cores one thread ran the ESG benchmark's trials 1.45x faster
      (docs/decisions/0006-esg-monte-carlo-hot-path.md). Restored when the call returns.
    - `processes`: run the chunks on this many Dask worker processes of this machine instead
      (CPU only; :func:`~gyrojax.analysis.cluster.pool_client`), each pinned to one core and
      running its chunks on its own CPU device; ``"all"``: one per core this process may use.
      ``None`` (default): in this process. This is how a CPU Monte Carlo uses every core: one
      process runs a trial's graph on one core, and several host devices in one process
      deadlock jaxlib 0.10.2's batched LAPACK (below). The workers stay up between calls and
      keep their compiled batch functions by a token of ``fn`` (pickled by value with
      ``cloudpickle``), so calling again with the same ``fn`` compiles nothing
      (:func:`shutdown_processes` stops them).
    - `client`: a ``distributed.Client``: run the chunks as tasks on its cluster (any Dask
      cluster: a scheduler address, ``dask-jobqueue`` on SLURM or PBS), compiled once per
      worker as with `processes`.

    **Raises:** ``ValueError`` naming a bad `chunk_size`, `blas_threads` or `processes`;
    ``TypeError`` if `processes` or `client` is given and ``fn`` cannot be pickled;
    ``RuntimeError`` naming the chunk whose trial failed on a worker, with the worker's error.

    With jaxlib 0.10.2 on the CPU and several host devices, a graph with batched LAPACK calls
    (QR, SVD: every least-squares fit) can deadlock: each device's LAPACK call waits on the shared
    thread pool (docs/decisions/0007-monte-carlo-worker-processes.md). Run such graphs on one
    device (``devices=jax.devices()[:1]``), or on several cores with ``processes``.
    """
    n = batch_size_of(draws)
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int | np.integer) \
            or chunk_size < 1:
        raise ValueError(f"monte_carlo: chunk_size={chunk_size!r}; give the draws per compiled "
                         "batch as a positive int (e.g. 512)")
    if blas_threads is not None and (not isinstance(blas_threads, int) or blas_threads < 1):
        raise ValueError(f"monte_carlo: blas_threads={blas_threads!r}; give a positive int "
                         "(threads for BLAS/LAPACK during the run) or None to leave it alone")
    workers = _worker_count(processes, devices, client)
    if workers is None:
        devices = list(devices or jax.devices())
        nd = len(devices)
        chunk = max(nd, int(math.ceil(min(chunk_size, n) / nd)) * nd)
    else:  # balance the chunks over the workers; each worker has one device
        chunk = min(chunk_size, int(math.ceil(n / workers)))
    n_chunks = int(math.ceil(n / chunk))
    bounds = [(i * chunk, min((i + 1) * chunk, n)) for i in range(n_chunks)]
    host = jax.tree.map(np.asarray, draws)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, desc=progress if isinstance(progress, str) else "monte carlo",
                   unit="draw")
        bar.set_postfix_str("compiling")  # cleared when the first chunk returns
    try:
        if workers is None:
            outs = _run_here(fn, host, bounds, chunk, devices, bool(vectorized), blas_threads,
                             bar)
        else:
            outs = _run_dask(fn, host, bounds, chunk, bool(vectorized), blas_threads,
                             client, workers, bar)
    finally:
        if bar is not None:
            bar.close()
    outs = [jax.tree.map(lambda y, k=hi - lo: np.asarray(y)[:k], out)
            for out, (lo, hi) in zip(outs, bounds, strict=True)]
    return jax.tree.map(lambda *xs: np.concatenate(xs, axis=0), *outs)


def shutdown_processes():
    """Stop the worker processes of ``monte_carlo(..., processes=...)`` (they start again on the
    next such call; they also stop when Python exits)."""
    from .cluster import shutdown_pool

    shutdown_pool()


def _worker_count(processes, devices, client) -> int | None:
    """Workers to balance the chunks over (``None``: run in this process)."""
    if processes is None and client is None:
        return None
    if devices is not None:
        raise ValueError("monte_carlo: give devices (shard each chunk in this process) or "
                         "processes/client (worker processes), not both")
    if client is not None:
        if processes is not None:
            raise ValueError("monte_carlo: give processes (a cluster of this machine) or client "
                             "(a cluster of yours), not both")
        return max(1, sum(w["nthreads"] for w in client.scheduler_info()["workers"].values()))
    if processes != "all" and (isinstance(processes, bool) or not isinstance(processes, int)
                               or processes < 1):
        raise ValueError(f"monte_carlo: processes={processes!r}; give a positive int, 'all' "
                         "(one worker process per core) or None (run in this process)")
    if jax.default_backend() != "cpu":
        raise ValueError(f"monte_carlo: processes={processes!r} runs CPU worker processes, but "
                         f"JAX's backend here is {jax.default_backend()!r}; use devices= (every "
                         "device of this backend by default) and processes=None")
    if processes == "all":
        from .cluster import available_cores

        return len(available_cores())
    return processes


def _padded(host, lo: int, hi: int, chunk: int):
    """Draws ``lo:hi`` of every leaf, padded to ``chunk`` by repeating the last draw (so every
    chunk has the compiled shape)."""

    def take(x):
        x = x[lo:hi]
        if hi - lo < chunk:
            x = np.concatenate([x, np.repeat(x[-1:], chunk - (hi - lo), axis=0)], axis=0)
        return x

    return jax.tree.map(take, host)


def _advance(bar, k: int) -> None:
    """Move the progress bar on by ``k`` draws (and clear its "compiling" note)."""
    if bar is not None:
        if bar.n == 0:
            bar.set_postfix_str("")
        bar.update(k)


def _blas_limit(blas_threads):
    return (contextlib.nullcontext() if blas_threads is None
            else threadpool_limits(blas_threads, user_api="blas"))


def _run_here(fn, host, bounds, chunk, devices, vectorized, blas_threads, bar):
    mesh = Mesh(np.array(devices), ("batch",))
    sharding = NamedSharding(mesh, PartitionSpec("batch"))
    batched = _batched(fn, vectorized, mesh)
    outs = []
    with _blas_limit(blas_threads):
        for lo, hi in bounds:
            chunk_draws = jax.tree.map(lambda x: jax.device_put(jnp.asarray(x), sharding),
                                       _padded(host, lo, hi, chunk))
            outs.append(jax.tree.map(np.asarray, batched(chunk_draws)))
            _advance(bar, hi - lo)
    return outs


class _Chunks:
    """What a Dask worker needs to run ``monte_carlo``'s chunks, sent to it once; the compiled
    batch function is kept in the worker by a token of ``fn``, the chunk and ``vectorized``."""

    def __init__(self, fn, chunk: int, vectorized: bool, blas_threads):
        from .streaming import token_of

        self.fn, self.vectorized, self.blas_threads = fn, vectorized, blas_threads
        self.token = token_of("chunks", fn, chunk, vectorized)

    def run(self, draws):
        from .streaming import cached_program

        batched = cached_program(self.token, lambda: _batched.__wrapped__(
            self.fn, self.vectorized, Mesh(np.array(jax.devices()[:1]), ("batch",))))
        with _blas_limit(self.blas_threads):
            return jax.tree.map(np.asarray, batched(jax.tree.map(jnp.asarray, draws)))


def _run_chunk(job: _Chunks, index: int, draws):
    """A Dask task: one chunk's outputs."""
    return index, job.run(draws)


def _run_dask(fn, host, bounds, chunk, vectorized, blas_threads, client, workers, bar):
    from distributed import as_completed

    from .cluster import pool_client

    job = _Chunks(fn, chunk, vectorized, blas_threads)  # raises TypeError if not picklable
    cl = client if client is not None else pool_client(workers)
    shared = cl.scatter(job, broadcast=True, hash=False)
    futures = [cl.submit(_run_chunk, shared, i, _padded(host, lo, hi, chunk), pure=False)
               for i, (lo, hi) in enumerate(bounds)]
    outs = [None] * len(bounds)
    try:
        for fut in as_completed(futures):
            try:
                i, out = fut.result()
            except Exception as e:  # noqa: BLE001 - the trial's own error, re-raised with where
                i = futures.index(fut)
                raise RuntimeError(f"monte_carlo: chunk {i} (draws {bounds[i][0]}-"
                                   f"{bounds[i][1] - 1}) failed on a Dask worker: "
                                   f"{type(e).__name__}: {e}") from e
            outs[i] = out
            _advance(bar, bounds[i][1] - bounds[i][0])
    finally:
        cl.cancel([f for f in futures if not f.done()])
    return outs
