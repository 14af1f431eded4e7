"""Luenberger observers: pole placement and frequency responses of state-space models.

Observer (spec gyrotheodolite §6): $\\dot{\\hat x} = (A - K C)\\hat x + K y$. For a single output,
Ackermann's formula gives $K = \\phi_d(A)\\,O^{-1} e_n$ with $O$ the observability matrix (rows
$C A^i$) and $\\phi_d$ the desired characteristic polynomial.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["observability_matrix", "ackermann_observer", "frequency_response",
           "binomial_poles"]


def observability_matrix(a, c):
    """Rows ``C, C A, ..., C A^{n-1}`` stacked: shape ``(n * m, n)``."""
    n = a.shape[0]
    rows = [c]
    for _ in range(n - 1):
        rows.append(rows[-1] @ a)
    return jnp.concatenate(rows, axis=0)


def binomial_poles(omega0, n: int = 4):
    """``n`` poles at ``-omega0`` (the binomial standard form ``(p + omega0)^n``)."""
    if not np.all(np.asarray(omega0) > 0):
        raise ValueError(f"omega0={omega0}: the observer pole magnitude must be > 0 (1/s)")
    return -jnp.full(n, jnp.asarray(omega0, dtype=float))


def ackermann_observer(a, c, poles):
    """Observer gain ``K`` (n,) placing the eigenvalues of ``A - K C`` at ``poles`` (one output).

    **Raises:** ``ValueError`` if ``C`` has more than one row (use a multi-output method), if the
    pair is not observable (the observability matrix is singular), or if complex poles do not come
    in conjugate pairs.
    """
    a = jnp.asarray(a, dtype=float)
    c = jnp.atleast_2d(jnp.asarray(c, dtype=float))
    n = a.shape[0]
    if c.shape != (1, n):
        raise ValueError(f"ackermann_observer: C has shape {c.shape}; Ackermann's formula needs one "
                         f"output, C of shape (1, {n})")
    poles = np.asarray(poles)
    if poles.shape != (n,):
        raise ValueError(f"need {n} poles, got {poles.shape}")
    coeffs = np.poly(poles)
    if np.max(np.abs(coeffs.imag)) > 1e-9 * np.max(np.abs(coeffs)):
        raise ValueError(f"poles {poles} are not closed under conjugation; a real gain cannot "
                         "place them")
    coeffs = coeffs.real
    obs = observability_matrix(a, c)
    # scale-aware rank test (a zero column is unobservable outright)
    norms = np.linalg.norm(np.asarray(obs), axis=0)
    s = np.linalg.svd(np.asarray(obs) / np.where(norms > 0, norms, 1.0), compute_uv=False)
    if np.any(norms == 0) or s[-1] < 1e-12 * s[0]:
        raise ValueError("the pair (A, C) is not observable (singular observability matrix); no "
                         "gain can place all observer poles")
    phi = sum(float(cf) * jnp.linalg.matrix_power(a, n - i) for i, cf in enumerate(coeffs))
    e_n = jnp.zeros(n).at[-1].set(1.0)
    return phi @ jnp.linalg.solve(obs, e_n)


def frequency_response(a, b, omegas, c=None):
    """``(j omega E - A)^{-1} B`` for every ``omega`` (vectorized), optionally premultiplied by
    ``C``. ``b`` may be a vector (one input). Returns complex ``(len(omegas), ...)``."""
    a = jnp.asarray(a, dtype=complex)
    b = jnp.asarray(b, dtype=complex)
    eye = jnp.eye(a.shape[0], dtype=complex)

    def one(w):
        x = jnp.linalg.solve(1j * w * eye - a, b)
        return x if c is None else jnp.asarray(c, dtype=complex) @ x

    return jax.vmap(one)(jnp.asarray(omegas, dtype=float))
