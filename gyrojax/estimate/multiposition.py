"""Multi-position tools for a strapdown IMU on a stand (no turntable, no reference attitude).

- :func:`detect_static`: static intervals from the gyro and accelerometer (moving statistics
  against a robust noise level), breaking at time gaps and masked samples.
- :func:`calibrate_accelerometer`: the |f| = g calibration (Tedaldi et al. 2014): biases, scale
  factors and the three non-orthogonality terms of an upper-triangular gauge, by
  Levenberg-Marquardt (optimistix) on the static means; says when the poses do not determine it.
- :func:`calibrate_gyro`: gyro scale factors and misalignments by propagating the gravity direction
  through the turns between static poses (``du/dt = -w x u`` in the body frame, exact rotation per
  sample under ``lax.scan``) and matching the next pose's accelerometer direction.
- :func:`leave_one_position_out`, :func:`time_ordered_split`: held-out checks.

Model conventions follow :mod:`gyrojax.models.imu`: ``f_meas = b_a + (I + diag(s_a) + M_a) f``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..datasets import masked
from ..record import BenchRecord
from ._linalg import scaled_lstsq, value_and_jacfwd
from .least_squares import stationary_converged

__all__ = ["Segment", "detect_static", "calibrate_accelerometer", "calibrate_gyro",
           "AccelCalibration", "GyroCalibration", "leave_one_position_out", "time_ordered_split",
           "segment_means"]


@dataclasses.dataclass(frozen=True)
class Segment:
    """A static interval: samples ``i0:i1`` (end exclusive) and its times."""

    i0: int
    i1: int
    t0: float
    t1: float

    @property
    def n(self) -> int:
        return self.i1 - self.i0


def _robust_sd(x):
    d = np.diff(x, axis=0)
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2)


def detect_static(record: BenchRecord, *, window_s: float = 1.0, min_s: float = 1.0,
                  trim_s: float = 0.2, k: float = 4.0, gyro_threshold=None) -> list[Segment]:
    """Static intervals of an IMU record.

    A sample is static when, over a centred window of ``window_s``, the mean gyro deviation from
    the record's median rate stays below ``gyro_threshold`` (rad/s; default ``k`` times the robust
    noise of the window mean plus 0.02 rad/s for a hand-held record's residual bias) and every
    accelerometer axis's moving std stays below ``k`` times its robust sample noise. Runs shorter
    than ``min_s`` are dropped, ``trim_s`` is cut from both ends, and intervals break at time gaps
    (> 1.5 median steps) and at masked samples (``masked_s``).
    """
    t = np.asarray(record.t, float)
    y = np.asarray(record.y, float)
    ch = list(record.channels)
    dt = float(np.median(np.diff(t)))
    m = max(3, int(round(window_s / dt)) | 1)
    ker = np.ones(m) / m

    def movmean(x):
        return np.stack([np.convolve(x[:, j], ker, mode="same") for j in range(x.shape[1])], 1)

    ok = ~masked(record)
    gi = [ch.index(c) for c in ("wx", "wy", "wz") if c in ch]
    ai = [ch.index(c) for c in ("ax", "ay", "az") if c in ch]
    if gi:
        w = y[:, gi] - np.median(y[:, gi], axis=0)
        sd = _robust_sd(y[:, gi])
        thr = gyro_threshold if gyro_threshold is not None else \
            k * np.sqrt(np.sum(sd ** 2) / m) + 0.02
        ok &= np.linalg.norm(movmean(w), axis=1) < thr
    if ai:
        a = y[:, ai]
        sd = _robust_sd(a)
        var = movmean(a ** 2) - movmean(a) ** 2
        ok &= np.all(np.sqrt(np.maximum(var, 0)) < k * sd, axis=1)
    breaks = np.flatnonzero(np.diff(t) > 1.5 * dt)
    ok[breaks] = False
    ok[np.minimum(breaks + 1, len(ok) - 1)] = False
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(int), [0]])))
    trim = int(round(trim_s / dt))
    out = []
    for i0, i1 in zip(edges[::2], edges[1::2]):
        i0, i1 = i0 + trim, i1 - trim
        if (i1 - i0) * dt >= min_s:
            out.append(Segment(int(i0), int(i1), float(t[i0]), float(t[i1 - 1])))
    return out


def segment_means(record: BenchRecord, segments, channels=("ax", "ay", "az")):
    """``(n_segments, len(channels))`` means and their standard errors (white-noise form)."""
    y = np.stack([np.asarray(record.channel(c)) for c in channels], 1)
    mean = np.stack([y[s.i0:s.i1].mean(0) for s in segments])
    se = np.stack([y[s.i0:s.i1].std(0, ddof=1) / np.sqrt(s.n) for s in segments])
    return mean, se


# -- accelerometer: |f| = g ------------------------------------------------------------------
ACCEL_NAMES = ("bax", "bay", "baz", "sax", "say", "saz", "maxy", "maxz", "mayz")
ACCEL_MAX_STEPS = 200  # Levenberg-Marquardt budget of the |f| = g fit


def _accel_matrix(theta):
    s, m = theta[3:6], theta[6:9]
    return jnp.array([[1 + s[0], m[0], m[1]], [0.0, 1 + s[1], m[2]], [0.0, 0.0, 1 + s[2]]])


def _true_force(theta, f_meas):
    """Invert ``f_meas = b + A f``: ``f = A^-1 (f_meas - b)``."""
    return jnp.linalg.solve(_accel_matrix(theta), (f_meas - theta[:3]).T).T


def _accel_resid(theta, args):
    means, w, gravity = args
    return (jnp.linalg.norm(_true_force(theta, means), axis=1) - gravity) * jnp.sqrt(w)


@jax.jit
def _accel_fit(th0, means, w, gravity):
    """LM fit, Jacobian and residual at the solution: compiled once per number of poses (the
    leave-one-position-out loop and repeated units reuse it)."""
    args = (means, w, gravity)
    sol = optx.least_squares(_accel_resid, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12), th0,
                             args, max_steps=ACCEL_MAX_STEPS, throw=False)
    return _at_solution(_accel_resid, sol, args)


def _at_solution(resid, sol, args):
    """``(value, Jacobian, residual, converged)`` at an optimistix least-squares solution;
    converged by the rule of every Gauss-Newton fit in gyrojax (the solver's test passed, or the
    step left is under ``STATIONARY_SE`` standard errors: ``stationary_converged``)."""
    r, jac = value_and_jacfwd(lambda x: resid(x, args))(sol.value)
    minus_step = scaled_lstsq(jac, r)[0]
    sigma2 = jnp.sum(r**2) / max(r.shape[0] - jac.shape[1], 1)
    return sol.value, jac, r, stationary_converged(sol.result, jac, minus_step, sigma2)[0]


@dataclasses.dataclass
class AccelCalibration:
    """Result of :func:`calibrate_accelerometer` (SI; ``params`` keyed as in the IMU rig)."""

    params: dict
    stderr: dict
    residual: np.ndarray  # |f_cal| - g per pose, m/s^2
    rank: int
    condition: float
    determined: bool
    message: str
    gravity: float
    converged: bool = True  # the Levenberg-Marquardt fit ended at its solution

    def correct(self, f_meas):
        th = jnp.asarray([self.params[n] for n in ACCEL_NAMES])
        return np.asarray(_true_force(th, jnp.asarray(f_meas, float)))


def calibrate_accelerometer(means, gravity: float, *, weights=None) -> AccelCalibration:
    """Fit ``b_a``, ``s_a`` and the upper-triangular misalignments ``ma_xy ma_xz ma_yz`` so that
    every static mean has ``|f| = g`` (Levenberg-Marquardt, optimistix). The rotational gauge (3
    terms) is unobservable without a reference attitude and fixed to zero. With fewer than 9 poses,
    or poses that leave the Jacobian rank-deficient (e.g. all poses about one axis), the result
    says so (``determined=False``) rather than report arbitrary numbers as calibrated."""
    means = np.asarray(means, float)
    n = len(means)
    w = np.ones(n) if weights is None else np.asarray(weights, float)
    th0 = np.zeros(9)
    th0[:3] = means.mean(0) * (n >= 6)
    th, jac, r, converged = (np.asarray(x) for x in _accel_fit(th0, means, w, float(gravity)))
    sv = np.linalg.svd(jac, compute_uv=False)
    rank = int(np.sum(sv > 1e-9 * sv[0]))
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    dof = n - 9
    determined = rank == 9 and dof > 0 and cond < 1e8
    if determined:
        s2 = float(r @ r / dof)
        cov = s2 * np.linalg.pinv(jac.T @ jac)
        se = np.sqrt(np.diag(cov))
        msg = f"{n} poses, rank 9, {dof} residual dof"
    else:
        se = np.full(9, np.nan)
        msg = (f"{n} poses give rank {rank} of 9 (condition {cond:.3g}): the 9-term accelerometer "
               "model is not determined by these poses; record more orientations (>= 12, spread "
               "over the sphere)")
    msg += _not_converged(converged, ACCEL_MAX_STEPS)
    return AccelCalibration(dict(zip(ACCEL_NAMES, np.asarray(th).tolist())),
                            dict(zip(ACCEL_NAMES, se.tolist())), r / np.sqrt(w), rank, cond,
                            determined, msg, gravity, bool(converged))


def _not_converged(converged, max_steps) -> str:
    return ("" if converged else f"; the Levenberg-Marquardt fit did not converge in {max_steps} "
            "steps: these values are not a solution (check the poses' means and units)")


# -- gyro: gravity propagation ----------------------------------------------------------------
GYRO_NAMES = ("sgx", "sgy", "sgz", "mgxy", "mgxz", "mgyx", "mgyz", "mgzx", "mgzy")
GYRO_MAX_STEPS = 100  # Levenberg-Marquardt budget of the turns' fit


def _gyro_matrix(theta):
    s, m = theta[:3], theta[3:]
    return jnp.array([[1 + s[0], m[0], m[1]], [m[2], 1 + s[1], m[3]], [m[4], m[5], 1 + s[2]]])


def _propagate(u0, w_true, dt):
    """Body-frame up vector through a turn: ``u_{j+1} = exp(-[w_j dt]x) u_j`` (Rodrigues)."""

    def step(u, w):
        phi = w * dt
        a = jnp.sqrt(jnp.sum(phi ** 2) + 1e-300)
        k = phi / a
        u_new = (u * jnp.cos(a) - jnp.cross(k, u) * jnp.sin(a)
                 + k * jnp.dot(k, u) * (1 - jnp.cos(a)))
        return u_new, None

    u, _ = jax.lax.scan(step, u0, w_true)
    return u


def _gyro_resid(theta, args):
    u0, u1, wt, live, dt = args
    wtrue = jnp.einsum("ij,tlj->tli", jnp.linalg.inv(_gyro_matrix(theta)), wt) * live
    return (jax.vmap(_propagate, in_axes=(0, 0, None))(u0, wtrue, dt) - u1).reshape(-1)


@jax.jit
def _gyro_fit(u0, u1, wt, live, dt):
    args = (u0, u1, wt, live, dt)
    sol = optx.least_squares(_gyro_resid, optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12),
                             jnp.zeros(9), args, max_steps=GYRO_MAX_STEPS, throw=False)
    return _at_solution(_gyro_resid, sol, args)


@dataclasses.dataclass
class GyroCalibration:
    params: dict
    stderr: dict
    bias: np.ndarray
    residual_deg: np.ndarray  # angle between propagated and measured up vector per turn
    n_turns: int
    determined: bool
    message: str
    converged: bool = True  # the Levenberg-Marquardt fit ended at its solution


def calibrate_gyro(record: BenchRecord, segments, accel: AccelCalibration, *, bias=None,
                   max_turn_s: float = 30.0) -> GyroCalibration:
    """Gyro scale factors and misalignments from the turns between consecutive static poses.

    The gyro bias is the first static interval's mean (or ``bias``); the rate inside each turn
    is ``A_g^-1 (w_meas - b_g)``; the up vector of the pose before the turn (accelerometer,
    calibrated) is propagated through the turn and compared with the pose after it. Turns longer
    than ``max_turn_s`` (the stand was put aside) are skipped.
    """
    t = np.asarray(record.t, float)
    w = np.stack([np.asarray(record.channel(c)) for c in ("wx", "wy", "wz")], 1)
    f = np.stack([np.asarray(record.channel(c)) for c in ("ax", "ay", "az")], 1)
    dt = float(np.median(np.diff(t)))
    b = np.asarray(bias if bias is not None else w[segments[0].i0:segments[0].i1].mean(0))
    ups = []
    for s in segments:
        fc = accel.correct(f[s.i0:s.i1].mean(0, keepdims=True))[0]
        ups.append(fc / np.linalg.norm(fc))
    turns = [(k, segments[k].i1, segments[k + 1].i0) for k in range(len(segments) - 1)
             if (segments[k + 1].i0 - segments[k].i1) * dt <= max_turn_s]
    if not turns:
        raise ValueError("no turns between static poses shorter than max_turn_s; gyro "
                         "calibration by gravity propagation needs the motions between poses")
    # pad all turns to one length (zero rate after the end) so one scan serves every turn
    lmax = max(i1 - i0 for _, i0, i1 in turns)
    wt = np.zeros((len(turns), lmax, 3))
    for j, (_, i0, i1) in enumerate(turns):
        wt[j, : i1 - i0] = w[i0:i1] - b
    live = np.zeros((len(turns), lmax, 1))
    for j, (_, i0, i1) in enumerate(turns):
        live[j, : i1 - i0] = 1.0
    u0 = np.stack([ups[k] for k, _, _ in turns])
    u1 = np.stack([ups[k + 1] for k, _, _ in turns])
    th, jac, r, converged = (np.asarray(x) for x in _gyro_fit(u0, u1, wt, live, dt))
    r = r.reshape(-1, 3)
    pred = u1 + r
    ang = np.degrees(np.arccos(np.clip(np.sum(np.asarray(pred) * np.asarray(u1), 1)
                                       / np.linalg.norm(pred, axis=1), -1, 1)))
    sv = np.linalg.svd(jac, compute_uv=False)
    rank = int(np.sum(sv > 1e-9 * sv[0]))
    dof = 2 * len(turns) - 9  # each turn constrains two directions
    determined = rank == 9 and dof > 0
    if determined:
        s2 = float(np.sum(r ** 2) / dof)
        se = np.sqrt(np.diag(s2 * np.linalg.pinv(jac.T @ jac)))
        msg = f"{len(turns)} turns, rank 9, {dof} residual dof"
    else:
        se = np.full(9, np.nan)
        msg = (f"{len(turns)} turns give rank {rank} of 9: turn about all three axes (>= 5 turns)")
    msg += _not_converged(converged, GYRO_MAX_STEPS)
    return GyroCalibration(dict(zip(GYRO_NAMES, np.asarray(th).tolist())),
                           dict(zip(GYRO_NAMES, se.tolist())), b, ang, len(turns), determined,
                           msg, bool(converged))


# -- held-out checks --------------------------------------------------------------------------
def leave_one_position_out(means, gravity: float) -> np.ndarray:
    """Held-out |f| - g of each pose under the calibration fitted without it (m/s^2); NaN where
    the remaining poses do not determine the calibration."""
    means = np.asarray(means, float)
    out = np.full(len(means), np.nan)
    for k in range(len(means)):
        keep = np.arange(len(means)) != k
        cal = calibrate_accelerometer(means[keep], gravity)
        if cal.determined:
            out[k] = np.linalg.norm(cal.correct(means[k:k + 1])[0]) - gravity
    return out


def time_ordered_split(segments, holdout: float = 0.25):
    """(train, held-out) segment lists: the last ``holdout`` of the poses by time."""
    n_ho = int(round(holdout * len(segments)))
    return list(segments[: len(segments) - n_ho]), list(segments[len(segments) - n_ho:])
