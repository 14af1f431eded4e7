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

Engines (``scheduler``): ``None`` runs the blocks in this process (on ``devices``); ``"local"``
starts :func:`~gyrojax.analysis.cluster.local_cluster`, one pinned single-threaded worker process
per core; an address (``"tcp://..."``) or ``client=`` runs the blocks as tasks on any Dask
cluster (a laptop, an HPC allocation through ``dask-jobqueue``, the cloud). Each worker receives
the study once (broadcast) and compiles its block program once; a lost worker's blocks are
rescheduled by Dask (a block whose trial raises is not retried: the error reaches the caller).
``resume=FILE`` keeps the statistics of every finished block in ``FILE`` (written atomically every
``checkpoint_s`` and when the run stops, an interrupt included); a later call with the same file
skips them.

Trials whose outputs are not finite are left out of the statistics and counted (``nonfinite``);
the result says how many.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import math
import os
import re
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

__all__ = ["monte_carlo_stats", "MonteCarloStats", "LeafStats", "merge_stats", "load_outputs"]

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
"""Compiled programs of this process (the caller's, or a Dask worker's), by token: a second study
with the same functions, block size and bins reuses one, whatever its key and number of trials
(both are arguments of the program); a second ``monte_carlo`` call with the same trial function
and chunk reuses its batch function."""
_MAX_PROGRAMS = 16
_COMPILED = [0]  # programs built in this process (read by the tests through a host callback)


def token_of(*objs) -> str:
    """A hex digest of ``objs`` pickled by value (``cloudpickle``: closures, lambdas, notebook
    functions): equal for the same functions and constants, in any process.

    **Raises:** ``TypeError`` naming what cannot be pickled (e.g. a lock closed over)."""
    import cloudpickle

    try:
        return hashlib.sha256(cloudpickle.dumps(objs)).hexdigest()
    except Exception as e:  # noqa: BLE001 - pickling raises many types
        raise TypeError(f"the trial function cannot be pickled to send it to the workers: {e} "
                        "(close over arrays and plain values, not locks, files or clients)"
                        ) from e


def cached_program(token: str, build: Callable[[], Callable]) -> Callable:
    """This process's program under `token`, built by ``build()`` on first use (at most
    ``_MAX_PROGRAMS`` kept, the oldest dropped first)."""
    prog = _PROGRAMS.get(token)
    if prog is None:
        if len(_PROGRAMS) >= _MAX_PROGRAMS:
            _PROGRAMS.pop(next(iter(_PROGRAMS)))
        prog = _PROGRAMS[token] = build()
        _COMPILED[0] += 1
    return prog


class _Study:
    """What every worker needs, sent once: the functions, the key, the sizes, the bins, whether
    the per-trial outputs come back too, and the token its compiled block program is kept
    under."""

    def __init__(self, trial, draw, key_data, impl, n, block_size, bins, vectorized,
                 keep_outputs=False):
        self.trial, self.draw, self.vectorized = trial, draw, vectorized
        self.key_data, self.impl = key_data, impl
        self.n, self.block_size, self.bins = n, block_size, bins
        self.keep_outputs = keep_outputs
        self.token = token_of("block", trial, draw, impl, block_size, vectorized, keep_outputs,
                              None if bins is None else np.asarray(bins, float))

    def launch(self, index: int, device=None):
        """Start block `index` (on `device`, else JAX's default); returns its device arrays
        without waiting for them (JAX dispatches asynchronously)."""
        prog = cached_program(self.token, lambda: _block_program(
            self.trial, self.draw, self.impl, self.block_size, self.bins, self.vectorized,
            self.keep_outputs))
        args = (np.asarray(self.key_data), np.asarray(self.n),
                np.asarray(index * self.block_size))
        return prog(*(jnp.asarray(a) if device is None else jax.device_put(a, device)
                      for a in args))

    def finish(self, index: int, out) -> tuple[dict, object]:
        """Block `index`'s statistics ``{path: LeafStats}`` and its per-trial outputs (numpy,
        the trials past `n` dropped; ``None`` unless kept) from :meth:`launch`'s arrays."""
        stats, outs = jax.device_get(out)
        if outs is not None:
            k = min(self.block_size, self.n - index * self.block_size)
            outs = jax.tree.map(lambda x: np.asarray(x)[:k], outs)
        return _host_block(stats, self.bins), outs

    def block(self, index: int) -> tuple[dict, object]:
        return self.finish(index, self.launch(index))


def _block_program(trial, draw, impl, b, bins, vectorized, keep_outputs):
    """One block's statistics (and, if kept, its outputs) as a compiled function of
    ``(key_data, n, start)``."""

    @jax.jit
    def run(key_data, n, start):
        key = jax.random.wrap_key_data(key_data, impl=impl)
        idx = start + jnp.arange(b)
        valid = idx < n
        keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.minimum(idx, n - 1))
        draws = jax.vmap(draw)(keys)
        outs = trial(draws) if vectorized else jax.vmap(trial)(draws)
        stats = jax.tree.map(lambda x: _reduce(x.reshape(b, -1), valid, bins), outs)
        return stats, (outs if keep_outputs else None)

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
    """A Dask task: one block's statistics and kept outputs (``study`` arrives once per
    worker)."""
    return index, *study.block(index)


def monte_carlo_stats(trial: Callable, draw: Callable, key: PRNGKeyArray, n: int, *,
                      block_size: int = 1024, bins=None, scheduler: str | None = None,
                      client=None, resume: str | os.PathLike | None = None,
                      checkpoint_s: float = 30.0, progress: bool = False,
                      stop_after: int | None = None, vectorized: bool = False,
                      on_block: Callable[[int, int], None] | None = None, devices=None,
                      outputs: str | os.PathLike | None = None) -> MonteCarloStats:
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
    - `scheduler`: ``None`` (this process), ``"local"``
      (:func:`~gyrojax.analysis.cluster.local_cluster`: one pinned single-threaded worker
      process per core, closed at the end), ``"local:N"`` (``N`` workers) or a scheduler
      address.
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
    - `devices`: the JAX devices of this process to run blocks on when `scheduler` and `client`
      are ``None``: block ``i`` on ``devices[i % len(devices)]``, all of them busy at once
      (several GPUs); the statistics are the same bit for bit as on one device of the kind.
      Default: every device of JAX's default backend, but only the first CPU device (several
      host devices in one process deadlock jaxlib 0.10.2's batched LAPACK:
      docs/decisions/0007-monte-carlo-worker-processes.md; use `scheduler` ``"local"`` for
      every core).
    - `outputs`: a directory to keep every trial's outputs in too, one NetCDF file per block
      (``block-00000012.nc``, written atomically as the block arrives; never all in memory);
      :func:`load_outputs` opens them as one lazy ``xarray.Dataset``. For small studies: the
      files hold ``n`` times the outputs' size.

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
                   str(jax.random.key_impl(key)), int(n), int(block_size), bins, vectorized,
                   keep_outputs=outputs is not None)
    out_dir = None if outputs is None else Path(outputs)
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
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

    def record(index, stats, outs=None):
        nonlocal last_save, computed
        nonlocal bar
        if out_dir is not None:
            _write_outputs(out_dir, index, index * study.block_size, outs)
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
            _run_here(study, todo, _local_devices(devices), record)
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


def _local_devices(devices) -> list:
    if devices is not None:
        devices = list(devices)
        if not devices:
            raise ValueError("monte_carlo_stats: devices=[]; give at least one JAX device")
        return devices
    return jax.devices()[:1] if jax.default_backend() == "cpu" else jax.devices()


def _run_here(study, todo, devices, record):
    """The blocks in this process, block ``todo[j]`` on ``devices[j % len(devices)]``: as many
    in flight as there are devices (JAX dispatches asynchronously), collected in order."""
    in_flight = collections.deque()
    for j, i in enumerate(todo):
        in_flight.append((i, study.launch(i, devices[j % len(devices)]
                                          if len(devices) > 1 else None)))
        if len(in_flight) >= len(devices):
            i0, out = in_flight.popleft()
            record(i0, *study.finish(i0, out))
    while in_flight:
        i0, out = in_flight.popleft()
        record(i0, *study.finish(i0, out))


def _var_name(path) -> str:
    """An output leaf's variable name: ``['joint']`` -> ``joint``, ``[0]['a']`` -> ``o0_a``."""
    parts = re.findall(r"\w+", jax.tree_util.keystr(path))
    return "_".join(p if not p[0].isdigit() else f"o{p}" for p in parts) or "output"


def _write_outputs(directory: Path, index: int, start: int, outs) -> None:
    """Block `index`'s per-trial outputs as ``directory/block-{index:08d}.nc`` (atomically)."""
    import xarray as xr

    from ..io import atomic_write

    flat, _ = jax.tree_util.tree_flatten_with_path(outs)
    data = {}
    for path, x in flat:
        name = _var_name(path)
        data[name] = (("trial", *(f"{name}_dim{j}" for j in range(1, x.ndim))), x)
    k = len(flat[0][1])
    ds = xr.Dataset(data, coords={"trial": start + np.arange(k)})
    atomic_write(directory / f"block-{index:08d}.nc",
                 lambda tmp: ds.to_netcdf(tmp, engine="h5netcdf"))


def load_outputs(directory: str | os.PathLike):
    """The per-trial outputs kept by ``monte_carlo_stats(..., outputs=directory)`` as one lazy
    ``xarray.Dataset`` over ``trial`` (Dask-backed: nothing is read until asked).

    **Raises:** ``FileNotFoundError`` if `directory` holds no block file."""
    import xarray as xr

    files = sorted(Path(directory).glob("block-*.nc"))
    if not files:
        raise FileNotFoundError(f"load_outputs: no block-*.nc file in {str(directory)!r}; "
                                "run monte_carlo_stats(..., outputs=DIRECTORY) first")
    return xr.open_mfdataset(files, combine="nested", concat_dim="trial", engine="h5netcdf")


def _run_dask(study, todo, scheduler, client, record, progress):
    from distributed import as_completed

    from .cluster import client_for

    cl, cluster = client_for(scheduler, client)
    try:
        if progress:
            print(f"monte_carlo_stats: Dask dashboard {cl.dashboard_link}", flush=True)
            print("monte_carlo_stats: compiling the block program on each worker...", flush=True)
        if not todo:
            return
        shared = cl.scatter(study, broadcast=True, hash=False)
        futures = cl.map(_run_block, [shared] * len(todo), todo, pure=False)
        for fut in as_completed(futures):
            record(*fut.result())
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
