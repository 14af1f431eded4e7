"""The ESG mounting-error budget on the Dask engine against the worker-process pool, timed in
one run on this machine, and the engine's memory against the number of trials.

Throughput (scheme-draw trials per second, warm: each configuration runs once to compile, then
``--repeat`` times, best kept):
- pool: ``mounting_error_budget`` (every draw up front, every output gathered), in this process
  and with ``processes=2`` (the hand-written pool, one pinned worker per core);
- stats: ``mounting_budget_stats`` (draws from keys, statistics only), in this process and on a
  ``distributed.LocalCluster`` of 1 and 2 single-threaded workers (one client per cluster, so
  the second and later runs reuse the workers' compiled block program).
Memory: peak RSS of a fresh process running ``monte_carlo_stats`` on a cheap trial (six normal
deviates squared) at 10^5, 10^6 and 10^7 trials: the engine holds no per-trial array, so it
does not grow with N.

    python benchmarks/montecarlo_dask.py [--draws 1024] [--repeat 2] [--out benchmarks/RESULTS.md]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

sys.path.insert(0, os.path.dirname(__file__))

from _results import first_and_best, machine_line, publish  # noqa: E402

MEMORY_SCRIPT = """
import sys, time
import jax, jax.numpy as jnp
import gyrojax
from gyrojax.analysis import monte_carlo_stats
n = int(sys.argv[1])
t = time.perf_counter()
res = monte_carlo_stats(lambda x: x * x, lambda k: jax.random.normal(k, (6,)), jax.random.key(0),
                        n, block_size=8192)
dt = time.perf_counter() - t
# VmHWM: this process's own peak (ru_maxrss would carry the parent's across exec)
hwm = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM"))
print(hwm, dt, res[""].n)
"""


def _vmhwm_kb() -> int:
    """This process's peak resident set (kB)."""
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith("VmHWM"))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=1024, help="draws per scheme (default 1024)")
    ap.add_argument("--block", type=int, default=128, help="draws per block (default 128)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--memory", default="100000,1000000,10000000",
                    help="trial counts of the memory runs (comma separated)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "RESULTS.md"))
    args = ap.parse_args()

    import jax
    from distributed import Client

    from gyrojax.analysis.mounting import mounting_budget_stats, mounting_error_budget
    from gyrojax.analysis.streaming import _stats_equal, local_cluster

    key = jax.random.key(0)
    kw = dict(alpha20_deg=30.0, noise_arcsec=1.0)
    n, rows, results = args.draws, [], {}
    trials = 4 * n

    def row(label, first, best):
        rows.append((label, first, best, trials / best))
        print(f"{label}: first {first:.1f} s, best {best:.2f} s, {trials / best:.0f} trials/s",
              flush=True)

    _, f, b = first_and_best(lambda: mounting_error_budget(key, n, chunk_size=4 * args.block, **kw),
                    args.repeat)
    row("pool, this process", f, b)
    _, f, b = first_and_best(lambda: mounting_error_budget(key, n, chunk_size=4 * args.block,
                                                  processes=2, **kw), args.repeat)
    row("pool, processes=2", f, b)
    ref, f, b = first_and_best(lambda: mounting_budget_stats(key, n, block_size=args.block, **kw),
                      args.repeat)
    row("stats, this process", f, b)
    rss = {}
    for workers in (1, 2):
        with local_cluster(workers) as cluster, Client(cluster) as client:
            got, f, b = first_and_best(lambda: mounting_budget_stats(key, n, block_size=args.block,
                                                            client=client, **kw), args.repeat)
            peak = client.run(_vmhwm_kb)
            rss[workers] = max(peak.values()) / 1024
        results[workers] = _stats_equal(got.stats.leaves, ref.stats.leaves)
        row(f"stats, Dask {workers} worker{'s' if workers > 1 else ''}", f, b)
    rate = {r[0]: r[3] for r in rows}

    mem = []
    for count in (int(c) for c in args.memory.split(",")):
        out = subprocess.run([sys.executable, "-c", MEMORY_SCRIPT, str(count)],
                             capture_output=True, text=True, check=True).stdout.split()
        mem.append((count, int(out[0]) / 1024, float(out[1])))
        print(f"memory: {count} trials, peak RSS {mem[-1][1]:.0f} MB, {mem[-1][2]:.1f} s",
              flush=True)

    lines = ["## Monte Carlo on Dask: the mounting budget as statistics "
             "(`benchmarks/montecarlo_dask.py`)", "", machine_line(), "",
             f"ESG mounting-error budget, {n} draws per scheme x 4 schemes = {trials} trials "
             f"(24 h exact model, 1 arcsec noise, alpha2(0) = 30 deg), blocks of {args.block} "
             f"draws; best of {args.repeat} warm runs after one that compiles.", "",
             "| engine | first run s (compile incl.) | best s | trials/s |", "|---|---|---|---|"]
    lines += [f"| {lab} | {f:.1f} | {b:.2f} | {r:.0f} |" for lab, f, b, r in rows]
    lines += ["",
              f"- Statistics against the pool, both in this process: "
              f"{rate['stats, this process'] / rate['pool, this process']:.2f}x the throughput.",
              f"- Dask 2 workers against the pool's `processes=2`: "
              f"{rate['stats, Dask 2 workers'] / rate['pool, processes=2']:.2f}x.",
              f"- Dask 1 -> 2 workers: "
              f"{rate['stats, Dask 2 workers'] / rate['stats, Dask 1 worker']:.2f}x.",
              f"- Bit-identical to this process's statistics: 1 worker {results[1]}, "
              f"2 workers {results[2]}.",
              f"- Peak RSS of a worker: {rss[1]:.0f} MB (1 worker), {rss[2]:.0f} MB (2 workers).",
              "", "Engine memory (a fresh process's peak resident set, VmHWM; a cheap trial, blocks "
              "of 8,192; a bare process that imports gyrojax and runs one JAX op: ~240 MB):", "",
              "| trials | peak RSS MB | s |", "|---|---|---|"]
    lines += [f"| {c:,} | {m:.0f} | {t:.1f} |" for c, m, t in mem]
    publish(args.out, "montecarlo_dask", lines)


if __name__ == "__main__":
    main()
