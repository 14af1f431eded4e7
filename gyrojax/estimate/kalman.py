"""Square-root Kalman filter and RTS smoother under ``lax.scan``; the ESG augmented-state filter.

Generic part: a linear time-varying model $x_{j+1} = \\Phi_j x_j + \\gamma_j + w_j$,
$y_j = H x_j + v_j$, with $w \\sim N(0, L_{Q} L_{Q}^T)$, $v \\sim N(0, L_R L_R^T)$. The covariance
is carried as a lower-triangular factor ``S`` (``P = S S^T``) and both steps are QR
triangularizations of pre-arrays (no covariance subtraction, no loss of positivity), so gyro-scale
states (1e-10 rad/s) need no jitter. Innovations are returned standardized by the Cholesky factor of
their covariance (N(0, I) under the model).

ESG part (docs/rigs/esg.md): state ``(alpha1, alpha2, p, delta)`` with ``p`` the linear-model
parameters (6.9) and ``delta = m - m*`` the start-up transients of the six drift coefficients
(``delta' = -k delta``). Discretised with the regression's integrals between samples, the
integrands evaluated at the measured angles (third-order three-point rule, see
:func:`interval_integrals`).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jaxtyping import Array, ArrayLike, Float

from ..record import BenchRecord
from ..simulate import integrate
from ._result import AbstractNamedEstimate

__all__ = ["KalmanResult", "square_root_filter", "rts_smoother", "kalman_gains", "apply_gains",
           "esg_augmented_filter", "ESGFilterResult"]


def _tria(a):
    """Lower-triangular ``L`` with ``L L^T = a a^T`` (QR of ``a^T``), sign-normalized."""
    r = jnp.linalg.qr(a.T, mode="r")
    lower = r.T[:, : a.shape[0]]
    sign = jnp.sign(jnp.diagonal(lower))
    sign = jnp.where(sign == 0, 1.0, sign)
    return lower * sign[None, :]


class KalmanResult(eqx.Module):
    """Filter output (leading time axis ``n``).

    - `x_pred`, `s_pred`: prior mean and covariance factor at each sample (before its update).
    - `x_filt`, `s_filt`: posterior mean and factor after the update at each sample.
    - `innovations`: standardized innovations ``L_S^{-1} (y - H x_pred)``, N(0, I) under the model.
    - `log_likelihood`: sum of Gaussian log-densities of the innovations.
    """

    x_pred: jax.Array
    s_pred: jax.Array
    x_filt: jax.Array
    s_filt: jax.Array
    innovations: jax.Array
    log_likelihood: jax.Array

    @property
    def p_filt(self):
        return self.s_filt @ jnp.swapaxes(self.s_filt, -1, -2)


def square_root_filter(x0: Float[ArrayLike, " d"], s0: Float[ArrayLike, "d d"],
                       phis: Float[ArrayLike, "n-1 d d"], gammas: Float[ArrayLike, "n-1 d"],
                       sqrt_qs: Float[ArrayLike, "n-1 d d"],
                       h: Float[ArrayLike, "m d"] | Float[ArrayLike, "n m d"],
                       sqrt_r: Float[ArrayLike, "m m"], ys: Float[ArrayLike, "n m"], *,
                       history: bool = True) -> KalmanResult:
    """Square-root Kalman filter over ``n`` samples.

    **Arguments:**
    - `x0`, `s0`: prior mean (d,) and covariance factor (d, d) at the first sample (any square
      factor, e.g. of a rank-deficient prior).
    - `phis`, `gammas`, `sqrt_qs`: transitions from sample j to j+1, shapes (n-1, d, d),
      (n-1, d), (n-1, d, d) (``sqrt_qs`` may be zeros for constant parameters).
    - `h`: measurement matrix (m, d), or (n, m, d) when it varies with time; `sqrt_r` (m, m):
      noise factor; `ys` (n, m).
    - `history`: keep every sample's means and factors; with ``False`` only the last sample's are
      returned (leading axis of length 1) — what a batched Monte Carlo needs, at O(d^2) memory.

    **Returns:** a :class:`KalmanResult`.
    """
    d = x0.shape[0]
    hs = h if h.ndim == 3 else jnp.broadcast_to(h, (ys.shape[0],) + h.shape)
    m = hs.shape[1]

    def update(x, s, y, h):
        pre = jnp.block([[sqrt_r, h @ s], [jnp.zeros((d, m)), s]])
        post = _tria(pre)
        sy = post[:m, :m]
        kbar = post[m:, :m]
        s_new = post[m:, m:]
        e = jsl.solve_triangular(sy, y - h @ x, lower=True)
        x_new = x + kbar @ e
        ll = -0.5 * (e @ e) - jnp.sum(jnp.log(jnp.abs(jnp.diagonal(sy)))) \
            - 0.5 * m * jnp.log(2 * jnp.pi)
        return x_new, s_new, e, ll

    x1, s1, e1, ll1 = update(x0, s0, ys[0], hs[0])

    def step(carry, inp):
        x, s = carry
        phi, gamma, sq, y, h = inp
        xp = phi @ x + gamma
        sp = _tria(jnp.concatenate([phi @ s, sq], axis=1))
        xn, sn, e, ll = update(xp, sp, y, h)
        return (xn, sn), ((xp, sp, xn, sn, e, ll) if history else (e, ll))

    (xl, sl), outs = jax.lax.scan(step, (x1, s1), (phis, gammas, sqrt_qs, ys[1:], hs[1:]))
    if not history:
        es, lls = outs
        innov = jnp.concatenate([e1[None], es], axis=0)
        return KalmanResult(xl[None], sl[None], xl[None], sl[None], innov, ll1 + jnp.sum(lls))
    xp, sp, xf, sf, es, lls = outs
    cat = lambda a, b: jnp.concatenate([a[None], b], axis=0)  # noqa: E731
    return KalmanResult(cat(x0, xp), cat(s0, sp), cat(x1, xf), cat(s1, sf), cat(e1, es),
                        ll1 + jnp.sum(lls))


def kalman_gains(s0, phis, sqrt_qs, h, sqrt_r):
    """The covariance recursion alone: gains ``K_j`` (n, d, m) and the final covariance factor.

    For a linear model the covariances and gains do not depend on the measurements, so across
    Monte Carlo runs of one model they are computed once (here) and applied to every run with
    :func:`apply_gains` as batched matrix products (``benchmarks/schuler_kf.py`` times it).
    """
    d = s0.shape[0]
    n = phis.shape[0] + 1
    hs = h if h.ndim == 3 else jnp.broadcast_to(h, (n,) + h.shape)
    m = hs.shape[1]

    def update(s, h):
        post = _tria(jnp.block([[sqrt_r, h @ s], [jnp.zeros((d, m)), s]]))
        sy, kbar = post[:m, :m], post[m:, :m]
        gain = jsl.solve_triangular(sy.T, kbar.T, lower=False).T  # K = Kbar Sy^{-1}
        return post[m:, m:], gain

    s1, k1 = update(s0, hs[0])

    def step(s, inp):
        phi, sq, h = inp
        sn, k = update(_tria(jnp.concatenate([phi @ s, sq], axis=1)), h)
        return sn, k

    s_last, ks = jax.lax.scan(step, s1, (phis, sqrt_qs, hs[1:]))
    return jnp.concatenate([k1[None], ks], axis=0), s_last


def apply_gains(x0, phis, h, gains, ys):
    """Run precomputed gains over a batch of measurement sequences ``ys`` (r, n, m) from prior
    means ``x0`` (r, d): returns the final filtered means (r, d). Each step is two batched matrix
    products over the runs."""
    n = ys.shape[1]
    hs = h if h.ndim == 3 else jnp.broadcast_to(h, (n,) + h.shape)
    yt = jnp.swapaxes(ys, 0, 1)  # (n, r, m)

    def upd(x, h, k, y):
        return x + (y - x @ h.T) @ k.T

    x1 = upd(x0, hs[0], gains[0], yt[0])

    def step(x, inp):
        phi, h, k, y = inp
        return upd(x @ phi.T, h, k, y), None

    x_last, _ = jax.lax.scan(step, x1, (phis, hs[1:], gains[1:], yt[1:]))
    return x_last


def rts_smoother(result: KalmanResult, phis: Float[ArrayLike, "n-1 d d"]
                 ) -> tuple[Float[Array, "n d"], Float[Array, "n d d"]]:
    """Rauch-Tung-Striebel smoother: smoothed means (n, d) and covariances (n, d, d).

    The gain $G_j = P_j \\Phi_j^T (P^-_{j+1})^{-1}$ is formed by triangular solves with the
    predicted factor; covariances are symmetrized.
    """
    p_f = result.p_filt

    def step(carry, inp):
        xs_next, ps_next = carry
        xf, pf, phi, xp_next, sp_next = inp
        # G = pf phi^T (sp sp^T)^{-1}
        tmp = jsl.solve_triangular(sp_next, phi @ pf, lower=True)
        g = jsl.solve_triangular(sp_next.T, tmp, lower=False).T
        pp_next = sp_next @ sp_next.T
        xs = xf + g @ (xs_next - xp_next)
        ps = pf + g @ (ps_next - pp_next) @ g.T
        ps = 0.5 * (ps + ps.T)
        return (xs, ps), (xs, ps)

    last = (result.x_filt[-1], p_f[-1])
    _, (xs, ps) = jax.lax.scan(
        step, last, (result.x_filt[:-1], p_f[:-1], phis, result.x_pred[1:], result.s_pred[1:]),
        reverse=True)
    return (jnp.concatenate([xs, result.x_filt[-1:]], 0),
            jnp.concatenate([ps, p_f[-1:]], 0))


class ESGFilterResult(AbstractNamedEstimate):
    """ESG augmented-state filter output.

    - `names`: state names (``alpha1, alpha2``, the linear-model parameters, ``d{m}_0`` transients).
    - `values`, `stderr`: final filtered estimates of the parameters (the transients are given at
      the first sample, i.e. ``m0 - m*``).
    - `filter`: the :class:`KalmanResult`; `smoothed_x`, `smoothed_std`: RTS means and standard
      deviations over time.
    """

    names: tuple[str, ...] = eqx.field(static=True)
    values: jax.Array
    stderr: jax.Array
    filter: KalmanResult
    smoothed_x: jax.Array
    smoothed_std: jax.Array


def interval_integrals(tau, f):
    """Integrals of sampled ``f`` over each sample interval, third-order accurate.

    Each interval ``[tau_j, tau_{j+1}]`` integrates the parabola through three neighbouring samples
    (``j-1, j, j+1``; for the first interval ``j, j+1, j+2``), with exact weights for non-uniform
    sampling. For uniform steps ``h`` the weights are ``h (-1, 8, 5) / 12``. The trapezoid rule's
    O(h^2) bias (~1e-4 deg/h at 1-min samples) would exceed the filter's standard errors.
    """
    if tau.shape[0] < 3:
        return 0.5 * jnp.diff(tau).reshape(-1, *([1] * (f.ndim - 1))) * (f[1:] + f[:-1])

    def weights(a, b):  # previous node at -a, interval [0, b]
        w0 = -(b**3) / (6 * a * (a + b))
        w1 = b**2 / (6 * a) + b / 2
        w2 = (b**2 / 3 + a * b / 2) / (a + b)
        return w0, w1, w2

    h = jnp.diff(tau)
    expand = (slice(None),) + (None,) * (f.ndim - 1)
    w0, w1, w2 = weights(h[:-1], h[1:])  # intervals 1..n-2 with left neighbour
    inner = w0[expand] * f[:-2] + w1[expand] * f[1:-1] + w2[expand] * f[2:]
    v0, v1, v2 = weights(h[1], h[0])  # interval 0, mirrored, right neighbour tau_2
    first = v0 * f[2] + v1 * f[1] + v2 * f[0]
    return jnp.concatenate([first[None], inner], axis=0)


@eqx.filter_jit
def _esg_filter(rig, names, transient, passes, record, conditions, noise_std, k, prior_std,
                transient_std, q_param):
    all_names = rig.regression_names
    cols = jnp.array([all_names.index(n) for n in names])
    tau = record.t * rig.time_scale
    alpha = record.y
    h = jnp.diff(tau)
    kp = len(names)
    drift_cols = [names.index(n) for n in rig.drift_names]
    nt = len(drift_cols) if transient else 0
    d = 2 + kp + nt
    n1 = h.shape[0]
    pidx = jnp.arange(2, 2 + kp)
    sq = jnp.zeros((n1, d, d)).at[:, pidx, pidx].set(q_param * jnp.sqrt(h)[:, None])
    x0 = jnp.zeros(d).at[0:2].set(alpha[0])
    s0 = jnp.diag(jnp.concatenate([jnp.full(2, noise_std), prior_std,
                                   jnp.full(nt, transient_std)]))
    hm = jnp.zeros((2, d)).at[0, 0].set(1.0).at[1, 1].set(1.0)

    def run(alpha_lin, p_ref=None):
        c, f = rig.regression_terms(alpha_lin, conditions)
        f = f[..., cols]
        a_int = interval_integrals(tau, f)  # (n-1, 2, k)
        c_int = interval_integrals(tau, c)
        phi = jnp.broadcast_to(jnp.eye(d), (n1, d, d))
        phi = phi.at[:, 0:2, 2 : 2 + kp].set(a_int)
        if p_ref is not None:
            # linearization about a reference trajectory alpha_ref(tau) of the rig (EKF form):
            # alpha_{j+1} = alpha_ref_{j+1} + (I + int J)(alpha_j - alpha_ref_j)
            #               + int F (p - p_ref),   J = d(c + F p_ref)/d alpha
            def rate(a):
                cc, ff = rig.regression_terms(a, conditions)
                return cc + ff[..., cols] @ p_ref

            jac = jax.vmap(jax.jacfwd(rate))(alpha_lin)
            j_int = interval_integrals(tau, jac)
            phi = phi.at[:, 0:2, 0:2].add(j_int)
            c_int = (alpha_lin[1:] - alpha_lin[:-1]
                     - jnp.einsum("nij,nj->ni", jnp.eye(2) + j_int, alpha_lin[:-1]) + alpha_lin[:-1]
                     - a_int @ p_ref)
        if transient:
            kh = k * h
            frac = jnp.where(kh > 1e-8, -jnp.expm1(-kh) / jnp.where(kh > 1e-8, kh, 1.0),
                             1.0 - kh / 2)
            a_m = a_int[..., jnp.array(drift_cols)] * frac[:, None, None]
            phi = phi.at[:, 0:2, 2 + kp :].set(a_m)
            idx = jnp.arange(2 + kp, d)
            phi = phi.at[:, idx, idx].set(jnp.exp(-kh)[:, None])
        gamma = jnp.zeros((n1, d)).at[:, 0:2].set(c_int)
        res = square_root_filter(x0, s0, phi, gamma, sq, hm, noise_std * jnp.eye(2), alpha)
        xs, ps = rts_smoother(res, phi)
        return res, xs, ps

    # pass 1 linearizes at the measured angles (the paper's choice); later passes about the
    # noise-free trajectory of the rig simulated from the previous pass's estimates, with the
    # Jacobian d(c + F p)/d alpha in the transition (iterated EKF). This removes the
    # errors-in-variables effect of the angle noise entering c(alpha), F(alpha), which otherwise
    # inflates the true error variance about 2x over the reported one at 1-min samples.
    res, xs, ps = run(alpha)
    for _ in range(passes - 1):
        est = dict(zip(names, xs[0, 2 : 2 + kp]))
        if transient:
            est |= dict(zip((f"d{n}_0" for n in rig.drift_names), xs[0, 2 + kp :]))
            est["k_tr"] = k
        est |= {"alpha10": xs[0, 0], "alpha20": xs[0, 1]}
        params = rig.param_space.null_values() | est
        ref = integrate(rig, params, conditions, record.t, throw=False)
        res, xs, ps = run(ref, xs[0, 2 : 2 + kp])
    p_last = res.p_filt[-1]
    values = res.x_filt[-1, 2:]
    stderr = jnp.sqrt(jnp.diagonal(p_last)[2:])
    if transient:  # transients are reported at the first sample (smoothed)
        values = values.at[kp:].set(xs[0, 2 + kp :])
        stderr = stderr.at[kp:].set(jnp.sqrt(jnp.diagonal(ps[0])[2 + kp :]))
    return values, stderr, res, xs, jnp.sqrt(jnp.diagonal(ps, axis1=-2, axis2=-1))


def esg_augmented_filter(rig, record: BenchRecord, conditions, *, noise_std: float,
                         names: Sequence[str] | None = None, transient_k: float | None = None,
                         prior_std: Sequence[float] | None = None, transient_std: float = 0.1,
                         param_random_walk: float = 0.0, passes: int = 2) -> ESGFilterResult:
    """The augmented-state square-root Kalman filter (7.1)-(7.3) of the ESG rig, with RTS smoother.

    **Arguments:**
    - `rig`, `record`, `conditions`: model, measured angles, test conditions.
    - `noise_std`: angle pick-off noise sigma_v (rad).
    - `names`: linear-model parameters in the state (default: all of ``rig.regression_names``).
    - `transient_k`: decay rate ``k`` of law (7.4) per unit of tau; ``None`` leaves the transient
      states out (a constant-parameter filter).
    - `prior_std`: prior standard deviations of the parameters (default 100 x their scales).
    - `transient_std`: prior std of the transients ``m0 - m*`` (normalized).
    - `param_random_walk`: random-walk intensity on the parameters (per sqrt(tau)), 0 = constant.
    - `passes`: 1 = the paper's filter (c, F at the measured angles); 2 (default) re-runs it with
      c, F on the rig's noise-free trajectory simulated from the first pass's smoothed estimates
      (an iterated filter), which makes the reported standard errors consistent with the errors.

    **Returns:** an :class:`ESGFilterResult` whose `values` are the settled drifts ``m*`` etc.
    """
    names = tuple(rig.regression_names if names is None else names)
    space = rig.param_space
    space.check_names(names)
    if noise_std <= 0:
        raise ValueError(f"noise_std={noise_std}: the filter needs the angle noise sigma_v > 0 "
                         "(rad); give the pick-off noise, e.g. 1 arcsec = 4.85e-6 rad")
    if passes < 1:
        raise ValueError(f"passes={passes}: need at least one filter pass")
    transient = transient_k is not None
    if transient and transient_k <= 0:
        raise ValueError(f"transient_k={transient_k}: the decay rate must be > 0 (per unit tau)")
    if transient and not all(n in names for n in rig.drift_names):
        raise ValueError("transient states need all six drift coefficients among names")
    ps = jnp.asarray(prior_std if prior_std is not None else 100 * space.scales(names), float)
    values, stderr, res, xs, sstd = _esg_filter(
        rig, names, transient, int(passes), record, conditions, jnp.asarray(noise_std, float),
        jnp.asarray(transient_k if transient else 1.0, float), ps,
        jnp.asarray(transient_std, float), jnp.asarray(param_random_walk, float))
    out_names = names + (tuple(f"d{n}_0" for n in rig.drift_names) if transient else ())
    return ESGFilterResult(names=out_names, values=values, stderr=stderr, filter=res, smoothed_x=xs,
                           smoothed_std=sstd)
