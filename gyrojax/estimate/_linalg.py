"""Small dense least-squares kernels shared by the estimators (no normal equations)."""

from __future__ import annotations

import jax.numpy as jnp


def scaled_lstsq(a, b, *, rcond: float = 1e-12):
    """Least squares ``min |a p - b|`` via column scaling, QR, and an SVD of the small ``R``.

    Rank-deficient designs are solved in the minimum-norm sense (singular values below
    ``rcond * max`` are dropped). Returns ``(p, cov_unit, singular_values)``: ``cov_unit`` is
    ``(A^T A)^+`` (multiply by the residual variance for the covariance); ``singular_values`` are those
    of the column-normalized ``a``, largest first.
    """
    norms = jnp.linalg.norm(a, axis=0)
    # a column that is zero up to rounding (e.g. theta in the equatorial scheme) is exactly
    # unobservable: scale it to zero instead of amplifying rounding noise to unit norm.
    norms = jnp.where(norms > 1e-10 * jnp.max(norms), norms, jnp.inf)
    q, r = jnp.linalg.qr(a / norms)
    u, s, vt = jnp.linalg.svd(r)
    keep = s > rcond * s[0]
    s_inv = jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0)
    p_scaled = vt.T @ (s_inv * (u.T @ (q.T @ b)))
    cov_scaled = (vt.T * s_inv**2) @ vt
    p = p_scaled / norms
    cov = cov_scaled / jnp.outer(norms, norms)
    return p, cov, s
