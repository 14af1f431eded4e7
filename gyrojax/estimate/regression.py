"""Integral-equation linear regression (docs/rigs/esg.md, equations (6.2)-(6.5)).

The motion equations linear in the parameters, $\\alpha' = c(\\tau, \\alpha) + F(\\tau, \\alpha) p$
(6.1), are integrated over blocks of ``window`` samples with the trapezoid rule, the integrands
evaluated at the *measured* angles:
$A^{(q)} = \\int F d\\tau$, $b^{(q)} = \\alpha(T_q) - \\alpha(T_{q-1}) - \\int c d\\tau$ (6.3), and
$A p = b$ (6.4) is solved by QR + SVD of the column-scaled design (never the normal equations (6.5)).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..record import BenchRecord
from ._linalg import scaled_lstsq_blocks
from ._result import AbstractNamedEstimate

__all__ = ["RegressionResult", "integral_regression", "regression_design"]


class RegressionResult(AbstractNamedEstimate):
    """Outcome of :func:`integral_regression` (batched with leading axes under vmap).

    - `names`: the estimated parameters, in order.
    - `values`, `stderr`: estimates and OLS standard errors (internal units).
    - `residual_rms`: RMS of ``b - A p`` (rad).
    - `singular_values`: of the column-normalized design, largest first (observability diagnostic).
    - `covariance`: ``sigma^2 (A^T A)^+``.
    """

    names: tuple[str, ...] = eqx.field(static=True)
    values: jax.Array
    stderr: jax.Array
    covariance: jax.Array
    residual_rms: jax.Array
    singular_values: jax.Array


def regression_design(rig, record: BenchRecord, conditions, *, window: int = 1,
                      names: Sequence[str] | None = None, quadrature: str = "trapezoid"):
    """The stacked block design ``A`` (2r, k) and right-hand side ``b`` (2r,) of (6.3)-(6.4): the
    ``r`` block rows of the first channel, then those of the second."""
    blocks, columns, names = _design_blocks(rig, record, conditions, window, names, quadrature)
    a = jnp.concatenate([jnp.zeros((blk.shape[1], len(names)), blk.dtype).at[:, np.asarray(cols, int)]
                         .set(blk[:-1].T) for blk, cols in zip(blocks, columns)])
    return a, jnp.concatenate([blk[-1] for blk in blocks]), names


def _design_blocks(rig, record, conditions, window, names, quadrature):
    """The design one channel at a time: for each, ``[A_c b_c]^T`` (k_c + 1, r) holding only the
    columns of ``A`` that are not zero by construction in that channel's rows (their indices
    into ``names`` in ``columns``), each column one contiguous row. Each channel's rows are zero
    in a few columns the other's are not (the ESG's first channel in ``mc1`` and ``theta1``, the
    second in ``mc2`` and ``theta2``), so factoring each channel on its own columns and merging
    the two small triangular factors does ~30 % less work than factoring the stacked design."""
    if window < 1:
        raise ValueError(f"window={window}: the block length must be an integer >= 1 sample")
    if quadrature not in ("trapezoid", "simpson"):
        raise ValueError(f"quadrature={quadrature!r}; use 'trapezoid' or 'simpson'")
    if quadrature == "simpson" and window % 2:
        raise ValueError(f"quadrature='simpson' needs an even window, got window={window}")
    all_names = rig.regression_names
    names = tuple(all_names if names is None else names)
    bad = [n for n in names if n not in all_names]
    if bad:
        raise ValueError(f"{bad} are not regression parameters of this rig; use {all_names}")
    tau = record.t * rig.time_scale
    alpha = record.y
    n = tau.shape[0]
    r = (n - 1) // window
    if r < 1:
        raise ValueError(f"window={window} is longer than the record ({n} samples)")
    m = r * window
    cs, *fs = rig.regression_columns(alpha, conditions)
    if quadrature == "trapezoid":
        h = 0.5 * jnp.diff(tau)[:m]

        def block_integral(x):
            return (h * (x[1 : m + 1] + x[:m])).reshape(r, window).sum(1)
    else:  # composite Simpson over pairs of intervals (uniform sampling within each pair)
        h = (tau[2 : m + 1 : 2] - tau[:m:2]) / 6.0

        def block_integral(x):
            return (h * (x[: m : 2] + 4 * x[1:m:2] + x[2 : m + 1 : 2])).reshape(r, -1).sum(1)

    ends = alpha[: m + 1 : window]
    blocks, columns = [], []
    for ch, (c, f) in enumerate(zip(cs, fs)):
        cols = tuple(i for i, nm in enumerate(names) if f[all_names.index(nm)] is not None)
        rows = [block_integral(f[all_names.index(names[i])]) for i in cols]
        rows.append(ends[1:, ch] - ends[:-1, ch] - block_integral(c))
        # in-place row updates, not a stacking concatenate (which XLA evaluates operand by
        # operand for every element: several times slower here)
        blk = jnp.zeros((len(rows), r), alpha.dtype)
        for i, x in enumerate(rows):
            blk = blk.at[i].set(x)
        blocks.append(blk)
        columns.append(cols)
    return tuple(blocks), tuple(columns), names


@eqx.filter_jit
def _solve(blocks, columns, k):
    # the residual sum of squares from the factors: forming the 2 x 1440 residuals costs a
    # sixth of the regression's time (XLA's small float64 matrix-vector products)
    p, cov_unit, s, rss = scaled_lstsq_blocks(blocks, columns, k)
    rows = sum(blk.shape[1] for blk in blocks)
    dof = jnp.maximum(rows - jnp.sum(s > 1e-12 * s[0]), 1)
    cov = rss / dof * cov_unit
    return p, jnp.sqrt(jnp.diag(cov)), cov, jnp.sqrt(rss / rows), s


def integral_regression(rig, record: BenchRecord, conditions, *, window: int = 1,
                        names: Sequence[str] | None = None,
                        quadrature: str = "trapezoid") -> RegressionResult:
    """Estimate the linear-model parameters of ``rig`` from a record by integral regression.

    **Arguments:**
    - `rig`: a rig with ``regression_columns`` and ``regression_names`` (the ESG rig).
    - `record`: the measured angles; `conditions`: the rig's conditions (latitude, scheme).
    - `window`: block length ``s`` in samples (docs/rigs/esg.md); 1 uses every sample interval.
    - `names`: subset of ``rig.regression_names`` to estimate (the others are held at zero), e.g.
      only the six drift coefficients as in Table 3.
    - `quadrature`: ``"trapezoid"`` (the paper's checks) or ``"simpson"`` (even ``window``; error
      O(h^4) instead of O(h^2), needed to reach 1e-5 deg/h when ``alpha2`` is large).

    **Returns:** a :class:`RegressionResult`. Works under ``jax.vmap`` over records.
    """
    names = tuple(rig.regression_names if names is None else names)
    p, se, cov, rms, s = _regression(rig, record.t, record.y, record.channels, conditions, window,
                                     names, quadrature)
    return RegressionResult(names=names, values=p, stderr=se, covariance=cov, residual_rms=rms,
                            singular_values=s)


@eqx.filter_jit
def _regression(rig, t, y, channels, conditions, window, names, quadrature):
    """The design and its solve as one compiled function (eagerly, the design's few dozen small
    operations cost ~30 ms per record in dispatch alone). The record enters without its
    attributes, which would be part of the compile key."""
    blocks, columns, _ = _design_blocks(rig, BenchRecord(t, y, channels), conditions, window,
                                        names, quadrature)
    return _solve(blocks, columns, len(names))
