"""The ESG mounting-error budget on Dask, timed in one run on this machine, and the memory of
the statistics engine and of the budget against the number of trials.

Throughput (scheme-draw trials per second, warm: each configuration runs once to compile, then
``--repeat`` times, best kept):
- outputs: ``mounting_error_budget`` (every draw up front, every output gathered), in this
  process and with ``processes=2`` (chunks on the kept local Dask cluster, one pinned worker
  per core);
- stats: ``mounting_budget_stats`` (draws from keys, statistics only), in this process and on a
  ``local_cluster`` of 1 and 2 single-threaded pinned workers (one client per cluster, so the
  second and later runs reuse the workers' compiled block program); the scaling from 1 to 2
  workers also paired: both clusters up, runs alternating (``--pairs``), so the VM's drifting
  speed cancels within a pair; and the machine's own ceiling, two independent pinned processes
  running the statistics in-process at the same time.
Memory: peak RSS of a fresh process running ``monte_carlo_stats`` on a cheap trial (six normal
deviates squared) at 10^5, 10^6 and 10^7 trials, and ``mounting_budget_stats`` configured for
10^5, 10^6 and 10^7 trials of which the first ``--budget-blocks`` blocks are computed
(``stop_after``): nothing of either grows with N.

    python benchmarks/montecarlo_dask.py [--draws 1024] [--repeat 2] [--out benchmarks/RESULTS.md]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

import numpy as np

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

CEILING_SCRIPT = """
import os, sys, time
import jax
from gyrojax.analysis.mounting import mounting_budget_stats
n, block, barrier, me, repeat = (int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4],
                                 int(sys.argv[5]))
os.sched_setaffinity(0, {int(me)})
kw = dict(alpha20_deg=30.0, noise_arcsec=1.0, block_size=block)
mounting_budget_stats(jax.random.key(0), n, **kw)  # compile
open(os.path.join(barrier, me), "w").close()
while len(os.listdir(barrier)) < 2:
    time.sleep(0.01)
best = float("inf")
for _ in range(repeat):
    t = time.perf_counter()
    mounting_budget_stats(jax.random.key(0), n, **kw)
    best = min(best, time.perf_counter() - t)
print(best)
"""

BUDGET_MEMORY_SCRIPT = """
import sys, time
import jax
from gyrojax.analysis.mounting import mounting_budget_stats
n, blocks, block = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
t = time.perf_counter()
res = mounting_budget_stats(jax.random.key(0), n // 4, alpha20_deg=30.0, noise_arcsec=1.0,
                            block_size=block, stop_after=blocks)
dt = time.perf_counter() - t
hwm = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM"))
print(hwm, dt, res.stats.computed)
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
    ap.add_argument("--pairs", type=int, default=5,
                    help="alternating 1-worker / 2-worker runs for the paired scaling (default 5)")
    ap.add_argument("--budget-blocks", type=int, default=8,
                    help="blocks computed by each budget memory run (default 8)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "RESULTS.md"))
    args = ap.parse_args()

    import jax
    from distributed import Client

    from gyrojax.analysis.cluster import local_cluster
    from gyrojax.analysis.mounting import mounting_budget_stats, mounting_error_budget
    from gyrojax.analysis.streaming import _stats_equal

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
    row("outputs, this process", f, b)
    _, f, b = first_and_best(lambda: mounting_error_budget(key, n, chunk_size=4 * args.block,
                                                  processes=2, **kw), args.repeat)
    row("outputs, processes=2 (Dask)", f, b)
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
    # paired scaling: a 1-worker and a 2-worker cluster both up, runs alternating, so both
    # sides of a pair see the same phase of the VM (whose speed drifts by up to 2x)
    import time

    paired = []
    with local_cluster(1) as c1, Client(c1) as cl1, local_cluster(2) as c2, Client(c2) as cl2:
        for cl in (cl1, cl2):
            mounting_budget_stats(key, n, block_size=args.block, client=cl, **kw)  # compile
        for _ in range(args.pairs):
            dt = []
            for cl in (cl1, cl2):
                t = time.perf_counter()
                mounting_budget_stats(key, n, block_size=args.block, client=cl, **kw)
                dt.append(time.perf_counter() - t)
            paired.append(dt[0] / dt[1])
            print(f"paired 1 -> 2 workers: {paired[-1]:.2f}x", flush=True)
    # the machine's own ceiling for two workers: two independent processes, each pinned to a
    # core and running the statistics in-process, timed at the same time after both compiled
    import tempfile

    with tempfile.TemporaryDirectory() as barrier:
        procs = [subprocess.Popen([sys.executable, "-c", CEILING_SCRIPT, str(n), str(args.block),
                                   barrier, str(core), str(args.repeat)], stdout=subprocess.PIPE,
                                  text=True) for core in sorted(os.sched_getaffinity(0))[:2]]
        best = [float(p.communicate()[0].split()[-1]) for p in procs]
    rows.append(("ceiling: 2 independent processes at once", float("nan"), max(best),
                 2 * trials / max(best)))
    print(f"ceiling: {2 * trials / max(best):.0f} trials/s", flush=True)
    rate = {r[0]: r[3] for r in rows}

    mem = []
    for count in (int(c) for c in args.memory.split(",")):
        out = subprocess.run([sys.executable, "-c", MEMORY_SCRIPT, str(count)],
                             capture_output=True, text=True, check=True).stdout.split()
        mem.append((count, int(out[0]) / 1024, float(out[1])))
        print(f"memory: {count} trials, peak RSS {mem[-1][1]:.0f} MB, {mem[-1][2]:.1f} s",
              flush=True)
    bmem = []
    for count in (int(c) for c in args.memory.split(",")):
        out = subprocess.run([sys.executable, "-c", BUDGET_MEMORY_SCRIPT, str(count),
                              str(args.budget_blocks), str(args.block)],
                             capture_output=True, text=True, check=True).stdout.split()
        bmem.append((count, int(out[0]) / 1024, float(out[1])))
        print(f"budget memory: {count} trials configured, {args.budget_blocks} blocks computed, "
              f"peak RSS {bmem[-1][1]:.0f} MB, {bmem[-1][2]:.1f} s", flush=True)

    lines = ["## Monte Carlo on Dask: the mounting budget as statistics "
             "(`benchmarks/montecarlo_dask.py`)", "", machine_line(), "",
             f"ESG mounting-error budget, {n} draws per scheme x 4 schemes = {trials} trials "
             f"(24 h exact model, 1 arcsec noise, alpha2(0) = 30 deg), blocks of {args.block} "
             f"draws; best of {args.repeat} warm runs after one that compiles.", "",
             "| engine | first run s (compile incl.) | best s | trials/s |", "|---|---|---|---|"]
    lines += [f"| {lab} | {f:.1f} | {b:.2f} | {r:.0f} |".replace("| nan |", "| - |")
              for lab, f, b, r in rows]
    lines += ["",
              f"- Statistics against outputs, both in this process: "
              f"{rate['stats, this process'] / rate['outputs, this process']:.2f}x the "
              "throughput.",
              f"- Statistics on 2 Dask workers against outputs with `processes=2`: "
              f"{rate['stats, Dask 2 workers'] / rate['outputs, processes=2 (Dask)']:.2f}x.",
              f"- Outputs, this process -> `processes=2`: "
              f"{rate['outputs, processes=2 (Dask)'] / rate['outputs, this process']:.2f}x.",
              f"- Dask 1 -> 2 workers: "
              f"{rate['stats, Dask 2 workers'] / rate['stats, Dask 1 worker']:.2f}x; this "
              "machine's ceiling (two independent pinned processes running the statistics "
              "in-process at the same time, each on its own draws' worth of trials, against one "
              "in this process): "
              f"{rate['ceiling: 2 independent processes at once'] / rate['stats, this process']:.2f}x;"
              " Dask 2 workers reach "
              f"{rate['stats, Dask 2 workers'] / rate['ceiling: 2 independent processes at once']:.2f}"
              " of it. Paired (a 1-worker and a 2-worker cluster both up, runs alternating, "
              f"{len(paired)} pairs): median {np.median(paired):.2f}x (range "
              f"{min(paired):.2f}x-{max(paired):.2f}x).",
              f"- Bit-identical to this process's statistics: 1 worker {results[1]}, "
              f"2 workers {results[2]}.",
              f"- Peak RSS of a worker: {rss[1]:.0f} MB (1 worker), {rss[2]:.0f} MB (2 workers).",
              "", "Engine memory (a fresh process's peak resident set, VmHWM; a cheap trial, blocks "
              "of 8,192; a bare process that imports gyrojax and runs one JAX op: ~240 MB):", "",
              "| trials | peak RSS MB | s |", "|---|---|---|"]
    lines += [f"| {c:,} | {m:.0f} | {t:.1f} |" for c, m, t in mem]
    lines += ["", f"Budget memory (`mounting_budget_stats` configured for N trials in a fresh "
              f"process, its first {args.budget_blocks} blocks of {args.block} draws computed "
              "with `stop_after`: what the budget allocates for N, and a block's peak):", "",
              "| trials configured | peak RSS MB | s |", "|---|---|---|"]
    lines += [f"| {c:,} | {m:.0f} | {t:.1f} |" for c, m, t in bmem]
    publish(args.out, "montecarlo_dask", lines)


if __name__ == "__main__":
    main()
