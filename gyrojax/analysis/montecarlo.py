"""Monte Carlo sweeps: ``vmap`` over draws, chunked for memory, sharded over all JAX devices.

``monte_carlo(fn, draws)`` evaluates ``fn`` (one draw -> a pytree of arrays) for every draw (a
pytree with a leading batch axis). Draws are processed in chunks of ``chunk_size`` (the last chunk
is padded, so the jitted batch function compiles once); each chunk is split over
``jax.devices()`` along a one-dimensional ``("batch",)`` mesh with ``jax.shard_map``, so every
device runs the batch function on its own slice with no communication (a vmapped ODE solve's
while loop never waits on another device's lanes). The same call uses every CPU device
(``XLA_FLAGS=--xla_force_host_platform_device_count=N``), GPU, or, under ``jax.distributed``,
every host. A progress bar (tqdm) advances between chunks.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["monte_carlo", "batch_size_of"]


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


def monte_carlo(fn: Callable, draws, *, chunk_size: int = 1024, devices=None,
                progress: bool | str = False, vectorized: bool = False):
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
      a trial at different batch sizes, e.g. a vmapped ODE solve over the whole slice (its
      per-step overhead shrinks with the batch) followed by ``jax.lax.map(identify, ys,
      batch_size=16)`` (the least-squares designs then stay in cache).

    With jaxlib 0.10.2 on the CPU, as many host devices as cores, and a graph that calls batched
    LAPACK (QR, SVD) outside any loop after an ODE solve, every device can end up waiting on the
    shared thread pool (a deadlock; docs/notes.md). Keep such solves inside ``jax.lax.map`` with
    at least two iterations per device, or run on one device.
    """
    n = batch_size_of(draws)
    devices = list(devices or jax.devices())
    nd = len(devices)
    chunk = max(nd, int(math.ceil(min(chunk_size, n) / nd)) * nd)
    mesh = Mesh(np.array(devices), ("batch",))
    sharding = NamedSharding(mesh, PartitionSpec("batch"))
    batched = _batched(fn, bool(vectorized), mesh)
    n_chunks = int(math.ceil(n / chunk))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, desc=progress if isinstance(progress, str) else "monte carlo",
                   unit="draw")
    outs = []
    try:
        for i in range(n_chunks):
            lo, hi = i * chunk, min((i + 1) * chunk, n)

            def take(x, lo=lo, hi=hi):
                x = np.asarray(x)[lo:hi]
                if hi - lo < chunk:  # pad the last chunk by repeating its last draw
                    pad = np.repeat(x[-1:], chunk - (hi - lo), axis=0)
                    x = np.concatenate([x, pad], axis=0)
                return jax.device_put(jnp.asarray(x), sharding)

            out = batched(jax.tree.map(take, draws))
            outs.append(jax.tree.map(lambda y, k=hi - lo: np.asarray(y)[:k], out))
            if bar is not None:
                bar.update(hi - lo)
    finally:
        if bar is not None:
            bar.close()
    return jax.tree.map(lambda *xs: np.concatenate(xs, axis=0), *outs)
