"""Luenberger observers: pole placement and frequency responses of state-space models.

Observer (docs/rigs/gyrotheodolite.md): $\\dot{\\hat x} = (A - K C)\\hat x + K y$. For a single output,
Ackermann's formula gives $K = \\phi_d(A)\\,O^{-1} e_n$ with $O$ the observability matrix (rows
$C A^i$) and $\\phi_d$ the desired characteristic polynomial.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = ["observability_matrix", "ackermann_observer", "place_observer", "frequency_response",
           "observer_error_response", "binomial_poles", "DiscreteObserver",
           "simulate_with_observer"]


def observability_matrix(a: Float[ArrayLike, "n n"], c: Float[ArrayLike, "p n"]
                         ) -> Float[Array, "pn n"]:
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


def ackermann_observer(a: Float[ArrayLike, "n n"], c: Float[ArrayLike, "1 n"],
                       poles: ArrayLike) -> Float[Array, "n 1"]:
    """Observer gain ``K`` (n,) placing the eigenvalues of ``A - K C`` at ``poles`` (one output).

    **Raises:** ``ValueError`` if ``C`` has more than one row (use a multi-output method), if the
    pair is not observable (the observability matrix is singular), or if the poles are not in the
    open left half-plane or not closed under conjugation. The checks run on concrete inputs; under
    ``jit``/``vmap`` (traced inputs) the formula is applied as is (pure JAX, differentiable).
    """
    a = jnp.asarray(a, dtype=float)
    c = jnp.atleast_2d(jnp.asarray(c, dtype=float))
    n = a.shape[0]
    if c.shape != (1, n):
        raise ValueError(f"ackermann_observer: C has shape {c.shape}; Ackermann's formula needs one "
                         f"output, C of shape (1, {n})")
    obs = observability_matrix(a, c)
    if isinstance(poles, jax.core.Tracer):
        coeffs = jnp.real(jnp.poly(poles))
    else:
        coeffs = np.poly(_check_poles(poles, n)).real
    if not isinstance(obs, jax.core.Tracer):
        _check_observable(obs)
    phi = sum(cf * jnp.linalg.matrix_power(a, n - i) for i, cf in enumerate(coeffs))
    e_n = jnp.zeros(n).at[-1].set(1.0)
    return phi @ jnp.linalg.solve(obs, e_n)


def frequency_response(a: Float[ArrayLike, "n n"], b: Float[ArrayLike, " n"] | Float[ArrayLike, "n m"],
                       omegas: Float[ArrayLike, " F"], c=None):
    """``(j omega E - A)^{-1} B`` for every ``omega`` (rad/s), optionally premultiplied by ``C``.

    ``a`` is ``(n, n)`` or a stack ``(S, n, n)`` of systems (then ``b`` is ``(S, n)`` or
    ``(S, n, k)``); ``b`` may be a vector (one input). Returns complex ``(F, n)`` /
    ``(F, n, k)``, with a leading ``S`` for a stack, or ``(..., F, p, ...)`` with ``C``.

    Method (Laub's): one orthogonal Hessenberg reduction ``A = Q H Q^T`` per system, then for every
    frequency an elimination of ``j omega E - H`` with partial pivoting between adjacent rows (all
    a Hessenberg matrix needs) and back substitution, written as elementwise array operations
    vectorized over frequencies: O(n^2) per frequency instead of a general O(n^3) solve, and no
    per-frequency LAPACK calls.
    """
    a = jnp.asarray(a, dtype=float)
    b = jnp.asarray(b)
    single = a.ndim == 2
    if single:
        a, b = a[None], b[None]
    vec = b.ndim == 2
    if vec:
        b = b[..., None]
    n = a.shape[-1]
    h, q = jax.vmap(lambda m: jax.scipy.linalg.hessenberg(m, calc_q=True))(a)
    bt = jnp.einsum("sji,sjk->sik", q, b).astype(complex)  # (S, n, K)
    w = jnp.atleast_1d(jnp.asarray(omegas, dtype=float))
    jw = 1j * w[None, None, :]
    # scalar entries as (S, 1, F) arrays and right-hand sides as (S, K, F): frequency is the
    # contiguous axis, so every step is a long elementwise loop
    hh = h.astype(complex)
    m = [[(jw if i == j else 0.0) - hh[:, i, j, None, None] for j in range(n)] for i in range(n)]
    r = [jnp.broadcast_to(bt[:, i, :, None], bt.shape[:1] + bt.shape[2:] + w.shape)
         for i in range(n)]
    for k in range(n - 1):  # eliminate the single subdiagonal entry of column k
        swap = jnp.abs(m[k + 1][k]) > jnp.abs(m[k][k])
        top = [jnp.where(swap, m[k + 1][j], m[k][j]) for j in range(n)]
        bot = [jnp.where(swap, m[k][j], m[k + 1][j]) for j in range(n)]
        top_r = jnp.where(swap, r[k + 1], r[k])
        bot_r = jnp.where(swap, r[k], r[k + 1])
        factor = bot[k] / top[k]
        m[k], r[k] = top, top_r
        m[k + 1] = [bot[j] - factor * top[j] for j in range(n)]
        r[k + 1] = bot_r - factor * top_r
    x = [None] * n
    for i in reversed(range(n)):
        acc = r[i]
        for j in range(i + 1, n):
            acc = acc - m[i][j] * x[j]
        x[i] = acc / m[i][i]
    xs = jnp.stack(x, axis=1)  # (S, n, K, F)
    if c is None:
        y = jnp.einsum("sij,sjkf->sfik", q.astype(complex), xs)
    else:  # fold Q into C: only the requested outputs are formed
        cq = jnp.einsum("pi,sij->spj", jnp.atleast_2d(jnp.asarray(c, dtype=float)), q)
        y = jnp.einsum("spj,sjkf->sfpk", cq.astype(complex), xs)
    if vec:
        y = y[..., 0]
    return y[0] if single else y


def _check_poles(poles, n):
    poles = np.asarray(poles, dtype=complex).reshape(-1)
    if poles.shape != (n,):
        raise ValueError(f"need {n} poles (one per state), got {poles.shape[0]}")
    if not np.all(np.isfinite(poles)):
        raise ValueError(f"poles {poles} must be finite")
    if np.any(poles.real >= 0):
        bad = poles[poles.real >= 0]
        raise ValueError(f"poles {bad} are not in the open left half-plane: an observer with them "
                         "would not converge; request poles with negative real parts")
    coeffs = np.poly(poles)
    if np.max(np.abs(coeffs.imag)) > 1e-9 * np.max(np.abs(coeffs)):
        raise ValueError(f"poles {poles} are not closed under conjugation; a real gain cannot "
                         "place them")
    return poles


def _check_observable(obs):
    obs = np.asarray(obs)
    norms = np.linalg.norm(obs, axis=0)
    s = np.linalg.svd(obs / np.where(norms > 0, norms, 1.0), compute_uv=False)
    if np.any(norms == 0) or s[-1] < 1e-12 * s[0]:
        raise ValueError("the pair (A, C) is not observable (rank-deficient observability matrix); "
                         "no gain can place all observer poles")


def place_observer(a: Float[ArrayLike, "n n"], c: Float[ArrayLike, "p n"], poles: ArrayLike, *,
                   method: str = "auto", max_sweeps: int = 50,
                   tol: float = 1e-10) -> Float[Array, "n p"]:
    """Observer gain ``K`` (n, m) with the eigenvalues of ``A - K C`` at ``poles``.

    - ``method="ackermann"`` (one output only): :func:`ackermann_observer`; places repeated poles
      (the closed loop is then a Jordan block). Pure JAX and differentiable in ``A``, ``C``.
    - ``method="robust"`` (any number of outputs): the Kautsky-Nichols-Van Dooren method 0 on the
      dual pair ``(A^T, C^T)``: the closed-loop eigenvectors are chosen, one at a time, as close to
      orthogonal to the others as the placement allows, which minimizes the eigenvalue sensitivity
      (the condition number of the eigenvector matrix). Iterative, runs on the host in numpy (it is
      a design step, not part of a batched workload). Each pole may appear at most ``m`` times
      (the closed loop must stay diagonalizable). Complex poles in conjugate pairs.
    - ``method="auto"``: Ackermann for one output, robust otherwise.

    **Raises:** ``ValueError`` naming the problem: poles not in the open left half-plane, not
    closed under conjugation, a pole repeated more than ``m`` times (robust method), or an
    unobservable pair.
    """
    a = np.asarray(a, dtype=float)
    c = np.atleast_2d(np.asarray(c, dtype=float))
    n, m = a.shape[0], c.shape[0]
    if a.shape != (n, n) or c.shape[1] != n:
        raise ValueError(f"A must be square and C (m, n): got A {a.shape}, C {c.shape}")
    if method == "auto":
        method = "ackermann" if m == 1 else "robust"
    if method == "ackermann":
        return ackermann_observer(a, c, poles)[:, None]
    if method != "robust":
        raise ValueError(f"method={method!r}: use 'auto', 'ackermann' or 'robust'")
    poles = _check_poles(poles, n)
    _check_observable(observability_matrix(a, c))
    if np.linalg.matrix_rank(c) < m:
        raise ValueError(f"C has linearly dependent rows (rank {np.linalg.matrix_rank(c)} < {m}); "
                         "drop the redundant outputs")
    # order: real poles, then each conjugate pair as (p, conj p) with Im p > 0
    real = np.sort(poles[np.abs(poles.imag) <= 1e-12 * np.maximum(1, np.abs(poles))].real)
    upper = poles[poles.imag > 1e-12 * np.maximum(1, np.abs(poles))]
    ordered = list(real.astype(complex))
    for p in upper:
        ordered += [p, np.conj(p)]
    lam = np.array(ordered)
    for p in np.unique(np.round(lam, 12)):
        mult = int(np.sum(np.isclose(lam, p, rtol=1e-9, atol=1e-12)))
        if mult > m:
            raise ValueError(f"pole {p:.6g} is requested {mult} times but C has only {m} "
                             f"output(s): the robust method places a pole at most {m} times "
                             "(distinct eigenvectors); spread the poles slightly, or use one "
                             "output with method='ackermann'")
    # dual problem: eig(A^T - C^T F) with F = K^T
    at, b = a.T, c.T
    q, r = np.linalg.qr(b, mode="complete")
    u0, u1, z = q[:, :m], q[:, m:], r[:m]
    bases = []
    for p in lam:  # admissible eigenvectors: null space of U1^T (A^T - p I)
        _, _, vh = np.linalg.svd(u1.T @ (at - p * np.eye(n)))
        bases.append(vh[-m:].conj().T)
    x = np.empty((n, n), dtype=complex)
    seen: dict = {}
    for j, p in enumerate(lam):
        k = seen.get(np.round(p, 9), 0)
        seen[np.round(p, 9)] = k + 1
        x[:, j] = bases[j][:, k % m]
    is_pair = np.abs(lam.imag) > 0
    prev = -np.inf
    for _ in range(max_sweeps):
        for j in range(n):
            if is_pair[j] and lam[j].imag < 0:
                continue  # set with its partner
            others = np.delete(x, j, axis=1)
            qq, _ = np.linalg.qr(others, mode="complete")
            y = qq[:, -1]
            v = bases[j] @ (bases[j].conj().T @ y)
            x[:, j] = v / np.linalg.norm(v)
            if is_pair[j]:
                x[:, j + 1] = np.conj(x[:, j])
        detx = abs(np.linalg.det(x))
        if abs(detx - prev) <= tol * max(detx, 1e-300):
            break
        prev = detx
    if np.linalg.cond(x) > 1e12:
        raise ValueError("robust placement failed: the closed-loop eigenvectors are (nearly) "
                         "dependent; the requested poles cannot be placed robustly")
    closed = (x * lam) @ np.linalg.inv(x)
    f = np.linalg.solve(z, u0.T @ (at - closed))
    return jnp.asarray(f.real.T)


def observer_error_response(a, c, k, g, omegas):
    """Estimation-error response ``e = x - x_hat`` to a disturbance entering as ``G w``:
    ``(j omega E - A + K C)^{-1} G`` (the error dynamics ``e' = (A - K C) e + G w``)."""
    k = jnp.atleast_2d(jnp.asarray(k, dtype=float).T).T
    return frequency_response(jnp.asarray(a) - k @ jnp.atleast_2d(c), g, omegas)


class DiscreteObserver(eqx.Module):
    """Exact discretization of $\\dot{\\hat x} = (A - K C)\\hat x + K y + b$ over a sample interval
    ``dt``: ``x_{k+1} = Phi x_k + Gamma0 y_k + Gamma1 (y_{k+1} - y_k) + beta``.

    ``hold="zoh"`` holds ``y`` constant over the interval (``Gamma1 = 0``; causal, the source's
    choice); ``hold="foh"`` interpolates it linearly (one sample of look-ahead, exact for
    piecewise-linear ``y``, second order in ``dt`` for smooth signals).
    """

    phi: jax.Array
    gamma0: jax.Array
    gamma1: jax.Array
    beta: jax.Array
    dt: float = eqx.field(static=True)

    @staticmethod
    def create(a, c, k, dt, *, b=None, hold: str = "zoh") -> DiscreteObserver:
        if hold not in ("zoh", "foh"):
            raise ValueError(f"hold={hold!r}: use 'zoh' or 'foh'")
        if not float(dt) > 0:
            raise ValueError(f"dt={dt}: the sample interval must be > 0 s")
        a = jnp.asarray(a, dtype=float)
        c = jnp.atleast_2d(jnp.asarray(c, dtype=float))
        n, m = a.shape[0], c.shape[0]
        k = jnp.asarray(k, dtype=float).reshape(n, m)
        b = jnp.zeros(n) if b is None else jnp.asarray(b, dtype=float)
        # augmented generator: x' = (A - K C) x + K y + b, y' = s (slope), s' = 0, 1' = 0
        size = n + 2 * m + 1
        mat = jnp.zeros((size, size))
        mat = mat.at[:n, :n].set(a - k @ c).at[:n, n:n + m].set(k).at[:n, -1].set(b)
        mat = mat.at[n:n + m, n + m:n + 2 * m].set(jnp.eye(m))
        e = jax.scipy.linalg.expm(mat * dt)
        gamma1 = e[:n, n + m:n + 2 * m] / dt if hold == "foh" else jnp.zeros((n, m))
        return DiscreteObserver(e[:n, :n], e[:n, n:n + m], gamma1, e[:n, -1], float(dt))

    def __call__(self, y, x0=None):
        """Run over samples ``y`` of shape ``(N, m)`` (or ``(N,)``); returns ``x_hat`` ``(N, n)``,
        with ``x_hat[0] = x0`` (default zero)."""
        y = jnp.asarray(y, dtype=float)
        y = y[:, None] if y.ndim == 1 else y
        n = self.phi.shape[0]
        x0 = jnp.zeros(n) if x0 is None else jnp.asarray(x0, dtype=float)

        def step(x, yy):
            y0, y1 = yy
            xn = self.phi @ x + self.gamma0 @ y0 + self.gamma1 @ (y1 - y0) + self.beta
            return xn, xn

        _, xs = jax.lax.scan(step, x0, (y[:-1], y[1:]))
        return jnp.concatenate([x0[None], xs], axis=0)


def simulate_with_observer(rig, params, conditions, gain: Float[ArrayLike, " n"],
                           ts: Float[ArrayLike, " T"], *, xhat0=None, x0=None,
                           constant_input: bool = True, solver=None, rtol: float = 1e-9,
                           atol: float = 1e-12, max_steps: int = 1_000_000):
    """Integrate the rig's nonlinear equations and a Luenberger observer on its linear model
    together with diffrax (one augmented ODE, continuous measurement ``y = rig.observe``).

    The observer is $\\dot{\\hat x} = (A - K C)\\hat x + K y + b$ with ``(A, C, b)`` from
    ``rig.state_space`` (``b`` is dropped when ``constant_input=False``). ``gain`` has shape
    ``(n,)`` or ``(n, m)``. For large observer poles the system is stiff: pass an implicit
    ``solver`` (e.g. ``diffrax.Kvaerno5()``) for long runs.

    **Returns:** ``(x, x_hat)``, each ``(len(ts), n)`` at the sample times ``ts`` (s).
    """
    a, c, _, b = rig.state_space(params, conditions)
    n = a.shape[0]
    k = jnp.asarray(gain, dtype=float).reshape(n, -1)
    b = b if constant_input else jnp.zeros_like(b)
    ts = jnp.asarray(ts, dtype=float)
    start = rig.initial_state(params, conditions) if x0 is None else jnp.asarray(x0, dtype=float)
    xh0 = jnp.zeros(n) if xhat0 is None else jnp.asarray(xhat0, dtype=float)

    def field(t, z, args):
        x, xh = z[:n], z[n:]
        y = rig.observe(t, x, params, conditions)
        return jnp.concatenate([rig.vector_field(t, x, params, conditions),
                                a @ xh + k @ (y - c @ xh) + b])

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field), solver or diffrax.Dopri8(), t0=ts[0], t1=ts[-1], dt0=None,
        y0=jnp.concatenate([start, xh0]), saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol), max_steps=max_steps)
    return sol.ys[:, :n], sol.ys[:, n:]
