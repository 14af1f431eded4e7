"""Small dense least-squares kernels shared by the estimators (no normal equations), and the
forward Jacobian with its value."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def value_and_jacfwd(fn, *, has_aux: bool = False):
    """``x -> (fn(x), jax.jacfwd(fn)(x))`` from one forward-mode pass: the value is the JVP's own
    primal, so a model behind ``fn`` (a diffrax solve) is traced, compiled and run once, not once
    more for the value. With ``has_aux``, ``fn`` returns ``(out, aux)``: the result is
    ``((out, aux), d out / d x)``."""
    def both(x):
        if has_aux:
            jac, value = jax.jacfwd(lambda v: (lambda out, aux: (out, (out, aux)))(*fn(v)),
                                    has_aux=True)(x)
        else:
            jac, value = jax.jacfwd(lambda v: (lambda out: (out, out))(fn(v)), has_aux=True)(x)
        return value, jac

    return both


def tall_qr_r(a, *, block_rows: int = 480):
    """``R`` of a tall matrix by a two-level (TSQR) factorization: QR of row blocks, then QR of
    the stacked ``R`` factors. Same ``R`` (up to row signs) as one Householder QR, but each block
    fits in cache: faster for the 2880 x 12 regression designs (6 blocks measured best among
    96-720 rows per block)."""
    n, k = a.shape
    nb = n // block_rows
    if nb < 2 or n < 4 * k:
        return jnp.linalg.qr(a, mode="r")
    rows = -(-n // nb)
    a = jnp.pad(a, ((0, rows * nb - n), (0, 0)))  # zero rows leave R unchanged
    r_blocks = jnp.linalg.qr(a.reshape(nb, rows, k), mode="r")  # (nb, k, k)
    return jnp.linalg.qr(r_blocks.reshape(nb * k, k), mode="r")


def scaled_lstsq(a, b, *, rcond: float = 1e-12):
    """Least squares ``min |a p - b|`` via column scaling, QR, and an SVD of the small ``R``.

    Rank-deficient designs are solved in the minimum-norm sense (singular values below
    ``rcond * max`` are dropped). Returns ``(p, cov_unit, singular_values)``: ``cov_unit`` is
    ``(A^T A)^+`` (multiply by the residual variance for the covariance); ``singular_values`` are those
    of the column-normalized ``a``, largest first.
    """
    k = a.shape[1]
    norms = _column_norms(a)
    scale = jnp.concatenate([1.0 / norms, jnp.ones(1, a.dtype)])
    # R of the augmented [A b]: its last column holds Q^T b. Built transposed, the scaled
    # [A b] is the column-major matrix LAPACK factors without a copy. Scaled before the QR: on one
    # stacked design, scaling R afterwards measured 1.4-2.4x slower
    # (docs/decisions/0006-esg-monte-carlo-hot-path.md).
    ab_t = jnp.concatenate([a.T, b[None]], axis=0) * scale[:, None]
    return _solve_r(tall_qr_r(ab_t.T), norms, k, rcond)[:3]


def scaled_lstsq_blocks(blocks, columns, k: int, *, rcond: float = 1e-12,
                        block_rows: int = 1440):
    """:func:`scaled_lstsq` for a design whose row blocks each use only some of its ``k``
    columns: block ``j`` is given transposed with its right-hand side, ``[A_j b_j]^T``
    (len(columns[j]) + 1, m_j), one row per column of ``A`` it uses (``columns[j]``, static
    indices; its other columns are zero), then ``b_j``.

    Each block is factored on its own columns (:func:`tall_qr_r`, split only beyond
    ``block_rows`` rows; the transposed layout is the column-major matrix LAPACK factors without
    a copy), the small triangular factors are placed in their columns, stacked, column-scaled and
    factored once more. The
    column norms come from the stacked factors (they equal the design's: Q is orthogonal), and
    scaling after the QR loses nothing, as Householder QR is backward stable column by column.

    Returns ``(p, cov_unit, singular_values, rss)`` as :func:`scaled_lstsq` plus the residual
    sum of squares ``|A p - b|^2``, read from the factors (see :func:`_solve_r`).
    """
    stacked = []
    for blk, cols in zip(blocks, columns):
        # a 24 h channel at 1-min samples (1440 x 10, ~115 KB) in one LAPACK call: ~10 % faster
        # than the three 480-row blocks that suit the stacked 2880 x 12 (measured, one core)
        r_j = tall_qr_r(blk.T, block_rows=block_rows)
        place = np.asarray([*cols, k], int)
        stacked.append(jnp.zeros((r_j.shape[0], k + 1), r_j.dtype).at[:, place].set(r_j))
    r_aug = jnp.concatenate(stacked)
    norms = _column_norms(r_aug[:, :k])
    r_aug = r_aug * jnp.concatenate([1.0 / norms, jnp.ones(1, r_aug.dtype)])
    if len(blocks) > 1:
        r_aug = jnp.linalg.qr(r_aug, mode="r")
    return _solve_r(r_aug, norms, k, rcond)


def _column_norms(a):
    """Column norms of ``a``, with a column that is zero up to rounding (e.g. theta in the
    equatorial scheme: exactly unobservable) given an infinite norm, so scaling sets it to zero
    instead of amplifying rounding noise to unit norm."""
    norms = jnp.linalg.norm(a, axis=0)
    return jnp.where(norms > 1e-10 * jnp.max(norms), norms, jnp.inf)


def _solve_r(r_aug, norms, k, rcond):
    """The minimum-norm solution, unit covariance, singular values and residual sum of squares
    from ``R`` of the column-scaled ``[A b]`` (its last column holds ``Q^T b``, so ``Q`` is never
    formed). Fewer rows than unknowns (a short record) are padded with zero rows, which leave
    ``R`` unchanged.

    As ``[A b] = Q R`` with orthonormal ``Q``, ``|A p - b| = |R[:, :k] p - R[:, k]|`` over all of
    ``R``'s rows: the residual without the design (its ``Q^T`` part, plus ``R[k, k]``: the part
    of ``b`` outside the columns' span), as LAPACK's ``xGELS`` reads it."""
    if r_aug.shape[0] < k + 1:
        r_aug = jnp.pad(r_aug, ((0, k + 1 - r_aug.shape[0]), (0, 0)))
    r, qtb = r_aug[:k, :k], r_aug[:k, k]
    u, s, vt = jnp.linalg.svd(r)
    keep = s > rcond * s[0]
    s_inv = jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0)
    p_scaled = vt.T @ (s_inv * (u.T @ qtb))
    cov_scaled = (vt.T * s_inv**2) @ vt
    rss = jnp.sum((r_aug[:, :k] @ p_scaled - r_aug[:, k]) ** 2)
    p = p_scaled / norms
    cov = cov_scaled / jnp.outer(norms, norms)
    return p, cov, s, rss
