"""Monte Carlo from keys to statistics (gyrojax.analysis.streaming): the statistics against numpy
on the same trials, the merge against a one-pass computation, resume after an interruption, and
(slow) the same bits from a Dask cluster of one or two workers, one of them killed mid-run."""

import contextlib
import os
import signal
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gyrojax.analysis.cluster import local_cluster
from gyrojax.analysis.streaming import (
    LeafStats,
    _stats_equal,
    merge_stats,
    monte_carlo_stats,
)

KEY = jax.random.key(11)
BINS = np.linspace(-4.0, 4.0, 161)


def draw(key):
    k1, k2 = jax.random.split(key)
    return {"a": jax.random.normal(k1, (3,)), "m": jax.random.normal(k2, (6, 3))}


def trial(d):
    """A small least-squares problem per draw (QR and a solve, as a budget's trial has), and a
    scalar that is not finite in about 1 % of the draws."""
    q, r = jnp.linalg.qr(d["m"])
    x = jnp.linalg.solve(r + 4.0 * jnp.eye(3), d["a"])
    s = jnp.where(d["a"][0] > 2.33, jnp.nan, jnp.sum(d["m"] ** 2))
    return {"x": x, "s": s}


def outputs(n):
    return jax.vmap(lambda i: trial(draw(jax.random.fold_in(KEY, i))))(jnp.arange(n))


def test_statistics_are_numpys_on_the_same_trials():
    """Trial i uses fold_in(key, i): the statistics equal numpy's on the trials recomputed one
    key at a time (a last block of 104 of 128 trials masked; non-finite trials counted and left
    out), the quantiles within one bin of numpy's."""
    n = 1000
    res = monte_carlo_stats(trial, draw, KEY, n, block_size=128, bins=BINS)
    out = jax.tree.map(np.asarray, outputs(n))
    x, s = res["['x']"], res["['s']"]
    assert res.n_blocks == 8 and res.computed == 8 and x.n == n and x.nonfinite == 0
    np.testing.assert_allclose(x.mean, out["x"].mean(0), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(x.cov, np.cov(out["x"].T), rtol=1e-11)
    np.testing.assert_allclose(x.rms, np.sqrt((out["x"] ** 2).mean(0)), rtol=1e-12)
    np.testing.assert_array_equal(x.min, out["x"].min(0))
    np.testing.assert_array_equal(x.max, out["x"].max(0))
    width = BINS[1] - BINS[0]
    for q in (0.1, 0.5, 0.9):
        assert np.all(np.abs(x.quantile(q) - np.quantile(out["x"], q, axis=0)) <= width)
    finite = np.isfinite(out["s"])
    assert s.nonfinite == int((~finite).sum()) > 0 and s.n == int(finite.sum())
    np.testing.assert_allclose(s.mean, [out["s"][finite].mean()], rtol=1e-12)
    # the standard error of the RMS against the delta method on numpy's moments
    sq = out["x"] ** 2
    se = np.sqrt(sq.var(0, ddof=1) / n) / (2 * np.sqrt(sq.mean(0)))
    np.testing.assert_allclose(x.rms_se, se, rtol=1e-10)
    ds = res.to_xarray(quantiles=(0.5,))
    assert ds.attrs["n_trials"] == n and ds["x_rms"].shape == (3,)


def test_kept_outputs_are_the_trials_on_disk_and_leave_the_statistics(tmp_path):
    """``outputs=DIR``: one NetCDF file per block (the last block's 40 padding trials dropped),
    read back lazily by ``load_outputs`` as the trials recomputed key by key, in trial order;
    the statistics are those of the run without outputs."""
    from gyrojax.analysis import load_outputs

    n = 600
    res = monte_carlo_stats(trial, draw, KEY, n, block_size=128, outputs=tmp_path / "out")
    ref = monte_carlo_stats(trial, draw, KEY, n, block_size=128)
    files = sorted((tmp_path / "out").iterdir())
    assert [f.name for f in files] == [f"block-{i:08d}.nc" for i in range(5)]
    ds = load_outputs(tmp_path / "out")
    out = jax.tree.map(np.asarray, outputs(n))
    assert ds["x"].shape == (n, 3) and ds["s"].shape == (n,)
    np.testing.assert_array_equal(ds["trial"].values, np.arange(n))
    np.testing.assert_allclose(ds["x"].values, out["x"], rtol=1e-13, atol=1e-15)
    np.testing.assert_array_equal(np.isnan(ds["s"].values), np.isnan(out["s"]))
    for leaf in ("['x']", "['s']"):
        assert res[leaf].n == ref[leaf].n and res[leaf].nonfinite == ref[leaf].nonfinite
        np.testing.assert_allclose(res[leaf].mean, ref[leaf].mean, rtol=1e-13)
        np.testing.assert_allclose(res[leaf].rms, ref[leaf].rms, rtol=1e-13)
    with pytest.raises(FileNotFoundError, match="no block"):
        load_outputs(tmp_path)


def test_blocks_spread_over_every_device_of_the_process():
    """``devices=``: with two (forced) host devices, blocks alternate between them and the
    statistics are those of one device, bit for bit (a trial without LAPACK: several host
    devices in one process deadlock jaxlib 0.10.2's batched LAPACK)."""
    code = textwrap.dedent("""
        import jax, jax.numpy as jnp
        from gyrojax.analysis.streaming import _stats_equal, monte_carlo_stats
        assert len(jax.devices()) == 2, jax.devices()
        used = set()
        put = jax.device_put
        def spy(x, device=None, **kw):
            if device is not None:
                used.add(str(device))
            return put(x, device, **kw)
        jax.device_put = spy
        key = jax.random.key(3)
        def draw(k):
            return jax.random.normal(k, (4,))
        def trial(x):
            return {"y": jnp.sin(x) * jnp.cumsum(x), "z": x @ x}
        one = monte_carlo_stats(trial, draw, key, 1000, block_size=100)
        both = monte_carlo_stats(trial, draw, key, 1000, block_size=100, devices=jax.devices())
        assert both.computed == 10 and _stats_equal(one.leaves, both.leaves)
        print("DEVICES", len(used))
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "DEVICES 2" in res.stdout, res.stdout


def test_merged_blocks_equal_a_one_pass_computation():
    """Chan's pairwise merge of uneven pieces equals the statistics of all the data at once."""
    rng = np.random.default_rng(0)
    data = rng.normal(size=(500, 4)) * [1.0, 10.0, 1e-3, 5.0] + [3.0, -1.0, 0.0, 1e4]

    def stats(x):
        d = x - x.mean(0)
        sq = x**2
        return {"v": LeafStats(n=len(x), nonfinite=0, mean=x.mean(0), m2=d.T @ d,
                               sq_mean=sq.mean(0), sq_m2=((sq - sq.mean(0)) ** 2).sum(0),
                               min=x.min(0), max=x.max(0), hist=None, edges=None, shape=(4,))}

    cuts = [0, 7, 8, 200, 333, 500]
    merged = merge_stats([stats(data[a:b]) for a, b in zip(cuts, cuts[1:])])["v"]
    whole = stats(data)["v"]
    for f in ("mean", "m2", "sq_mean", "sq_m2"):
        np.testing.assert_allclose(getattr(merged, f), getattr(whole, f), rtol=1e-9)
    assert merged.n == 500


def test_an_interrupted_run_resumes_to_the_same_bits(tmp_path):
    """Three blocks, then an interruption (``stop_after``); the resumed run computes the other
    five and gives the uninterrupted run's statistics bit for bit. The file refuses another
    study by name."""
    path = tmp_path / "budget.npz"
    full = monte_carlo_stats(trial, draw, KEY, 1000, block_size=128)
    part = monte_carlo_stats(trial, draw, KEY, 1000, block_size=128, resume=path, stop_after=3)
    assert part.computed == 3 and part["['x']"].n == 384 and path.exists()
    seen = []
    rest = monte_carlo_stats(trial, draw, KEY, 1000, block_size=128, resume=path,
                             on_block=lambda i, done: seen.append((i, done)))
    assert rest.computed == 5 and [i for i, _ in seen] == [3, 4, 5, 6, 7] and seen[-1][1] == 8
    assert _stats_equal(rest.leaves, full.leaves)
    again = monte_carlo_stats(trial, draw, KEY, 1000, block_size=128, resume=path)
    assert again.computed == 0 and _stats_equal(again.leaves, full.leaves)
    with pytest.raises(ValueError, match="another study"):
        monte_carlo_stats(trial, draw, jax.random.key(12), 1000, block_size=128, resume=path)


def test_bad_arguments_name_the_value():
    for kwargs, match in (({"n": 0}, "n=0"), ({"n": 10, "block_size": 0}, "block_size=0"),
                          ({"n": 10, "bins": [1.0, 0.0]}, "bins")):
        with pytest.raises(ValueError, match=match):
            monte_carlo_stats(trial, draw, KEY, **kwargs)
    with pytest.raises(ValueError, match="typed key"):
        monte_carlo_stats(trial, draw, jax.random.PRNGKey(0), 10)


@contextlib.contextmanager
def _cluster(n_workers):
    """A client of :func:`local_cluster` with ``n_workers`` single-threaded worker processes."""
    from distributed import Client

    with local_cluster(n_workers) as cluster, Client(cluster) as client:
        yield client


@pytest.mark.slow  # starts Dask clusters (each worker imports JAX and compiles); CI runs it
def test_dask_workers_give_the_in_process_bits():
    """The same statistics, bit for bit, from this process, a one-worker and a two-worker
    ``local_cluster``: blocks are reduced in their own compiled program and merged in
    block order, whoever computed them."""
    ref = monte_carlo_stats(trial, draw, KEY, 3000, block_size=256, bins=BINS)
    for n_workers in (1, 2):
        with _cluster(n_workers) as client:
            got = monte_carlo_stats(trial, draw, KEY, 3000, block_size=256, bins=BINS,
                                    client=client)
        assert got.computed == ref.n_blocks == 12
        assert _stats_equal(got.leaves, ref.leaves), n_workers


@pytest.mark.slow  # starts a Dask cluster and kills one of its workers; CI runs it
def test_a_worker_killed_mid_run_leaves_the_statistics_unchanged():
    """After the second block arrives one of the two workers is killed (SIGKILL); Dask retries
    its blocks on the other (and on the restarted one) and the statistics are the in-process
    run's, bit for bit."""
    ref = monte_carlo_stats(trial, draw, KEY, 6000, block_size=250)
    killed = []
    with _cluster(2) as client:

        def kill_one(index, done):
            if done == 2 and not killed:
                victim = sorted(client.scheduler_info()["workers"])[0]
                pid = client.run(os.getpid, workers=[victim])[victim]
                killed.append(pid)
                os.kill(pid, signal.SIGKILL)

        got = monte_carlo_stats(trial, draw, KEY, 6000, block_size=250, client=client,
                                on_block=kill_one)
    assert killed and got.computed == ref.n_blocks == 24
    assert _stats_equal(got.leaves, ref.leaves)


@pytest.mark.slow  # compiles the ESG budget's block program (~40 s); CI runs it
def test_budget_command_resumes_and_writes_its_dataset(tmp_path, monkeypatch, capsys):
    """``gyrojax montecarlo --study budget``: statistics per fit, scheme and parameter (RMS and
    its standard error, bias, quantiles) as JSON, NetCDF and a figure; a rerun with the same
    ``--resume`` file computes nothing and prints the same numbers; on the horizontal scheme at
    alpha2(0) = 30 deg estimating the mounting errors removes most of the drift error."""
    import json

    import xarray as xr

    from gyrojax.cli import main

    monkeypatch.chdir(tmp_path)
    argv = ["montecarlo", "--study", "budget", "--draws", "24", "--chunk-size", "8",
            "--resume", "r.npz", "--json", "b.json", "--netcdf", "b.nc", "--plot", "b.png"]
    assert main(argv) == 0
    first = json.loads((tmp_path / "b.json").read_text())
    assert main(argv) == 0
    assert json.loads((tmp_path / "b.json").read_text()) == first
    assert first["n_draws"] == 24 and first["nonfinite"] == 0
    ds = xr.open_dataset(tmp_path / "b.nc")
    assert dict(ds.sizes) == {"fit": 2, "scheme": 4, "parameter": 6, "quantile": 2}
    h = ds.sel(scheme="horizontal")
    assert float(h["rms"].sel(fit="joint").max()) < 0.1 * float(h["rms"].sel(fit="drift_only").max())
    assert (tmp_path / "b.png").read_bytes()[:4] == b"\x89PNG"
