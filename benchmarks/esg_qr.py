"""Benchmark: the ESG regression's least-squares solve, Householder QR against CholeskyQR2 and
the normal equations, on the same draws: time per trial and accuracy against Householder.

The ESG Monte Carlo trial (benchmarks/esg_montecarlo.py: vertical scheme, 55.75 deg N, 24 h at
1-min samples, 1 arcsec noise, all 11 regression parameters) spends much of its time in the
regression's QR factorizations of its two 1440-row channel blocks. This script simulates
``--draws`` records once, builds their regression designs (the library's own), and times only
the solve, vmapped over batches of ``--batch`` records on one core, for ``householder`` (the
library's), ``cholqr2``, ``seminormal`` (Cholesky of the Gram matrix, one refinement step) and
``gram_eigh`` (the Gram matrix's eigendecomposition, minimum norm, one refinement step); see
``SOLVERS``. Two problems: the trial's own 11 columns, whose design has rank 10 (the base
misorientation along the spin axis is not seen; Householder's SVD of ``R`` gives the minimum-norm
solution) and the full-rank 10 columns without ``dchi3``.

Accuracy: per draw and parameter, ``|p - p_householder|`` over Householder's standard error, the
largest over all draws, and the largest difference of the six drifts in deg/h.

    python benchmarks/esg_qr.py [--draws 512] [--batch 8] [--repeat 5] [--out benchmarks/RESULTS.md]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from threadpoolctl import threadpool_limits

from gyrojax import units
from gyrojax.estimate._linalg import _column_norms, _solve_r, scaled_lstsq_blocks
from gyrojax.estimate.regression import _design_blocks
from gyrojax.models.esg import DRIFT_NAMES
from gyrojax.models.esg import ESGRig as _ESGRig
from gyrojax.record import BenchRecord
from gyrojax.simulate import gaussian_noise, integrate

sys.path.insert(0, os.path.dirname(__file__))
from _results import machine_line, publish  # noqa: E402
from esg_montecarlo import NOISE, draws, nominal, trial_params  # noqa: E402

ESG_NAMES = _ESGRig(base_param="rotvec").regression_names


def _upper_chol(g):
    """Upper-triangular ``R`` with ``R^T R = g``."""
    return jnp.linalg.cholesky(g).T


def _assembled(blocks, columns, k):
    """The stacked design ``[A b]`` (rows of every channel, ``k + 1`` columns)."""
    return jnp.concatenate([jnp.zeros((blk.shape[1], k + 1)).at[:, np.asarray([*cols, k])]
                            .set(blk.T) for blk, cols in zip(blocks, columns)])


def _gram(blocks, columns, k):
    """``A^T A`` and ``A^T b`` summed over the channel blocks in their columns (GEMM-shaped)."""
    g, atb = jnp.zeros((k, k)), jnp.zeros(k)
    for blk, cols in zip(blocks, columns):
        c = np.asarray(cols, int)
        g = g.at[np.ix_(c, c)].add(blk[:-1] @ blk[:-1].T)
        atb = atb.at[c].add(blk[:-1] @ blk[-1])
    return g, atb


def _refine(blocks, columns, k, p, solve):
    """One step of iterative refinement: ``p + solve(A^T (b - A p))``."""
    r = jnp.zeros(k)
    for blk, cols in zip(blocks, columns):
        c = np.asarray(cols, int)
        r = r.at[c].add(blk[:-1] @ (blk[-1] - p[c] @ blk[:-1]))
    return p + solve(r)


def householder(blocks, columns, k):
    """The library's solve: Householder QR per channel block, merged, SVD of ``R``."""
    p, cov, _, _ = scaled_lstsq_blocks(blocks, columns, k)
    return p, cov


def cholqr2(blocks, columns, k):
    """CholeskyQR2 of the column-scaled stacked ``[A b]`` (two Gram/Cholesky passes), then the
    same SVD of ``R`` as Householder."""
    x = _assembled(blocks, columns, k)
    nrm = jnp.linalg.norm(x, axis=0)
    x = x / nrm
    r1 = _upper_chol(x.T @ x)
    q1 = jax.scipy.linalg.solve_triangular(r1.T, x.T, lower=True).T  # x r1^-1
    r = (_upper_chol(q1.T @ q1) @ r1) * nrm  # R of the unscaled [A b]
    norms = _column_norms(r[:, :k])
    p, cov, _, _ = _solve_r(r * jnp.concatenate([1.0 / norms, jnp.ones(1)]), norms, k, 1e-12)
    return p, cov


def seminormal(blocks, columns, k):
    """Semi-normal equations: ``R`` from ``chol(A^T A)`` (column-scaled), ``p = R^-1 R^-T A^T b``,
    one step of iterative refinement; covariance ``R^-1 R^-T``."""
    g, atb = _gram(blocks, columns, k)
    d = jnp.sqrt(jnp.diag(g))
    r = _upper_chol(g / jnp.outer(d, d))

    def solve(rhs):
        y = jax.scipy.linalg.solve_triangular(r.T, rhs / d, lower=True)
        return jax.scipy.linalg.solve_triangular(r, y, lower=False) / d

    p = _refine(blocks, columns, k, solve(atb), solve)
    r_inv = jax.scipy.linalg.solve_triangular(r, jnp.eye(k), lower=False)
    return p, (r_inv @ r_inv.T) / jnp.outer(d, d)


GRAM_RCOND = 1e-12
"""Eigenvalues of the scaled Gram matrix below this times the largest are dropped: singular
values below 1e-6 of the largest (Householder drops them below 1e-12, which the Gram matrix,
rounded at 1e-16 of its largest eigenvalue, cannot resolve)."""


def gram_eigh(blocks, columns, k):
    """Minimum-norm normal equations: the column-scaled Gram matrix's eigendecomposition, its
    small eigenvalues dropped (``GRAM_RCOND``), one step of iterative refinement; covariance
    the pseudo-inverse. Handles the rank-deficient design, where Cholesky fails."""
    g, atb = _gram(blocks, columns, k)
    d = jnp.sqrt(jnp.diag(g))
    lam, v = jnp.linalg.eigh(g / jnp.outer(d, d))
    keep = lam > GRAM_RCOND * lam[-1]
    inv = jnp.where(keep, 1.0 / jnp.where(keep, lam, 1.0), 0.0)

    def solve(rhs):
        return (v @ (inv * (v.T @ (rhs / d)))) / d

    p = _refine(blocks, columns, k, solve(atb), solve)
    return p, ((v * inv) @ v.T) / jnp.outer(d, d)


SOLVERS = {"householder": householder, "cholqr2": cholqr2, "seminormal": seminormal,
           "gram_eigh": gram_eigh}


def simulate_designs(n, names=None):
    """The regression designs of ``n`` draws of the ESG benchmark trial (noise from each draw's
    key) for the parameters ``names`` (default all 11), as ``(blocks, columns, names)`` with a
    leading draw axis on the blocks."""
    rig, base, cond, ts = nominal()
    d = draws(n, seed=4, noise=False)

    def one(dd):
        y = integrate(rig, trial_params(base, dd), cond, ts)
        y = y + gaussian_noise(jax.random.wrap_key_data(dd["key"]), y.shape, NOISE)
        blocks, _, _ = _design_blocks(rig, BenchRecord(ts, y, rig.channels), cond, 1, names,
                                      "trapezoid")
        return blocks

    _, columns, names = _design_blocks(rig, BenchRecord(ts, jnp.zeros((len(ts), 2)),
                                                        rig.channels), cond, 1, names,
                                       "trapezoid")
    blocks = jax.lax.map(one, d, batch_size=64)
    return blocks, columns, names


def condition(blocks, columns, k):
    """Largest ratio of the column-scaled design's extreme singular values over a few records,
    and its rank (singular values above 1e-12 of the largest)."""
    worst, rank = 0.0, k
    for i in range(4):
        a = np.asarray(_assembled(jax.tree.map(lambda b: b[i], blocks), columns, k))[:, :k]
        s = np.linalg.svd(a / np.linalg.norm(a, axis=0), compute_uv=False)
        worst = max(worst, s[0] / s[-1])
        rank = min(rank, int(np.sum(s > 1e-12 * s[0])))
    return worst, rank


def run_problem(label, names, n, batch, repeat):
    """Time every solver on one problem; returns the table's rows."""
    blocks, columns, names = simulate_designs(n, names)
    k = len(names)
    cond, rank = condition(blocks, columns, k)
    drift = np.array([names.index(m) for m in DRIFT_NAMES])
    results, times = {}, {}
    with threadpool_limits(1, user_api="blas"):
        for name, solver in SOLVERS.items():
            fn = jax.jit(lambda b, s=solver: jax.lax.map(lambda x: s(x, columns, k), b,
                                                         batch_size=batch))
            out = jax.block_until_ready(fn(blocks))  # compile
            best = np.inf
            for _ in range(repeat):
                t = time.perf_counter()
                jax.block_until_ready(fn(blocks))
                best = min(best, time.perf_counter() - t)
            results[name], times[name] = jax.tree.map(np.asarray, out), best / n
            print(f"{label} {name}: {times[name] * 1e6:.0f} us per trial", flush=True)
    p_ref, cov_ref = results["householder"]
    rss = np.asarray(jax.vmap(lambda b: scaled_lstsq_blocks(b, columns, k)[3])(blocks))
    rows_n = sum(int(b.shape[-1]) for b in blocks)
    se = np.sqrt(np.diagonal(cov_ref, axis1=1, axis2=2) * (rss / (rows_n - rank))[:, None])
    rows = []
    for name in SOLVERS:
        p, _ = results[name]
        bad = int(np.sum(~np.all(np.isfinite(p), axis=1)))
        ok = np.all(np.isfinite(p), axis=1)
        if ok.any():
            dz = f"{np.max(np.abs(p[ok] - p_ref[ok]) / se[ok]):.1e}"
            dd = (f"{np.max(np.abs(p[ok] - p_ref[ok])[:, drift]) * units.EARTH_RATE_DEG_PER_HOUR:.1e}")
        else:
            dz = dd = "-"
        rows.append(f"| {label} | {name} | {times[name] * 1e6:.0f} | "
                    f"{times['householder'] / times[name]:.2f} | {bad} of {n} | {dz} | {dd} |")
    return rows, (k, rank, cond)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=512)
    ap.add_argument("--batch", type=int, default=8, help="records per vmapped solve (as the "
                    "Monte Carlo's identify stage, default 8)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "RESULTS.md"))
    args = ap.parse_args()

    problems = {"11 columns (the trial's)": None,
                "10 columns (dchi3 held at 0)": tuple(n for n in ESG_NAMES if n != "dchi3")}
    rows, info = [], {}
    for label, names in problems.items():
        r, info[label] = run_problem(label, names, args.draws, args.batch, args.repeat)
        rows += r
    lines = ["## ESG regression: Householder QR against CholeskyQR2 and the normal equations "
             "(`benchmarks/esg_qr.py`)", "", machine_line(), "",
             f"{args.draws} records of the ESG benchmark trial (vertical scheme, 24 h at 1-min "
             f"samples, 1 arcsec noise), the solve alone (designs built beforehand) vmapped over "
             f"{args.batch} records, one core, one BLAS thread; best of {args.repeat} after a "
             "compiling call. Problems: " + "; ".join(
                 f"{lab}: rank {rk} of {k}, column-scaled condition number {c:.1e}"
                 for lab, (k, rk, c) in info.items()) + ".", "",
             "| problem | solve | us per trial | x Householder | failed (not finite) | "
             "max abs(p - p_HH) / se | max drift difference deg/h |",
             "|---|---|---|---|---|---|---|", *rows, "",
             "se: each record's Householder standard error (residual variance times "
             "(A^T A)^+). householder: the library's solve (QR per channel block, the factors "
             "merged, SVD of R: minimum norm). cholqr2: CholeskyQR2 of the stacked, "
             "column-scaled [A b], then the same SVD of R. seminormal: Cholesky of the "
             "column-scaled A^T A, one step of iterative refinement. gram_eigh: the "
             "eigendecomposition of the column-scaled A^T A with eigenvalues below "
             f"{GRAM_RCOND:g} of the largest dropped (minimum norm), one step of refinement."]
    publish(args.out, "esg_qr", lines)


if __name__ == "__main__":
    main()
