import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gyrojax.analysis.montecarlo import monte_carlo, shutdown_processes, staged
from gyrojax.analysis.mounting import mounting_error_budget


@pytest.fixture(scope="module", autouse=True)
def _stop_the_workers():
    """The kept local cluster of ``processes=`` serves this module's tests; stopped after them
    (idle workers still poll)."""
    yield
    shutdown_processes()


def test_chunked_monte_carlo_equals_direct_vmap(capsys):
    """Chunks (the last padded) give vmap's outputs; the progress bar says "compiling" until
    the first chunk returns, and counts every draw."""
    draws = {"a": jnp.arange(10.0), "b": jnp.arange(20.0).reshape(10, 2)}

    def fn(d):
        return {"s": d["a"] + d["b"].sum(), "v": d["b"] * d["a"]}

    out = monte_carlo(fn, draws, chunk_size=3, progress=True)  # 4 chunks, the last padded
    err = capsys.readouterr().err
    assert "compiling" in err and "10/10" in err, err
    ref = jax.vmap(fn)(draws)
    np.testing.assert_allclose(out["s"], ref["s"])
    np.testing.assert_allclose(out["v"], ref["v"])
    assert out["s"].shape == (10,)
    with pytest.raises(ValueError, match="different leading"):
        monte_carlo(fn, {"a": jnp.zeros(3), "b": jnp.zeros((4, 2))})


def test_vectorized_batch_function_equals_the_per_draw_function():
    """``vectorized=True`` calls a batch function on each chunk as is; here it maps its second
    stage in sub-batches with lax.map, and must give what vmap of the per-draw function gives."""
    draws = {"a": jnp.arange(37.0), "b": jnp.arange(74.0).reshape(37, 2)}

    def per_draw(d):
        return jnp.sin(d["a"]) + d["b"] @ jnp.array([1.0, -2.0])

    def batch(d):
        stage1 = jax.vmap(lambda x: jnp.sin(x["a"]))(d)
        stage2 = jax.lax.map(lambda b: b @ jnp.array([1.0, -2.0]), d["b"], batch_size=4)
        return stage1 + stage2

    out = monte_carlo(batch, draws, chunk_size=8, vectorized=True)  # 5 chunks, the last padded
    np.testing.assert_allclose(out, jax.vmap(per_draw)(draws), rtol=1e-14)
    assert out.shape == (37,)


def test_staged_trials_equal_the_composed_per_draw_function():
    """``staged(first, second)``: first vmapped over the batch, second in lax.map sub-batches
    (a divisor of the batch, here 37 -> 1 and 8 -> 8, 4 -> 4), same values as vmap of both."""
    draws = {"a": jnp.arange(37.0), "b": jnp.arange(74.0).reshape(37, 2)}

    def first(d):
        return jnp.sin(d["a"]) * d["b"]

    def second(d, y):
        return {"s": y.sum() + d["a"], "v": y * 2}

    ref = jax.vmap(lambda d: second(d, first(d)))(draws)
    for chunk in (37, 8, 4):
        out = monte_carlo(staged(first, second), draws, chunk_size=chunk, vectorized=True)
        np.testing.assert_allclose(out["s"], ref["s"], rtol=1e-14)
        np.testing.assert_allclose(out["v"], ref["v"], rtol=1e-14)


def test_blas_threads_limited_during_the_run_and_restored():
    """``monte_carlo`` runs with one BLAS/LAPACK thread by default (read inside the run through
    a host callback), leaves the setting alone with ``blas_threads=None``, restores it after,
    and rejects a bad value by name."""
    from threadpoolctl import threadpool_info, threadpool_limits

    def blas_threads():
        return max((i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"),
                   default=None)

    seen = []

    def fn(x):
        def probe(x):
            seen.append(blas_threads())
            return x
        return jax.pure_callback(probe, jax.ShapeDtypeStruct(x.shape, x.dtype), x)

    one = {"chunk_size": 4, "devices": jax.devices()[:1], "vectorized": True}
    with threadpool_limits(2, user_api="blas"):  # whatever the machine: 2 before the runs
        assert blas_threads() == 2  # scipy's OpenBLAS is loaded with jax's LAPACK
        out = monte_carlo(fn, np.arange(4.0), **one)
        np.testing.assert_array_equal(out, np.arange(4.0))
        monte_carlo(fn, np.arange(4.0), **one, blas_threads=None)
        assert seen == [1, 2] and blas_threads() == 2
    with pytest.raises(ValueError, match="blas_threads=0"):
        monte_carlo(fn, np.arange(4.0), blas_threads=0)


def test_sharded_over_two_host_devices():
    """The same call shards each chunk over every JAX device (here 2 forced CPU devices)."""
    code = textwrap.dedent("""
        import gyrojax, jax, jax.numpy as jnp, numpy as np
        from gyrojax.analysis.montecarlo import monte_carlo, staged
        assert len(jax.devices()) == 2, jax.devices()
        seen = []
        def fn(x):
            return jnp.sin(x) * 2
        out = monte_carlo(fn, jnp.arange(101.0), chunk_size=16)
        np.testing.assert_allclose(out, np.sin(np.arange(101.0)) * 2)
        print("OK", len(jax.devices()))
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    assert "OK 2" in res.stdout


def _qr_trial(c):
    """A trial with a small QR (the LAPACK call that deadlocks host devices in one process)
    whose output also carries how many batch functions its process has compiled so far (read
    at run time, in the worker, through a host callback)."""

    def compiled(x):
        from gyrojax.analysis.streaming import _COMPILED

        return np.full(x.shape, _COMPILED[0], dtype=np.int64)

    def fn(d):
        r = jnp.linalg.qr(jnp.outer(d["b"], c))[1]
        n = jax.pure_callback(compiled, jax.ShapeDtypeStruct((), jnp.int64), d["a"],
                              vmap_method="broadcast_all")
        return {"y": jnp.sin(d["a"]) * c.sum() + d["b"][0], "r": r[0, 0], "compiled": n}

    return fn


def test_worker_processes_equal_this_process_and_compile_once():
    """``processes=2``: the chunks (101 draws in chunks of 16, the last padded) run on two Dask
    worker processes and give the in-process outputs bit for bit; a second call with the same
    function compiles nothing new in the workers, a new function once."""
    c = jnp.linspace(0.0, 1.0, 5)
    fn = _qr_trial(c)
    draws = {"a": np.arange(101.0), "b": np.arange(202.0).reshape(101, 2)}
    ref = monte_carlo(fn, draws, chunk_size=16)
    first = monte_carlo(fn, draws, chunk_size=16, processes=2, progress=True)
    second = monte_carlo(fn, draws, chunk_size=16, processes=2)
    for out in (first, second):
        for k in ("y", "r"):
            np.testing.assert_array_equal(out[k], ref[k])
    assert second["compiled"].max() == first["compiled"].max() >= 1
    # a new function object goes to the workers and compiles there once
    third = monte_carlo(_qr_trial(jnp.ones(5)), draws, chunk_size=16, processes=2)
    assert third["compiled"].max() == first["compiled"].max() + 1
    np.testing.assert_allclose(third["y"], np.sin(draws["a"]) * 5 + draws["b"][:, 0],
                               rtol=1e-14)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 cores to pin 2 workers")
def test_worker_processes_are_pinned_one_per_core():
    """Each worker runs on one core of this process's affinity set, a different one each (read
    inside the run through a host callback)."""

    def fn(x):
        def where(x):
            return np.full(x.shape, min(os.sched_getaffinity(0)) + 100 * (
                len(os.sched_getaffinity(0)) - 1), dtype=x.dtype)
        return jax.pure_callback(where, jax.ShapeDtypeStruct(x.shape, x.dtype), x)

    cores = sorted(os.sched_getaffinity(0))[:2]
    out = monte_carlo(fn, np.arange(64.0), chunk_size=4, processes=2, vectorized=True)
    assert set(out.tolist()) == set(float(c) for c in cores), out  # one core each, both used


def test_an_unguarded_script_runs_once_with_worker_processes(tmp_path):
    """A script without ``if __name__ == "__main__"`` that calls ``monte_carlo(...,
    processes=2)`` with a function of its own runs its body once (the workers do not import it
    again, as ``multiprocessing``'s spawn would) and gets the in-process outputs."""
    script = tmp_path / "budget.py"
    script.write_text(textwrap.dedent("""
        import numpy as np
        from gyrojax.analysis import monte_carlo
        print("BODY RUNS", flush=True)
        def trial(x):
            return x ** 2 + 1
        out = monte_carlo(trial, np.arange(40.0), chunk_size=8, processes=2)
        assert np.array_equal(out, np.arange(40.0) ** 2 + 1), out
        print("OK", flush=True)
    """))
    res = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.count("BODY RUNS") == 1 and "OK" in res.stdout, res.stdout


def test_worker_error_is_raised_with_its_traceback_and_the_pool_recovers():
    def bad(x):
        def boom(x):
            raise FloatingPointError("trial 3 diverged")
        return jax.pure_callback(boom, jax.ShapeDtypeStruct(x.shape, x.dtype), x)

    with pytest.raises(RuntimeError, match=r"(?s)chunk \d \(draws \d-\d\) failed on a Dask "
                       r"worker.*trial 3 diverged"):
        monte_carlo(bad, np.arange(8.0), chunk_size=4, processes=2, vectorized=True)
    out = monte_carlo(lambda x: 2 * x, np.arange(8.0), chunk_size=4, processes=2)
    np.testing.assert_array_equal(out, 2 * np.arange(8.0))


def test_processes_bad_arguments_name_the_value():
    import threading

    lock = threading.Lock()
    with pytest.raises(TypeError, match="cannot be pickled"):
        monte_carlo(lambda x: x + (lock is None), np.arange(4.0), processes=2)
    for bad in (0, -1, True, "many", 1.5):
        with pytest.raises(ValueError, match=f"processes={bad!r}"):
            monte_carlo(lambda x: x, np.arange(4.0), processes=bad)
    with pytest.raises(ValueError, match="not both"):
        monte_carlo(lambda x: x, np.arange(4.0), processes=2, devices=jax.devices())
    for bad in (0, -3, 2.5, True):  # a chunk of 0 once ran one draw per chunk, silently
        with pytest.raises(ValueError, match=f"chunk_size={bad!r}"):
            monte_carlo(lambda x: x, np.arange(4.0), chunk_size=bad)
    from gyrojax.analysis.mounting import mounting_error_budget

    for field in ("noise_arcsec", "dchi_std_arcmin", "theta_std_arcmin"):
        with pytest.raises(ValueError, match=f"{field}=-1.0: a standard deviation"):
            mounting_error_budget(jax.random.key(0), 4, **{field: -1.0})


def test_processes_refused_off_the_cpu(monkeypatch):
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    for procs in (2, "all"):
        with pytest.raises(ValueError, match="backend here is 'gpu'"):
            monte_carlo(lambda x: x, np.arange(4.0), processes=procs)


@pytest.mark.slow  # moved out of the default suite (compile-heavy; CI runs it)
def test_mounting_budget_joint_estimation_beats_drift_only():
    """Monte Carlo over random mounting errors, noise-free (alpha2(0) = 30 deg where every
    parameter but theta is observable): estimating the mounting errors jointly cuts the drift
    error by at least 5x against ignoring them (cf. Table 3); what remains is the O(m dchi)
    bias of the first-order regression model (docs/rigs/esg.md). (In the equatorial scheme theta acts
    only at O(m theta), which the weak m11/mc2/eps3 direction amplifies: use Gauss-Newton there.)"""
    bud = mounting_error_budget(jax.random.key(3), 16, schemes=("horizontal", "vertical"),
                                noise_arcsec=0.0, alpha20_deg=30.0, chunk_size=32)
    for s in ("horizontal", "vertical"):
        only = np.sqrt(np.mean(bud.drift_only[s] ** 2))
        joint = np.sqrt(np.mean(bud.joint[s] ** 2))
        assert bud.drift_only[s].shape == (16, 6)
        assert joint < 0.2 * only, (s, only, joint)
    assert "drift + mounting" in bud.markdown()
