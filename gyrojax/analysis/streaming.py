"""Monte Carlo from keys to statistics: no host array of draws, no host array of outputs.

A study is a **draw** function ``draw(key) -> draw`` and a **trial** function
``trial(draw) -> pytree of arrays``. Trial ``i`` uses the key ``jax.random.fold_in(key, i)``, so
any trial can be recomputed alone and no draw exists on the host. Trials run in fixed **blocks**
of ``block_size`` (the last one masked, so one compilation serves every block); each block is
reduced *inside its compiled program* to mergeable statistics per output element: count, mean,
the co-moment matrix (Chan, Golub & LeVeque's pairwise form), the mean and co-moment of the
squares (for the RMS and its standard error), min, max and, if asked, fixed-bin histograms (for
quantiles). The client merges the blocks **in block order**, whoever computed them, so the result
is bit-identical for any number of workers or devices and for the plain in-process call.

Engines (``scheduler``): ``None`` runs the blocks in this process; ``"local"`` starts a
``distributed.LocalCluster`` with one single-threaded worker process per core; an address
(``"tcp://..."``) or ``client=`` runs the blocks as tasks on any Dask cluster (a laptop, an HPC
allocation through ``dask-jobqueue``, the cloud). Each worker receives the study once
(broadcast) and compiles its block program once; a lost worker's blocks are retried by Dask.
``resume=FILE`` keeps the statistics of every finished block in ``FILE`` (written atomically every
``checkpoint_s`` and when the run stops, an interrupt included); a later call with the same file
skips them.

Trials whose outputs are not finite are left out of the statistics and counted (``nonfinite``);
the result says how many.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

__all__ = ["monte_carlo_stats", "MonteCarloStats", "LeafStats", "merge_stats", "local_cluster",
           "WORKER_ENV"]

MAX_COV = 64
"""Leaves of up to this many elements keep their full covariance; larger ones its diagonal."""

_FIELDS = ("n", "nonfinite", "mean", "m2", "sq_mean", "sq_m2", "min", "max", "hist")


@dataclasses.dataclass(frozen=True)
class LeafStats:
    """Mergeable statistics of one output leaf (flattened to ``k`` elements) over ``n`` trials.

    - `n`: trials counted; `nonfinite`: trials left out (an element not finite).
    - `mean` ``(k,)``; `m2` ``(k, k)``: the co-moment sum ``sum (x - mean)(x - mean)^T``.
    - `sq_mean`, `sq_m2` ``(k,)``: the same for ``x**2`` elementwise (the RMS and its error).
    - `min`, `max` ``(k,)``.
    - `hist` ``(k, bins + 2)`` counts over `edges` (first and last: below and above them), or
      ``None``; `edges` ``(bins + 1,)``.
    - `shape`: the leaf's shape in one trial.
    """

    n: int
    nonfinite: int
    mean: np.ndarray
    m2: np.ndarray
    sq_mean: np.ndarray
    sq_m2: np.ndarray
    min: np.ndarray
    max: np.ndarray
    hist: np.ndarray | None
    edges: np.ndarray | None
    shape: tuple[int, ...]

    @property
    def var(self) -> np.ndarray:
        """Sample variance per element (``n - 1`` in the denominator)."""
        return np.diagonal(self.m2) / max(self.n - 1, 1)

    @property
    def cov(self) -> np.ndarray:
        """Sample covariance ``(k, k)``."""
        return self.m2 / max(self.n - 1, 1)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.var)

    @property
    def sem(self) -> np.ndarray:
        """Standard error of the mean (the bias)."""
        return np.sqrt(self.var / max(self.n, 1))

    @property
    def rms(self) -> np.ndarray:
        """Root mean square ``sqrt(mean(x**2))``."""
        return np.sqrt(self.sq_mean)

    @property
    def rms_se(self) -> np.ndarray:
        """Standard error of the RMS (delta method on the mean of the squares)."""
        se_sq = np.sqrt(self.sq_m2 / max(self.n - 1, 1) / max(self.n, 1))
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.rms > 0, se_sq / (2 * self.rms), 0.0)

    def quantile(self, q: float) -> np.ndarray:
        """The ``q`` quantile per element from the histogram (linear within a bin; ``nan`` where
        it falls below or above the edges). **Raises:** `ValueError` without a histogram."""
        if self.hist is None:
            raise ValueError("quantile: this study kept no histogram; pass bins= to "
                             "monte_carlo_stats")
        cdf = np.cumsum(self.hist, axis=1) / np.maximum(self.hist.sum(axis=1, keepdims=True), 1)
        out = np.full(self.hist.shape[0], np.nan)
        for j in range(self.hist.shape[0]):
            b = int(np.searchsorted(cdf[j], q, side="left"))
            if 1 <= b <= len(self.edges) - 1:
                lo = cdf[j, b - 1]
                frac = (q - lo) / max(cdf[j, b] - lo, 1e-300)
                out[j] = self.edges[b - 1] + frac * (self.edges[b] - self.edges[b - 1])
        return out

    def merge(self, other: LeafStats) -> LeafStats:
        """Chan, Golub & LeVeque's pairwise update: the statistics of both sets of trials."""
        n = self.n + other.n
        if other.n == 0 or self.n == 0:
            a = other if self.n == 0 else self
            return dataclasses.replace(a, nonfinite=self.nonfinite + other.nonfinite)
        d = other.mean - self.mean
        f = self.n * other.n / n
        dsq = other.sq_mean - self.sq_mean
        return LeafStats(
            n=n, nonfinite=self.nonfinite + other.nonfinite,
            mean=self.mean + d * (other.n / n), m2=self.m2 + other.m2 + f * np.outer(d, d),
            sq_mean=self.sq_mean + dsq * (other.n / n), sq_m2=self.sq_m2 + other.sq_m2 + f * dsq**2,
            min=np.minimum(self.min, other.min), max=np.maximum(self.max, other.max),
            hist=None if self.hist is None else self.hist + other.hist, edges=self.edges,
            shape=self.shape)


def merge_stats(blocks: list[dict]) -> dict:
    """Merge per-block statistics (``{leaf: LeafStats}``) left to right, in the order given."""
    out = dict(blocks[0])
    for b in blocks[1:]:
        out = {k: out[k].merge(b[k]) for k in out}
    return out


@dataclasses.dataclass(frozen=True)
class MonteCarloStats:
    """The outcome of :func:`monte_carlo_stats`: `leaves` ``{path: LeafStats}`` (paths as
    ``jax.tree_util.keystr`` gives them, e.g. ``"['joint']"``), `n_trials`, `block_size`,
    `n_blocks` and the blocks computed in this call (`computed`; the rest came from `resume`)."""

    leaves: dict
    n_trials: int
    block_size: int
    n_blocks: int
    computed: int

    def __getitem__(self, path: str) -> LeafStats:
        return self.leaves[path]

    @property
    def nonfinite(self) -> int:
        return max(s.nonfinite for s in self.leaves.values())

    def to_xarray(self, quantiles=(0.5, 0.9, 0.99)):
        """An ``xarray.Dataset``: per leaf, over its element dimension, the mean (bias) and its
        standard error, the standard deviation, the RMS and its standard error, min, max, and
        (with a histogram) the quantiles ``quantiles``."""
        import xarray as xr

        data = {}
        for path, s in self.leaves.items():
            name = path.strip("[]'\"").replace("']['", ".") or "out"
            dim = f"{name}_element"
            for stat, val in (("mean", s.mean), ("mean_se", s.sem), ("std", s.std),
                              ("rms", s.rms), ("rms_se", s.rms_se), ("min", s.min),
                              ("max", s.max)):
                data[f"{name}_{stat}"] = ((dim,), np.asarray(val))
            if s.hist is not None:
                data[f"{name}_quantile"] = (("quantile", dim),
                                            np.stack([s.quantile(q) for q in quantiles]))
        coords = {"quantile": list(quantiles)} if any(
            s.hist is not None for s in self.leaves.values()) else {}
        return xr.Dataset(data, coords=coords,
                          attrs={"n_trials": self.n_trials, "nonfinite": self.nonfinite,
                                 "block_size": self.block_size})


_PROGRAMS: dict = {}
"""Compiled block programs of this process (the caller's, or a Dask worker's), by study token:
a second study with the same functions, block size and bins reuses one, whatever its key and
number of trials (both are arguments of the program)."""
_MAX_PROGRAMS = 16


class _Study:
    """What every worker needs, sent once: the functions, the key, the sizes, the bins, and the
    token its compiled block program is kept under."""

    def __init__(self, trial, draw, key_data, impl, n, block_size, bins, vectorized):
        import cloudpickle

        self.trial, self.draw, self.vectorized = trial, draw, vectorized
        self.key_data, self.impl = key_data, impl
        self.n, self.block_size, self.bins = n, block_size, bins
        h = hashlib.sha256(cloudpickle.dumps((trial, draw)))
        h.update(f"{impl}|{block_size}|{vectorized}".encode())
        if bins is not None:
            h.update(np.asarray(bins, float).tobytes())
        self.token = h.hexdigest()

    def block(self, index: int) -> dict:
        prog = _PROGRAMS.get(self.token)
        if prog is None:
            if len(_PROGRAMS) >= _MAX_PROGRAMS:
                _PROGRAMS.pop(next(iter(_PROGRAMS)))
            prog = _PROGRAMS[self.token] = _block_program(
                self.trial, self.draw, self.impl, self.block_size, self.bins, self.vectorized)
        out = prog(jnp.asarray(self.key_data), jnp.asarray(self.n),
                   jnp.asarray(index * self.block_size))
        return _host_block(jax.device_get(out), self.bins)


def _block_program(trial, draw, impl, b, bins, vectorized):
    """One block's statistics as a compiled function of ``(key_data, n, start)``."""

    @jax.jit
    def run(key_data, n, start):
        key = jax.random.wrap_key_data(key_data, impl=impl)
        idx = start + jnp.arange(b)
        valid = idx < n
        keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.minimum(idx, n - 1))
        draws = jax.vmap(draw)(keys)
        outs = trial(draws) if vectorized else jax.vmap(trial)(draws)
        return jax.tree.map(lambda x: _reduce(x.reshape(b, -1), valid, bins), outs)

    return run


class _BlockStats(NamedTuple):
    """One leaf's statistics over one block, as the compiled program returns them."""

    n: jax.Array
    nonfinite: jax.Array
    mean: jax.Array
    m2: jax.Array
    sq_mean: jax.Array
    sq_m2: jax.Array
    min: jax.Array
    max: jax.Array
    hist: jax.Array | None


def _reduce(x, valid, bins) -> _BlockStats:
    """One block's statistics of ``x`` ``(B, k)`` over the rows ``valid`` and finite."""
    ok = valid & jnp.all(jnp.isfinite(x), axis=1)
    w = ok.astype(x.dtype)
    x0 = jnp.where(ok[:, None], x, 0.0)
    cnt = jnp.sum(w)
    mean = jnp.sum(x0, axis=0) / jnp.maximum(cnt, 1.0)
    d = (x0 - mean) * w[:, None]
    # elementwise products summed (no dot: the same bits whatever XLA's thread count); the
    # full co-moment matrix for leaves of up to MAX_COV elements, its diagonal beyond
    if x.shape[1] <= MAX_COV:
        m2 = jnp.sum(d[:, :, None] * d[:, None, :], axis=0)
    else:
        m2 = jnp.diag(jnp.sum(d * d, axis=0))
    sq = x0 * x0
    sq_mean = jnp.sum(sq, axis=0) / jnp.maximum(cnt, 1.0)
    sq_m2 = jnp.sum(((sq - sq_mean) * w[:, None]) ** 2, axis=0)
    lo = jnp.min(jnp.where(ok[:, None], x, jnp.inf), axis=0)
    hi = jnp.max(jnp.where(ok[:, None], x, -jnp.inf), axis=0)
    hist = None
    if bins is not None:
        idx = jnp.searchsorted(jnp.asarray(bins), x0, side="right")  # 0: below, len: above
        cols = jnp.broadcast_to(jnp.arange(x.shape[1]), idx.shape)
        hist = jnp.zeros((x.shape[1], len(bins) + 1), x.dtype).at[cols, idx].add(
            jnp.broadcast_to(w[:, None], idx.shape))
    return _BlockStats(cnt, jnp.sum(valid & ~ok), mean, m2, sq_mean, sq_m2, lo, hi, hist)


def _host_block(tree, bins) -> dict:
    """The block's statistics as ``{path: LeafStats}`` (numpy)."""
    flat, _ = jax.tree_util.tree_flatten_with_path(
        tree, is_leaf=lambda x: isinstance(x, _BlockStats))
    out = {}
    for path, s in flat:
        k = np.asarray(s.mean).shape[0]
        out[jax.tree_util.keystr(path)] = LeafStats(
            n=int(s.n), nonfinite=int(s.nonfinite), mean=np.asarray(s.mean), m2=np.asarray(s.m2),
            sq_mean=np.asarray(s.sq_mean), sq_m2=np.asarray(s.sq_m2), min=np.asarray(s.min),
            max=np.asarray(s.max), hist=None if s.hist is None else np.asarray(s.hist),
            edges=None if bins is None else np.asarray(bins), shape=(k,))
    return out


class _Finished:
    """The finished blocks: those of the contiguous prefix ``0 .. prefix_n - 1`` merged as they
    arrive (left to right, the same fold as merging every block at the end, so the same bits),
    and the blocks beyond a gap kept apart until it closes. Memory and the resume file stay the
    size of a few blocks however many are done."""

    def __init__(self, prefix_n: int = 0, prefix: dict | None = None, pending=None):
        self.prefix_n, self.prefix, self.pending = prefix_n, prefix, dict(pending or {})

    def __contains__(self, index: int) -> bool:
        return index < self.prefix_n or index in self.pending

    def __len__(self) -> int:
        return self.prefix_n + len(self.pending)

    def add(self, index: int, stats: dict) -> None:
        self.pending[index] = stats
        while self.prefix_n in self.pending:
            block = self.pending.pop(self.prefix_n)
            self.prefix = block if self.prefix is None else merge_stats([self.prefix, block])
            self.prefix_n += 1

    def merged(self) -> dict:
        blocks = ([] if self.prefix is None else [self.prefix]) + [
            self.pending[i] for i in sorted(self.pending)]
        return merge_stats(blocks)


# -- the resume file -------------------------------------------------------------------------

def _fingerprint(study: _Study) -> str:
    h = hashlib.sha256()
    h.update(np.asarray(study.key_data).tobytes())
    h.update(f"{study.impl}|{study.n}|{study.block_size}|{study.vectorized}".encode())
    if study.bins is not None:
        h.update(np.asarray(study.bins, float).tobytes())
    return h.hexdigest()[:16]


def _load_resume(path: Path, fingerprint: str) -> _Finished:
    if not path.exists():
        return _Finished()
    with np.load(path, allow_pickle=False) as z:
        got = str(z["fingerprint"])
        if got != fingerprint:
            raise ValueError(
                f"resume: {path} holds another study (fingerprint {got}, this one {fingerprint}: "
                "key, number of trials, block size or bins differ); give a new file or the "
                "same study")
        prefix_n = int(z["prefix_n"])
        blocks = {}
        for name in z.files:
            if "|" not in name:
                continue
            index, leaf, field = name.split("|", 2)
            blocks.setdefault(index, {}).setdefault(leaf, {})[field] = z[name]
    stats = {i: {leaf: _leaf_from(d) for leaf, d in b.items()} for i, b in blocks.items()}
    return _Finished(prefix_n, stats.pop("prefix", None), {int(i): b for i, b in stats.items()})


def _leaf_from(d: dict) -> LeafStats:
    hist = d.get("hist")
    return LeafStats(n=int(d["n"]), nonfinite=int(d["nonfinite"]), mean=d["mean"], m2=d["m2"],
                     sq_mean=d["sq_mean"], sq_m2=d["sq_m2"], min=d["min"], max=d["max"],
                     hist=hist, edges=d.get("edges"), shape=tuple(int(v) for v in d["shape"]))


def _save_resume(path: Path, fingerprint: str, finished: _Finished) -> None:
    from ..io import atomic_write

    arrays = {"fingerprint": np.asarray(fingerprint), "prefix_n": np.asarray(finished.prefix_n)}
    named = {str(i): b for i, b in finished.pending.items()}
    if finished.prefix is not None:
        named["prefix"] = finished.prefix
    for name, leaves in named.items():
        for leaf, s in leaves.items():
            for f in _FIELDS + ("edges",):
                v = getattr(s, f)
                if v is not None:
                    arrays[f"{name}|{leaf}|{f}"] = np.asarray(v)
            arrays[f"{name}|{leaf}|shape"] = np.asarray(s.shape)

    def write(tmp):
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)

    atomic_write(path, write)


# -- engines ---------------------------------------------------------------------------------

def _run_block(study: _Study, index: int):
    """A Dask task: one block's statistics (``study`` arrives once per worker)."""
    return index, study.block(index)


WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}
"""The environment of :func:`local_cluster`'s workers: one thread for BLAS and XLA's Eigen (a
trial's least-squares problems are small; threads on top of one process per core contend)."""


def local_cluster(n_workers: int | None = None):
    """A ``distributed.LocalCluster`` of `n_workers` single-threaded worker processes (default:
    one per core this process may use), with :data:`WORKER_ENV`; close it (or use it as a
    context manager) when done."""
    from distributed import LocalCluster

    if n_workers is None:
        n_workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") \
            else os.cpu_count()
    return LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                        dashboard_address=":0", env=WORKER_ENV)


def _client_for(scheduler, client):
    if client is not None:
        return client, None
    from distributed import Client

    if scheduler == "local" or str(scheduler).startswith("local:"):
        cluster = local_cluster(None if scheduler == "local" else int(scheduler.split(":", 1)[1]))
        return Client(cluster), cluster
    return Client(scheduler), None


def monte_carlo_stats(trial: Callable, draw: Callable, key: PRNGKeyArray, n: int, *,
                      block_size: int = 1024, bins=None, scheduler: str | None = None,
                      client=None, resume: str | os.PathLike | None = None,
                      checkpoint_s: float = 30.0, progress: bool = False,
                      stop_after: int | None = None, vectorized: bool = False,
                      on_block: Callable[[int, int], None] | None = None) -> MonteCarloStats:
    """Run ``n`` trials and return their statistics, never their outputs.

    **Arguments:**
    - `trial`: ``draw -> pytree of arrays`` (one trial; JAX-traceable). Close over constants.
    - `draw`: ``key -> draw`` (one trial's random inputs from its key).
    - `key`: a typed ``jax.random`` key; trial ``i`` gets ``fold_in(key, i)``.
    - `n`: number of trials (> 0).
    - `block_size`: trials per compiled block, the unit of work and of reduction; the result
      depends on it only through floating-point rounding (not on workers or devices).
    - `bins`: histogram edges ``(bins + 1,)`` (increasing) applied to every output element, for
      quantiles; ``None``: no histogram.
    - `scheduler`: ``None`` (this process), ``"local"`` (a ``distributed.LocalCluster``, one
      single-threaded worker process per core, closed at the end), ``"local:N"`` (``N``
      workers) or a scheduler address.
    - `client`: an existing ``distributed.Client`` (takes precedence over `scheduler`).
    - `resume`: a file keeping the finished blocks' statistics (those of the contiguous prefix
      merged into one); blocks already there are skipped. **Raises** `ValueError` if it holds
      another study.
    - `checkpoint_s`: seconds between writes of `resume`.
    - `progress`: a progress bar over blocks (tqdm), a "compiling" line until the first block
      returns, and the Dask dashboard's address when there is one.
    - `stop_after`: compute at most this many blocks in this call, then return the statistics
      of the blocks done so far (for tests and for budgets run in pieces).
    - `vectorized`: `trial` maps a batch of draws (leading axis) to a batch of outputs, e.g.
      :func:`~gyrojax.analysis.staged` (a vmapped ODE solve, then small least-squares problems
      in cache-sized sub-batches); otherwise it is vmapped over the block.
    - `on_block`: called as ``on_block(index, done)`` after each block arrives (``done``: blocks
      finished so far, resumed ones included).

    **Returns:** a :class:`MonteCarloStats`.
    """
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n <= 0:
        raise ValueError(f"monte_carlo_stats: n={n!r}; give a positive number of trials")
    if isinstance(block_size, bool) or not isinstance(block_size, int | np.integer) \
            or block_size <= 0:
        raise ValueError(f"monte_carlo_stats: block_size={block_size!r}; give a positive "
                         "integer (e.g. 1024)")
    if not (hasattr(key, "dtype") and jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key)):
        raise ValueError("monte_carlo_stats: key must be a typed key, jax.random.key(seed)")
    if bins is not None:
        bins = np.asarray(bins, float)
        if bins.ndim != 1 or len(bins) < 2 or not np.all(np.diff(bins) > 0):
            raise ValueError("monte_carlo_stats: bins must be increasing edges (at least 2)")
    study = _Study(trial, draw, np.asarray(jax.random.key_data(key)),
                   str(jax.random.key_impl(key)), int(n), int(block_size), bins, vectorized)
    n_blocks = math.ceil(n / block_size)
    path = None if resume is None else Path(resume)
    fingerprint = _fingerprint(study)
    done = _load_resume(path, fingerprint) if path is not None else _Finished()
    todo = [i for i in range(n_blocks) if i not in done]
    if stop_after is not None:
        todo = todo[:max(int(stop_after), 0)]
    bar = None
    last_save = time.monotonic()
    computed = 0

    def record(index, stats):
        nonlocal last_save, computed
        nonlocal bar
        done.add(index, stats)
        computed += 1
        if progress and bar is None:  # after the "compiling" line, at the first block
            bar = _progress_bar(n_blocks, len(done) - 1)
        if bar is not None:
            bar.update(1)
        if on_block is not None:
            on_block(index, len(done))
        if path is not None and time.monotonic() - last_save > checkpoint_s:
            _save_resume(path, fingerprint, done)
            last_save = time.monotonic()

    try:
        if scheduler is None and client is None:
            if progress and todo:
                print("monte_carlo_stats: compiling the block program...", flush=True)
            for i in todo:
                record(i, study.block(i))
        else:
            _run_dask(study, todo, scheduler, client, record, progress)
    finally:
        if path is not None and computed:
            _save_resume(path, fingerprint, done)
        if bar is not None:
            bar.close()
    if not done:
        raise ValueError("monte_carlo_stats: no block was computed (stop_after=0 and nothing "
                         "to resume)")
    leaves = done.merged()
    return MonteCarloStats(leaves=leaves, n_trials=int(n), block_size=int(block_size),
                           n_blocks=n_blocks, computed=computed)


def _run_dask(study, todo, scheduler, client, record, progress):
    from distributed import as_completed

    cl, cluster = _client_for(scheduler, client)
    try:
        if progress:
            print(f"monte_carlo_stats: Dask dashboard {cl.dashboard_link}", flush=True)
            print("monte_carlo_stats: compiling the block program on each worker...", flush=True)
        if not todo:
            return
        shared = cl.scatter(study, broadcast=True, hash=False)
        futures = cl.map(_run_block, [shared] * len(todo), todo, pure=False, retries=3)
        for fut in as_completed(futures):
            index, stats = fut.result()
            record(index, stats)
    finally:
        if cluster is not None:
            cl.close()
            cluster.close()


def _progress_bar(total: int, initial: int):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="block", desc="Monte Carlo")


def _stats_equal(a: Mapping, b: Mapping) -> bool:
    """Bit-for-bit equality of two ``{path: LeafStats}`` (for the tests)."""
    if a.keys() != b.keys():
        return False
    for k in a:
        for f in _FIELDS:
            x, y = getattr(a[k], f), getattr(b[k], f)
            if (x is None) != (y is None) or (x is not None and not np.array_equal(x, y)):
                return False
    return True
