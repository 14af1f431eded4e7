"""Multi-position tools for a strapdown IMU on a stand (no turntable, no reference attitude).

- :func:`detect_static`: static intervals from the gyro and accelerometer (moving statistics
  against a robust noise level), breaking at time gaps and masked samples.
- :func:`calibrate_accelerometer`: the |f| = g calibration (Tedaldi et al. 2014): biases, scale
  factors and the three non-orthogonality terms of an upper-triangular gauge, by
  Levenberg-Marquardt (optimistix) on the static means.
- :func:`calibrate_gyro`: gyro scale factors and misalignments by propagating the gravity direction
  through the turns between static poses (``du/dt = -w x u`` in the body frame, exact rotation per
  sample under ``lax.scan``) and matching the next pose's accelerometer direction; intervals with
  a time gap or masked samples are not turns.
- :func:`term_determination`: which terms a few poses determine (an x-up/x-down pair: ``bax`` and
  ``sax``; the six axis-up poses: the biases and scale factors), from the Jacobian's null space in
  prior-scaled units; a fit holds the others at zero, reports no number for them, and says how far
  they could move the determined ones. The gyro's determination carries the accelerometer terms
  the poses leave open (they tilt the up vectors the turns are matched to).
- :func:`leave_one_position_out`, :func:`time_ordered_split`: held-out checks.

Model conventions follow :mod:`gyrojax.models.imu`: ``f_meas = b_a + (I + diag(s_a) + M_a) f``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from ..datasets import masked
from ..models.imu import IMURig, _turn, pose_frame
from ..record import BenchRecord
from ..rotations import rotvec_to_matrix
from ._linalg import value_and_jacfwd
from ._lstsq import ScaledLevenbergMarquardt, solve_least_squares

__all__ = ["Segment", "detect_static", "recorded_turns", "turn_chains", "design_chain",
           "calibrate_accelerometer", "calibrate_gyro",
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


# -- which terms a calibration's observations determine --------------------------------------
RANK_TOL = 1e-3  # relative singular value (prior-scaled Jacobian) below which a direction is null
LEAK_TOL = 0.1  # a term is determined when at most this much of it lies in the null space


@dataclasses.dataclass(frozen=True)
class Determination:
    """Which of a calibration's ``names`` its observations determine.

    The Jacobian is taken in units of each term's prior scale (the IMU rig's ``Param.scale``: 10
    mg, 1000 ppm, 1 mrad), so that a bias and a scale factor compare as the errors a catalogue
    instrument has. Directions with relative singular value below :data:`RANK_TOL` are null. The
    ``leak`` of term k is ``|P_null e_k|``: moving the undetermined terms along the null space by
    one prior scale in all (unit norm in scaled units) moves term k's estimate by at most
    ``leak_k`` of its own scale. Term k is determined when ``leak_k <`` :data:`LEAK_TOL`; an
    x-up/x-down pair determines ``bax`` and ``sax`` so, with a leak of a few percent from the
    cross-axis biases' share of ``|f|`` (the classic up/down formula sets them to zero).
    """

    names: tuple
    rank: int
    condition: float  # largest over smallest singular value of the scaled Jacobian (inf: rank < p)
    terms: tuple  # the determined names
    n_obs: int
    leak: tuple  # |P_null e_k| per name (0 when all are determined)
    null: np.ndarray = dataclasses.field(default=None, compare=False, repr=False)  # scaled rows
    upstream_open: tuple = ()  # (names only the upstream fit's open terms leave undetermined,
    #                             those open terms): the gyro's, through the accelerometer's

    def shift(self, name) -> float:
        """The most the undetermined terms, at one prior scale in all, move ``name``'s estimate
        (SI units; 0 when every term is determined)."""
        return float(self.leak[self.names.index(name)] * _scales([name])[0])

    @property
    def complete(self) -> bool:
        return len(self.terms) == len(self.names)

    @property
    def dof(self) -> int:
        return self.n_obs - self.rank

    def message(self, what: str, advice: str) -> str:
        if self.complete:
            return (f"{what}, rank {self.rank}, {self.dof} residual dof"
                    + ("" if self.dof > 0 else ": no residual to give standard errors"))
        rest = [n for n in self.names if n not in self.terms]
        via = ""
        if self.upstream_open and self.upstream_open[0]:
            mine, theirs = self.upstream_open
            via = (f" ({', '.join(mine)} through the accelerometer terms the poses leave "
                   f"open: {', '.join(theirs)})")
        return (f"{what}, rank {self.rank} of {len(self.names)}; determined: "
                + (", ".join(self.terms) if self.terms else "none")
                + f"; not determined: {', '.join(rest)}{via}; {advice}")


def term_determination(jac, names, *, n_obs=None, upstream=None) -> Determination:
    """:class:`Determination` of the terms ``names`` (IMU rig names) from the Jacobian ``jac``
    (rows: observations, SI columns); ``n_obs`` independent observations (default: its rows).

    ``upstream = (jac_up, det_up)``: the observations also depend on the terms of an earlier
    calibration, held at its estimate (the gyro's turns on the accelerometer's up vectors):
    ``jac_up`` their Jacobian with respect to its terms, ``det_up`` its :class:`Determination`.
    Its undetermined terms move this fit's estimates by ``J^+ J_up N_up``; a term's leak is the
    root sum square of its own null-space share and that (an x-bias no pose determines tilts the
    up vectors, and a gyro scale factor through a half turn reads it as a rotation)."""
    scale = _scales(names)
    js = np.asarray(jac, float) * scale[None, :]
    p = js.shape[1]
    u, s, vt = np.linalg.svd(js, full_matrices=True)
    rank = int(np.sum(s > RANK_TOL * s[0])) if s.size and s[0] > 0 else 0
    leak = own = np.linalg.norm(vt[rank:], axis=0)
    via = ()
    if upstream is not None and upstream[1].null.shape[0]:
        jac_up, det_up = upstream
        moved = (np.asarray(jac_up, float) * _scales(det_up.names)[None, :]) @ det_up.null.T
        sens = (vt[:rank].T / s[:rank]) @ (u[:, :rank].T @ moved)  # J^+ J_up N_up, scaled
        leak = np.sqrt(own**2 + np.sum(sens**2, axis=1))
        via = (tuple(n for n, a, b in zip(names, own, leak) if a < LEAK_TOL <= b),
               tuple(n for n in det_up.names if n not in det_up.terms))
    cond = float(s[0] / s[p - 1]) if rank == p else float("inf")
    return Determination(tuple(names), rank, cond,
                         tuple(n for n, lk in zip(names, leak) if lk < LEAK_TOL),
                         js.shape[0] if n_obs is None else n_obs,
                         tuple(float(x) for x in leak), vt[rank:], via)


def _stderr(jac, r, det: Determination):
    """Standard errors of the determined terms (NaN for the others, and for all without residual
    degrees of freedom): ``s^2 (J^T J)^+`` on the determined rank, the variance of an estimable
    term under any solution; computed in the prior-scaled coordinates."""
    se = np.full(len(det.names), np.nan)
    if det.dof <= 0 or not det.terms:
        return se
    s2 = float(np.sum(np.asarray(r) ** 2) / det.dof)
    scale = _scales(det.names)
    _, s, vt = np.linalg.svd(np.asarray(jac, float) * scale[None, :], full_matrices=False)
    v = vt[: det.rank] / s[: det.rank, None]
    d = scale * np.sqrt(s2 * np.sum(v**2, axis=0))
    keep = np.isin(det.names, det.terms)
    se[keep] = d[keep]
    return se


def _scales(names) -> np.ndarray:
    space = IMURig().param_space
    return np.array([space[n].scale for n in names], float)


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
def _accel_fit(th0, means, w, gravity, free):
    """LM fit, Jacobian and residual at the solution: compiled once per number of poses (the
    leave-one-position-out loop and repeated units reuse it)."""
    return _lm_fit(_accel_resid, th0, (means, w, gravity), free, 1e-12, ACCEL_MAX_STEPS)


def _lm_fit(resid, th0, args, free, rtol, max_steps):
    """Levenberg-Marquardt (optimistix, :func:`~gyrojax.estimate.solve_least_squares`) over the
    terms ``free`` marks (1.0), the others held at zero: ``(value, Jacobian in every term,
    residual, converged)`` at the solution. Converged by the rule of every fit in gyrojax (the
    solver's test passed, or the free terms' step left is under ``STATIONARY_SE`` standard
    errors)."""
    def held(x, a):
        return resid(x * free, a)

    sol = solve_least_squares(held, th0 * free, args, max_steps=max_steps, step_se_tol=0.0,
                              solver=ScaledLevenbergMarquardt(rtol=rtol, atol=1e-12))
    value = sol.value * free
    r, jac = value_and_jacfwd(lambda x: resid(x, args))(value)  # one pass: every term's columns
    return value, jac, r, sol.converged


def _free_terms(jac0, names) -> np.ndarray:
    """1.0 for the terms the observations determine by themselves (the Jacobian ``jac0`` at the
    start, :func:`term_determination`), 0.0 for those in its null space: a fit holds these at
    zero instead of wandering along the null space (a gyro misalignment of radians)."""
    return np.array([lk < LEAK_TOL for lk in term_determination(jac0, names).leak], float)


_accel_jac = jax.jit(jax.jacfwd(_accel_resid))

# Unit checks of the inputs (SI by contract). A real stand's static |f| is within a few per
# cent of g (the five real sets' 18 records: 0.91-1.02 g, the MPU-6050 and the Xsens through
# nominal count scales), and a hand-moved turn's integrated rotation is 1-2x the angle between
# its poses (the eight multi-position records' medians: 1.24-1.77; single turns 0.67-12.5).
# A record in g, mg or counts, or with the gyros in deg/s (57x) or counts, falls far outside
# these ranges, where the fits fail or converge to values that are no calibration (a gyro in
# deg/s: turn residuals of ~17 deg, "converged").
ACCEL_MAGNITUDE_RANGE = (0.5, 2.0)  # median static |f| / g
TURN_ROTATION_RANGE = (0.25, 10.0)  # median integrated rotation / angle between poses
_TURN_MIN_DEG = 20.0  # turns counted in that median


def accel_units_problem(means, gravity: float) -> str | None:
    """Why static accelerometer means ``(n, 3)`` cannot be in m/s^2 (their median magnitude is
    outside ``ACCEL_MAGNITUDE_RANGE`` times ``gravity``), with the fix; ``None`` when they can."""
    mag = float(np.median(np.linalg.norm(np.asarray(means, float), axis=1)))
    if ACCEL_MAGNITUDE_RANGE[0] <= mag / gravity <= ACCEL_MAGNITUDE_RANGE[1]:
        return None
    fix = ("ax ay az look like g: multiply them by 9.80665" if 0.5 <= mag <= 2.0 else
           "ax ay az look like mg: multiply them by 0.00980665" if 500 <= mag <= 2000 else
           "convert ax ay az to m/s^2 (raw counts need the sensor's scale factor and zero offset)")
    return (f"the static accelerometer means have magnitude {mag:#.4g} (median over {len(means)} "
            f"poses), {mag / gravity:.3g} times gravity ({gravity:.6g} m/s^2), where a stand "
            f"reads 1 within a few per cent; gyrojax records are SI: {fix}")


def turn_rotation_ratio(w, b, dt, turns, ups) -> tuple[float, int]:
    """The median over ``turns`` ``(k, i0, i1)`` of more than ``_TURN_MIN_DEG`` between the up
    vectors ``ups[k]`` and ``ups[k + 1]`` of the gyros' integrated rotation ``sum |w - b| dt``
    over the angle between them, and how many turns it counts (NaN, 0 when none)."""
    out = []
    for k, i0, i1 in turns:
        ang = float(np.arccos(np.clip(np.dot(ups[k], ups[k + 1]), -1.0, 1.0)))
        if ang > np.radians(_TURN_MIN_DEG):
            out.append(float(np.sum(np.linalg.norm(w[i0:i1] - b, axis=1))) * dt / ang)
    return (float(np.median(out)), len(out)) if out else (float("nan"), 0)


def gyro_units_problem(ratio: float, n_turns: int) -> str | None:
    """Why gyro rates whose turns integrate to ``ratio`` times the poses' angles
    (:func:`turn_rotation_ratio`) cannot be in rad/s, with the fix; ``None`` when they can."""
    if not n_turns or TURN_ROTATION_RANGE[0] <= ratio <= TURN_ROTATION_RANGE[1]:
        return None
    fix = ("wx wy wz barely move during the turns: check that they are the gyro rates in rad/s, "
           "not stuck, saturated or filtered, and that t is in s" if ratio < TURN_ROTATION_RANGE[0]
           else "wx wy wz look like deg/s: multiply them by pi/180 = 0.0174533"
           if 20 <= ratio <= 200 else
           "t looks like ms (or wx wy wz like mrad/s): give t in s and wx wy wz in rad/s"
           if 500 <= ratio <= 2000 else
           "convert wx wy wz to rad/s and t to s (raw counts need the sensor's scale factor and "
           "zero offset)")
    return (f"the gyros integrate to {ratio:.3g} times the angle between the poses over the "
            f"turns (median over {n_turns} turns of more than {_TURN_MIN_DEG:g} deg, the angles "
            "from the accelerometers), where a hand-moved turn gives 1-2; gyrojax records are "
            f"SI: {fix}")


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
    determination: Determination | None = None  # which terms the poses determine

    def correct(self, f_meas):
        th = jnp.asarray([self.params[n] for n in ACCEL_NAMES])
        return np.asarray(_true_force(th, jnp.asarray(f_meas, float)))


def calibrate_accelerometer(means: Float[ArrayLike, "k 3"], gravity: float, *,
                            weights: Float[ArrayLike, " k"] | None = None) -> AccelCalibration:
    """Fit ``b_a``, ``s_a`` and the upper-triangular misalignments ``ma_xy ma_xz ma_yz`` so that
    every static mean has ``|f| = g`` (Levenberg-Marquardt, optimistix). The rotational gauge (3
    terms) is unobservable without a reference attitude and fixed to zero. Poses that do not
    determine all nine terms (fewer than 9, or all about one axis) still determine some: an
    x-up/x-down pair gives ``bax`` and ``sax``, the six axis-up poses the biases and scale
    factors. The result names the determined terms (``determination``, :func:`term_determination`)
    and gives standard errors for those only; ``determined`` is True when all nine are."""
    means = np.asarray(means, float)
    n = len(means)
    problem = accel_units_problem(means, gravity)
    if problem:
        raise ValueError(problem)
    w = np.ones(n) if weights is None else np.asarray(weights, float)
    th0 = np.zeros(9)
    th0[:3] = means.mean(0) * (n >= 6)
    free = _free_terms(_accel_jac(th0, (means, w, float(gravity))), ACCEL_NAMES)
    th, jac, r, converged = (np.asarray(x) for x in _accel_fit(th0, means, w, float(gravity),
                                                                free))
    det = term_determination(jac, ACCEL_NAMES)
    se = _stderr(jac, r, det)
    msg = det.message(f"{n} poses", "record more orientations (>= 12, spread over the sphere)")
    msg += _not_converged(converged, ACCEL_MAX_STEPS)
    return AccelCalibration(dict(zip(ACCEL_NAMES, np.asarray(th).tolist())),
                            dict(zip(ACCEL_NAMES, se.tolist())), r / np.sqrt(w), det.rank,
                            det.condition, det.complete, msg, gravity, bool(converged), det)


def _not_converged(converged, max_steps) -> str:
    return ("" if converged else f"; the Levenberg-Marquardt fit did not converge in {max_steps} "
            "steps: these values are not a solution (check the poses' means and units)")


# -- gyro: gravity propagation ----------------------------------------------------------------
GYRO_NAMES = ("sgx", "sgy", "sgz", "mgxy", "mgxz", "mgyx", "mgyz", "mgzx", "mgzy")
GYRO_MAX_STEPS = 100  # Levenberg-Marquardt budget of the turns' fit


def _gyro_matrix(theta):
    s, m = theta[:3], theta[3:]
    return jnp.array([[1 + s[0], m[0], m[1]], [m[2], 1 + s[1], m[3]], [m[4], m[5], 1 + s[2]]])


def up_step(u, phi):
    """One step of a body-frame vector fixed in space through the body rotation ``phi``
    ``(3,)`` (rad): ``exp(-[phi]x) u`` (Rodrigues)."""
    a = jnp.sqrt(jnp.sum(phi ** 2) + 1e-300)
    k = phi / a
    return u * jnp.cos(a) - jnp.cross(k, u) * jnp.sin(a) + k * jnp.dot(k, u) * (1 - jnp.cos(a))


def propagate_up(u0, w_true, dt):
    """Body-frame up vector through a turn: ``u_{j+1} = exp(-[w_j dt]x) u_j`` (:func:`up_step`)."""
    u, _ = jax.lax.scan(lambda u, w: (up_step(u, w * dt), None), u0, w_true)
    return u


def _up_vectors(theta_a, fmeans):
    """Unit up vectors (body frame) of static means under the accelerometer terms ``theta_a``."""
    fc = _true_force(theta_a, fmeans)
    return fc / jnp.linalg.norm(fc, axis=1, keepdims=True)


def _gyro_resid(theta, args):
    u0, u1, wt, live, dt = args
    wtrue = jnp.einsum("ij,tlj->tli", jnp.linalg.inv(_gyro_matrix(theta)), wt) * live
    return (jax.vmap(propagate_up, in_axes=(0, 0, None))(u0, wtrue, dt) - u1).reshape(-1)


@jax.jit
def _gyro_fit(u0, u1, wt, live, dt, free):
    return _lm_fit(_gyro_resid, jnp.zeros(9), (u0, u1, wt, live, dt), free, 1e-10,
                   GYRO_MAX_STEPS)


_gyro_jac = jax.jit(jax.jacfwd(_gyro_resid))


@jax.jit
@jax.jacfwd
def _gyro_upstream_jac(theta_a, theta, fmeans, before, after, wt, live, dt):
    """The turns' residuals' Jacobian with respect to the accelerometer terms (through the up
    vectors of the poses before and after each turn)."""
    u = _up_vectors(theta_a, fmeans)
    return _gyro_resid(theta, (u[before], u[after], wt, live, dt))


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
    determination: Determination | None = None  # which terms the turns determine


def calibrate_gyro(record: BenchRecord, segments, accel: AccelCalibration, *, bias=None,
                   max_turn_s: float = 30.0) -> GyroCalibration:
    """Gyro scale factors and misalignments from the turns between consecutive static poses.

    The gyro bias is the first static interval's mean (or ``bias``); the rate inside each turn
    is ``A_g^-1 (w_meas - b_g)``; the up vector of the pose before the turn (accelerometer,
    calibrated) is propagated through the turn and compared with the pose after it. Turns longer
    than ``max_turn_s`` (the stand was put aside), and intervals with a time gap or masked samples
    (the rotation is not in the record), are skipped, and the message says so. The determined
    terms and their standard errors as in :func:`calibrate_accelerometer`.
    """
    t = np.asarray(record.t, float)
    w = np.stack([np.asarray(record.channel(c)) for c in ("wx", "wy", "wz")], 1)
    f = np.stack([np.asarray(record.channel(c)) for c in ("ax", "ay", "az")], 1)
    dt = float(np.median(np.diff(t)))
    b = np.asarray(bias if bias is not None else w[segments[0].i0:segments[0].i1].mean(0))
    fmeans = jnp.asarray(np.stack([f[s.i0:s.i1].mean(0) for s in segments]))
    th_a = jnp.asarray([accel.params[n] for n in ACCEL_NAMES])
    ups = np.asarray(_up_vectors(th_a, fmeans))
    gap = np.zeros(len(t), bool)
    gap[1:] = np.diff(t) > 1.5 * dt
    unrecorded = gap | masked(record)  # a step across a time gap, or a masked sample
    near = [(k, segments[k].i1, segments[k + 1].i0) for k in range(len(segments) - 1)
            if (segments[k + 1].i0 - segments[k].i1) * dt <= max_turn_s]
    turns = [(k, i0, i1) for k, i0, i1 in near if not unrecorded[i0:i1 + 1].any()]
    skipped = len(near) - len(turns)
    why = (f"{skipped} interval(s) between poses skipped: a time gap or masked samples there, so "
           "the record does not hold the rotation" if skipped else "")
    if not turns:
        gaps = [(segments[k + 1].i0 - segments[k].i1) * dt for k in range(len(segments) - 1)]
        long = (f" (the {len(gaps)} intervals between poses last {np.median(gaps):.3g} s at the "
                f"median, over max_turn_s = {max_turn_s:g} s: a turn by hand takes seconds; is t "
                "in s?)" if gaps and not near else "")
        raise ValueError("no turns between static poses shorter than max_turn_s with every "
                         "sample recorded; gyro calibration by gravity propagation needs the "
                         "motions between poses" + (f" ({why})" if why else "") + long)
    problem = gyro_units_problem(*turn_rotation_ratio(w, b, dt, turns, ups))
    if problem:
        raise ValueError(problem)
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
    free = _free_terms(_gyro_jac(jnp.zeros(9), (u0, u1, wt, live, dt)), GYRO_NAMES)
    th, jac, r, converged = (np.asarray(x) for x in _gyro_fit(u0, u1, wt, live, dt, free))
    r = r.reshape(-1, 3)
    pred = u1 + r
    ang = np.degrees(np.arccos(np.clip(np.sum(np.asarray(pred) * np.asarray(u1), 1)
                                       / np.linalg.norm(pred, axis=1), -1, 1)))
    upstream = None
    if accel.determination is not None and not accel.determination.complete:
        before = np.array([k for k, _, _ in turns])
        jac_up = _gyro_upstream_jac(th_a, th, fmeans, before, before + 1, wt, live, dt)
        upstream = (np.asarray(jac_up), accel.determination)
    det = term_determination(jac, GYRO_NAMES, n_obs=2 * len(turns),  # two directions per turn
                             upstream=upstream)
    se = _stderr(jac, r, det)
    msg = det.message(f"{len(turns)} turn{'s' if len(turns) != 1 else ''}",
                      "turn about all three axes (>= 5 turns)")
    msg += (f"; {why}" if why else "") + _not_converged(converged, GYRO_MAX_STEPS)
    return GyroCalibration(dict(zip(GYRO_NAMES, np.asarray(th).tolist())),
                           dict(zip(GYRO_NAMES, se.tolist())), b, ang, len(turns), det.complete,
                           msg, bool(converged), det)


# -- chains of poses joined by recorded turns -------------------------------------------------
CHAIN_TOL_DEG = 3.0  # deg, the most a turn's propagated up vector may miss the next pose's


@jax.jit
def _turn_matrices(wt, dt):
    """``(turns, 3, 3)``: each turn's ``T`` with ``v_after = T v_before`` for a vector fixed in
    space, from the turn's body rates ``wt`` ``(turns, samples, 3)`` (bias removed; zero rate
    pads a shorter turn)."""
    basis = jnp.eye(3)
    prop = jax.vmap(jax.vmap(propagate_up, in_axes=(0, None, None)), in_axes=(None, 0, None))
    return jnp.swapaxes(prop(basis, wt, dt), 1, 2)


def recorded_turns(record: BenchRecord, segments, members=None, *,
                   max_turn_s: float = 30.0) -> list[tuple[int, int, int, int]]:
    """The turns the record holds between consecutive member poses: ``(k0, k1, i0, i1)``, the
    poses before and after and the samples ``i0:i1`` between them. A turn is held where the
    record has the three gyro channels, the interval lasts at most ``max_turn_s`` and none of
    its samples is masked or across a time gap. `members` ``(poses,)`` bool: the poses that may
    take part (default all)."""
    n = len(segments)
    members = np.ones(n, bool) if members is None else np.asarray(members, bool)
    idx = np.flatnonzero(members)
    if not all(c in record.channels for c in ("wx", "wy", "wz")) or idx.size < 2:
        return []
    t = np.asarray(record.t, float)
    dt = float(np.median(np.diff(t)))
    gap = np.zeros(len(t), bool)
    gap[1:] = np.diff(t) > 1.5 * dt
    unrecorded = gap | masked(record)
    out = []
    for k0, k1 in zip(idx[:-1], idx[1:]):
        i0, i1 = segments[k0].i1, segments[k1].i0
        if (t[i1] - t[i0 - 1]) <= max_turn_s and not unrecorded[i0:i1 + 1].any():
            out.append((int(k0), int(k1), int(i0), int(i1)))
    return out


def turn_chains(record: BenchRecord, segments, ups, members=None, *,
                max_turn_s: float = 30.0, tol_deg: float = CHAIN_TOL_DEG):
    """Chains of static poses joined by recorded turns, and each pose's horizontal frame
    carried along its chain.

    A vector fixed in space (north) is propagated through the gyro rates of each turn between
    consecutive member poses (bias: the mean of the two poses' gyro means, which holds the
    bias to the Earth rate's size). A chain breaks where the turn is not in the record (a time
    gap, masked samples, longer than ``max_turn_s``) or where the up vector propagated through
    it misses the next pose's (``ups``, from the accelerometers) by more than ``tol_deg``: a
    gyro scale error of 23 % reads a hand turn of 90 deg 20 deg wrong, and the heading with it.

    **Arguments:** `segments` (:class:`Segment`), `ups` ``(poses, 3)`` unit up vectors,
    `members` ``(poses,)`` bool: the poses that may join a chain (default all; a rate-table run
    is not one: it carries its own horizontal-rate terms).

    **Returns:** ``(head, a, b, miss_deg)``: ``head`` ``(poses,)`` int, the first pose of each
    pose's chain (-1 for non-members); ``a``, ``b`` ``(poses, 3)``: the head pose's
    :func:`~gyrojax.models.imu.pose_frame` ``e1``, ``e2`` carried to each pose (body frame, made
    horizontal there; zero for non-members); ``miss_deg``: the propagated up vector's miss at
    each turn followed, ``(k, angle)`` pairs.
    """
    ups = np.asarray(ups, float)
    n = len(segments)
    members = np.ones(n, bool) if members is None else np.asarray(members, bool)
    head = np.full(n, -1)
    a = np.zeros((n, 3))
    b = np.zeros((n, 3))
    idx = np.flatnonzero(members)
    if idx.size == 0:
        return head, a, b, []
    t = np.asarray(record.t, float)
    dt = float(np.median(np.diff(t)))
    pairs = recorded_turns(record, segments, members, max_turn_s=max_turn_s)
    if pairs:
        w = np.stack([np.asarray(record.channel(c), float) for c in ("wx", "wy", "wz")], 1)
    turn = {}
    if pairs:
        # padded to a few shapes (zero rate is no turn): one compilation serves many records
        lmax = 64 * -(-max(i1 - i0 for *_, i0, i1 in pairs) // 64)
        wt = np.zeros((8 * -(-len(pairs) // 8), lmax, 3))
        for j, (k0, k1, i0, i1) in enumerate(pairs):
            bias = 0.5 * (w[segments[k0].i0:segments[k0].i1].mean(0)
                          + w[segments[k1].i0:segments[k1].i1].mean(0))
            wt[j, : i1 - i0] = w[i0:i1] - bias
        mats = np.asarray(_turn_matrices(jnp.asarray(wt), dt))[: len(pairs)]
        turn = {(k0, k1): m for (k0, k1, *_), m in zip(pairs, mats)}
    miss = []
    prev = None
    for k in idx:
        m = turn.get((prev, k)) if prev is not None else None
        if m is not None:
            ang = float(np.degrees(np.arccos(np.clip(np.dot(m @ ups[prev], ups[k]), -1, 1))))
            miss.append((int(k), ang))
        if m is not None and ang <= tol_deg:
            head[k] = head[prev]
            v = m @ a[prev]
        else:
            head[k] = k
            v = pose_frame(ups[k][None])[0][0]
        v = v - np.dot(v, ups[k]) * ups[k]
        a[k] = v / np.linalg.norm(v)
        b[k] = np.cross(ups[k], a[k])
        prev = k
    return head, a, b, miss


def design_chain(ups):
    """:func:`turn_chains` of a planned design: every pose joined to the next by the shortest
    turn (exact, no noise), one chain. Returns ``(head, a, b)``."""
    ups = np.asarray(ups, float)
    ups = ups / np.linalg.norm(ups, axis=1, keepdims=True)
    a = np.zeros_like(ups)
    a[0] = pose_frame(ups[:1])[0][0]
    for k in range(1, len(ups)):
        v = np.asarray(rotvec_to_matrix(jnp.asarray(-_turn(ups[k - 1], ups[k])))) @ a[k - 1]
        v = v - np.dot(v, ups[k]) * ups[k]
        a[k] = v / np.linalg.norm(v)
    return np.zeros(len(ups), int), a, np.cross(ups, a)


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
