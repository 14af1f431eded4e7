"""Platform INS in the "Schuler period" test — docs/rigs/schuler.md.

A gimballed platform INS on a fixed stand is switched into a navigation mode whose model velocities
start at 200 m/s although nothing moves; the platform, torqued to follow the pretended motion, tilts
and the model velocities and tilts oscillate with the Schuler period $2\\pi\\sqrt{a_R/g}$.

Frames (docs/rigs/schuler.md): geographic ENU ``x0``; platform ``x`` with
$C_{x^0}^{x} = P_2(\\alpha_2) P_1(\\alpha_1) P_3(-A_z)$ (frame rotations ``P_k(t) = rot_k(-t)``);
azimuths clockwise from North. State ``X = (alpha1, alpha2, A_z, V1', V2', A')`` (rad, m/s), time in
seconds. The vector field is the full nonlinear model (S7), with the commanded rates (S5), the gyro
drift ``nu = nu0 + (D11 w1', D22 w2', 0)`` and the accelerometer error
``df = df0 + (K11 f1, K22 f2)`` (S3).

Parameters (internal SI; display units in reports): gyro drifts ``nu1 nu2 nu3`` (rad/s; deg/h),
torquer scale errors ``D11 D22`` (1; ppm), accelerometer biases ``df1 df2`` (m/s^2), accelerometer
scale errors ``K11 K22`` (1; ppm), initial tilts ``alpha10 alpha20`` and initial azimuth error
``dA0 = A'(t0) - A_z(t0)`` (rad; arcmin). Their scales are the prior standard deviations of
docs/rigs/schuler.md.

Measured channels: the model velocities ``V1 V2`` (m/s) and the platform's rotation since ``t0``,
$\\Delta R(t) = C(t)\\,C(t_0)^T$, as a rotation vector ``rot1 rot2 rot3`` (rad) — what gimbal
angles give on a stand of unknown attitude (docs/rigs/schuler.md).
"""

from __future__ import annotations

from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .. import units
from ..earth import check_gravity, normal_gravity
from ..params import Param, ParameterSpace
from ..rotations import matrix_to_rotvec, rot1, rot2, rot3, rotvec_to_matrix
from ._base import AbstractRig

__all__ = ["SchulerRig", "SchulerConditions", "EARTH_RADIUS", "EARTH_RATE_SOURCE", "ERROR_STATES",
           "error_matrix", "initial_error_state", "propagate_error_model", "add_measurement_noise",
           "platform_matrix", "schuler_solution", "schuler_period", "PARAM_NAMES", "EFFECT_NAMES"]

EARTH_RADIUS = 6_371_116.0
"""Mean Earth radius a_R of the source (m)."""
EARTH_RATE_SOURCE = 7.2921151467e-5
"""Earth rate u of the source (rad/s)."""

_DEG_H, _PPM, _ARCMIN = units.DEG_PER_HOUR, units.PPM, units.ARCMIN
_SPEC = (  # name, unit, display unit, display factor, prior sd (scale), effect, description
    ("nu1", "rad/s", "deg/h", _DEG_H, 0.2 * _DEG_H, "gyro_drift", "gyro drift about platform axis 1"),
    ("nu2", "rad/s", "deg/h", _DEG_H, 0.2 * _DEG_H, "gyro_drift", "gyro drift about platform axis 2"),
    ("nu3", "rad/s", "deg/h", _DEG_H, 0.2 * _DEG_H, "gyro_drift", "gyro drift about platform axis 3"),
    ("D11", "1", "ppm", _PPM, 1e-2, "torquer_scale", "scale error of torquer 1"),
    ("D22", "1", "ppm", _PPM, 1e-2, "torquer_scale", "scale error of torquer 2"),
    ("df1", "m/s^2", "m/s^2", 1.0, 1e-2, "accelerometer_bias", "bias of accelerometer 1"),
    ("df2", "m/s^2", "m/s^2", 1.0, 1e-2, "accelerometer_bias", "bias of accelerometer 2"),
    ("K11", "1", "ppm", _PPM, 1e-2, "accelerometer_scale", "scale error of accelerometer 1"),
    ("K22", "1", "ppm", _PPM, 1e-2, "accelerometer_scale", "scale error of accelerometer 2"),
    ("alpha10", "rad", "arcmin", _ARCMIN, 1e-3, "initial_misalignment", "initial tilt 1"),
    ("alpha20", "rad", "arcmin", _ARCMIN, 1e-3, "initial_misalignment", "initial tilt 2"),
    ("dA0", "rad", "arcmin", _ARCMIN, 1e-2, "initial_misalignment",
     "initial azimuth error A'(t0) - A_z(t0)"),
)
PARAM_NAMES = tuple(p[0] for p in _SPEC)
"""The 12 errors the test identifies (the nominal model of the diagnosis)."""

STEP_WIDTH = 60.0
"""Rise time scale of the smooth drift step (s): ``0.5 (1 + tanh((t - t_step) / STEP_WIDTH))``."""
_DEG_H_H, _DEG_H_G, _MG_H = _DEG_H / 3600.0, _DEG_H / units.G0, 1e-3 * units.G0 / 3600.0
_EFFECTS = (  # unmodelled effects of the diagnosis catalogue: null value, then as _SPEC
    *((f"nudot{i}", 0.0, "rad/s^2", "deg/h/h", _DEG_H_H, 0.05 * _DEG_H_H, "drift_ramp",
       f"gyro drift rate of change about axis {i} (from t = 0)") for i in (1, 2, 3)),
    *((f"nutr{i}", 0.0, "rad/s", "deg/h", _DEG_H, 0.1 * _DEG_H, "drift_transient",
       f"warm-up drift about axis {i} at t = 0, decaying as exp(-t / tau_tr)") for i in (1, 2, 3)),
    ("tau_tr", 1800.0, "s", "min", 60.0, 1800.0, "drift_transient", "warm-up decay time"),
    *((f"nustep{i}", 0.0, "rad/s", "deg/h", _DEG_H, 0.05 * _DEG_H, "drift_step",
       f"gyro drift step about axis {i} at t_step") for i in (1, 2, 3)),
    ("t_step", 3600.0, "s", "min", 60.0, 3600.0, "drift_step", "onset of the drift step"),
    *((f"dfdot{i}", 0.0, "m/s^3", "mg/h", _MG_H, 0.5 * _MG_H, "accelerometer_ramp",
       f"accelerometer {i} bias rate of change (from t = 0)") for i in (1, 2)),
    *((f"G{i}{j}", 0.0, "rad/m", "deg/h/g", _DEG_H_G, 0.3 * _DEG_H_G, "g_sensitivity",
       f"drift of gyro {i} per specific force along axis {j} (mass unbalance)")
      for i in (1, 2) for j in (1, 2)),
    ("mu12", 0.0, "rad", "arcmin", _ARCMIN, 10 * _ARCMIN, "accelerometer_cross_axis",
     "accelerometer 1 input axis tilted towards axis 2"),
    ("mu21", 0.0, "rad", "arcmin", _ARCMIN, 10 * _ARCMIN, "accelerometer_cross_axis",
     "accelerometer 2 input axis tilted towards axis 1"),
    ("mu13", 0.0, "rad", "arcmin", _ARCMIN, 10 * _ARCMIN, "accelerometer_tilt",
     "accelerometer 1 input axis tilted towards the vertical (senses g: a bias to first order)"),
    ("mu23", 0.0, "rad", "arcmin", _ARCMIN, 10 * _ARCMIN, "accelerometer_tilt",
     "accelerometer 2 input axis tilted towards the vertical"),
)
_SPACE = ParameterSpace(tuple(
    Param(name=n, unit=u, display_unit=du, display_factor=f, scale=s, null=0.0, effect=e,
          description=d) for n, u, du, f, s, e, d in _SPEC) + tuple(
    Param(name=n, unit=u, display_unit=du, display_factor=f, scale=s, null=nv, effect=e,
          description=d) for n, nv, u, du, f, s, e, d in _EFFECTS))
EFFECT_NAMES = tuple(e[0] for e in _EFFECTS)
"""Parameters of the unmodelled effects (null by default; absent keys read as null)."""


class SchulerConditions(eqx.Module):
    """Stand and test settings: latitude (rad), gravity ``g`` (m/s^2), the model velocities at
    ``t0`` ``v10``, ``v20`` (m/s) and the model azimuth ``a0`` (rad, clockwise from North)."""

    latitude: jax.Array
    g: jax.Array
    v10: jax.Array
    v20: jax.Array
    a0: jax.Array

    @staticmethod
    def from_record(record) -> SchulerConditions:
        """The conditions a record's attributes give (``latitude_deg``, ``g``, ``v10``, ``v20``,
        ``azimuth0_deg``; the test's defaults where absent)."""
        c = record.conditions
        return SchulerConditions.create(float(c.get("latitude_deg", 55.57)),
                                        g=c.get("g"), v10=float(c.get("v10", 200.0)),
                                        v20=float(c.get("v20", -200.0)),
                                        azimuth0_deg=float(c.get("azimuth0_deg", 0.0)))

    @staticmethod
    def create(latitude_deg: float = 55.57, *, g: float | None = None, v10: float = 200.0,
               v20: float = -200.0, azimuth0_deg: float = 0.0) -> SchulerConditions:
        """The defaults: 55.57 deg, normal gravity (9.815557 m/s^2), V' = (200, -200) m/s."""
        if not -89.0 <= float(latitude_deg) <= 89.0:
            raise ValueError(f"latitude {latitude_deg} deg is outside [-89, 89]; give degrees North")
        lat = jnp.asarray(latitude_deg * units.DEG, dtype=float)
        g_val = normal_gravity(lat) if g is None else jnp.asarray(g, dtype=float)
        check_gravity(g_val, "the record's g")
        f = lambda x: jnp.asarray(x, dtype=float)  # noqa: E731
        return SchulerConditions(lat, f(g_val), f(v10), f(v20), f(azimuth0_deg * units.DEG))

    @property
    def schuler_frequency(self):
        """$\\omega_0 = \\sqrt{g / a_R}$ (rad/s)."""
        return jnp.sqrt(self.g / EARTH_RADIUS)

    @property
    def schuler_period(self):
        """$T = 2\\pi / \\omega_0$ (s); 5062.09 s at the defaults."""
        return 2 * jnp.pi / self.schuler_frequency


def platform_matrix(alpha1, alpha2, azimuth):
    """$C_{x^0}^{x} = P_2(\\alpha_2) P_1(\\alpha_1) P_3(-A_z)$ (S1): ENU components to platform."""
    return rot2(-alpha2) @ rot1(-alpha1) @ rot3(azimuth)


class SchulerRig(AbstractRig):
    """The platform INS of the Schuler test on a fixed stand (full nonlinear model (S7))."""

    # the velocity errors of a platform INS on a stand: metres per second, not thousands
    CHANNEL_BOUNDS: ClassVar[dict] = {
        "V": (1000.0, "velocities are in m/s (from km/h: x 0.277778; from knots: x 0.514444)")}
    CHANNEL_UNITS: ClassVar[dict] = {"V": "m s-1", "rot": "rad"}

    @property
    def param_space(self) -> ParameterSpace:
        return _SPACE

    @property
    def channels(self) -> tuple[str, ...]:
        return ("V1", "V2", "rot1", "rot2", "rot3")

    @property
    def time_scale(self) -> float:
        return 1.0

    def initial_state(self, params, conditions):
        """$X(t_0) = (\\alpha_{10}, \\alpha_{20}, A'(t_0) - \\Delta A_0, V_1'(t_0), V_2'(t_0),
        A'(t_0))$."""
        p = params
        return jnp.stack([p["alpha10"], p["alpha20"], conditions.a0 - p["dA0"], conditions.v10,
                          conditions.v20, conditions.a0])

    def commanded_rate(self, state, conditions):
        """$\\omega'_{1,2}$ of (S5) (rad/s); $\\omega'_3 = 0$."""
        _, _, _, v1, v2, am = state
        un = EARTH_RATE_SOURCE * jnp.cos(conditions.latitude)
        return -v2 / EARTH_RADIUS - un * jnp.sin(am), v1 / EARTH_RADIUS + un * jnp.cos(am)

    def vector_field(self, t, state, params, conditions):
        """The nonlinear model (S7)."""
        a1, a2, az, _, _, _ = state
        p = params
        un = EARTH_RATE_SOURCE * jnp.cos(conditions.latitude)
        uv = EARTH_RATE_SOURCE * jnp.sin(conditions.latitude)
        w1, w2 = self.commanded_rate(state, conditions)
        g = conditions.g
        c1, s1, c2, s2 = jnp.cos(a1), jnp.sin(a1), jnp.cos(a2), jnp.sin(a2)
        f1, f2, f3 = -g * c1 * s2, g * s1, g * c1 * c2
        d1, d2, d3 = self.extra_drift(t, p, f1, f2)
        r1 = w1 + p["nu1"] + p["D11"] * w1 + d1  # omega_1' + nu_1
        r2 = w2 + p["nu2"] + p["D22"] * w2 + d2
        nu3 = p["nu3"] + d3
        e1, e2 = self.extra_specific_force(t, p, f1, f2, f3)
        return jnp.stack([
            r1 * c2 + nu3 * s2 + un * jnp.sin(az),
            r2 + jnp.tan(a1) * (r1 * s2 - nu3 * c2) - un * jnp.cos(az) / c1,
            -nu3 * c2 / c1 + uv - un * jnp.cos(az) * jnp.tan(a1) + r1 * s2 / c1,
            f1 + p["df1"] + p["K11"] * f1 + e1,
            f2 + p["df2"] + p["K22"] * f2 + e2,
            uv,
        ])

    def step_times(self, params, conditions):
        """Steps through the drift step's rise (``t_step`` +- 3 ``STEP_WIDTH``, at half-widths
        near the centre): the adaptive steps would otherwise stride over the rise where its
        amplitude is 0, and the step's forward sensitivity would be off by up to 7e-4 of its norm
        (docs/decisions/0004-forward-sensitivities-across-jumps.md)."""
        return jnp.asarray(params.get("t_step", 3600.0), dtype=float) + STEP_WIDTH * jnp.array(
            [-3.0, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0, 3.0])

    @staticmethod
    def extra_drift(t, p, f1, f2):
        """Gyro drift of the unmodelled effects (rad/s, platform axes 1-3): ramp, warm-up
        transient, smooth step and g-sensitivity. Zero when their parameters are null or absent
        (the 12-parameter dicts of the nominal model)."""
        q = lambda k: p.get(k, 0.0)  # noqa: E731
        decay = jnp.exp(-t / p.get("tau_tr", 1800.0))
        step = 0.5 * (1 + jnp.tanh((t - p.get("t_step", 3600.0)) / STEP_WIDTH))
        out = [q(f"nudot{i}") * t + q(f"nutr{i}") * decay + q(f"nustep{i}") * step
               for i in (1, 2, 3)]
        out[0] = out[0] + q("G11") * f1 + q("G12") * f2
        out[1] = out[1] + q("G21") * f1 + q("G22") * f2
        return out

    @staticmethod
    def extra_specific_force(t, p, f1, f2, f3):
        """Accelerometer error of the unmodelled effects (m/s^2): bias ramp, cross-axis and
        vertical-axis tilts of the input axes."""
        q = lambda k: p.get(k, 0.0)  # noqa: E731
        return (q("dfdot1") * t + q("mu12") * f2 + q("mu13") * f3,
                q("dfdot2") * t + q("mu21") * f1 + q("mu23") * f3)

    def observe(self, t, state, params, conditions):
        """``(V1', V2', rotation vector of C(t) C(t0)^T)``."""
        x0 = self.initial_state(params, conditions)
        rel = platform_matrix(state[0], state[1], state[2]) @ platform_matrix(x0[0], x0[1],
                                                                                x0[2]).T
        return jnp.concatenate([state[3:5], matrix_to_rotvec(rel)])


def schuler_solution(conditions: SchulerConditions, tau: Float[ArrayLike, " n"]):
    """The zero-order solution (S9) at ``tau = t - t0`` (s): ``(alpha1, alpha2, A', V1', V2')``,
    each shaped like ``tau``; ``A_z = A'`` at this order."""
    tau = jnp.asarray(tau, dtype=float)
    w0 = conditions.schuler_frequency
    root = jnp.sqrt(conditions.g * EARTH_RADIUS)
    s, c = jnp.sin(w0 * tau), jnp.cos(w0 * tau)
    return (-conditions.v20 / root * s, conditions.v10 / root * s,
            conditions.a0 + EARTH_RATE_SOURCE * jnp.sin(conditions.latitude) * tau,
            conditions.v10 * c, conditions.v20 * c)


def schuler_period(ts: Float[ArrayLike, " n"], v: Float[ArrayLike, " n"], *,
                   conditions: SchulerConditions | None = None) -> dict:
    """The classical pass/fail check: the oscillation period of a model-velocity record.

    Fits ``v(t) = a cos(w t) + b sin(w t) + c`` by least squares (variable projection: the linear
    coefficients solved exactly for each trial ``w``, then Gauss-Newton in ``w`` from the theoretical
    Schuler frequency, or from the record's spectral peak without ``conditions``).

    **Returns:** ``{"period_s", "period_min", "amplitude", "rms_residual"}``, plus
    ``"theoretical_min"`` and ``"relative_difference"`` with ``conditions``.

    **Raises:** ``ValueError`` when the record is shorter than half a Schuler period (the period
    is then not determined), or its times are not increasing.
    """
    ts = np.asarray(ts, dtype=float)
    v = np.asarray(v, dtype=float)
    if ts.ndim != 1 or v.shape != ts.shape:
        raise ValueError(f"schuler_period: t {ts.shape} and v {v.shape} must be equal 1-D arrays")
    if ts.size < 8 or np.any(np.diff(ts) <= 0):
        raise ValueError("schuler_period: need >= 8 samples with strictly increasing times")
    span = ts[-1] - ts[0]
    t_theory = float(conditions.schuler_period) if conditions is not None else 5062.0
    if span < 0.5 * t_theory:
        raise ValueError(f"schuler_period: the record spans {span:.0f} s, less than half a Schuler "
                         f"period ({0.5 * t_theory:.0f} s); record at least one period")
    tau = ts - ts[0]
    if conditions is not None:
        w = float(conditions.schuler_frequency)
    else:  # spectral peak of the zero-padded record
        n = 1 << int(np.ceil(np.log2(16 * ts.size)))
        spec = np.abs(np.fft.rfft(v - v.mean(), n))
        freq = np.fft.rfftfreq(n, d=span / (ts.size - 1))
        w = 2 * np.pi * freq[1 + np.argmax(spec[1:])]

    def project(w):
        basis = np.stack([np.cos(w * tau), np.sin(w * tau), np.ones_like(tau)], axis=1)
        coef, *_ = np.linalg.lstsq(basis, v, rcond=None)
        return coef, v - basis @ coef

    for _ in range(50):  # Gauss-Newton on w with the linear coefficients projected out
        coef, r = project(w)
        dr = -(-coef[0] * tau * np.sin(w * tau) + coef[1] * tau * np.cos(w * tau))
        basis = np.stack([np.cos(w * tau), np.sin(w * tau), np.ones_like(tau)], axis=1)
        q, _ = np.linalg.qr(basis)
        dr = dr - q @ (q.T @ dr)  # variable-projection Jacobian
        step = -(dr @ r) / (dr @ dr)
        w += step
        if abs(step) < 1e-13 * w:
            break
    coef, r = project(w)
    out = {"period_s": 2 * np.pi / w, "period_min": 2 * np.pi / w / 60.0,
           "amplitude": float(np.hypot(coef[0], coef[1])),
           "rms_residual": float(np.sqrt(np.mean(r**2)))}
    if conditions is not None:
        out["theoretical_min"] = t_theory / 60.0
        out["relative_difference"] = out["period_s"] / t_theory - 1.0
    return out


ERROR_STATES = ("dalpha1", "dalpha2", "dV1", "dV2", "dA") + PARAM_NAMES
"""The 17 states of the first-order error model (S10), in the order of docs/rigs/schuler.md."""
INSTRUMENT_NAMES = PARAM_NAMES[:9]


def error_matrix(rig: SchulerRig, params_ref, conditions: SchulerConditions, state_ref):
    """$A(t)$ of (S10), 17 x 17, at one reference state: the autodiff Jacobian of (S7) with respect
    to the state and the nine instrument errors, mapped to the error state with
    $\\delta A_z = -\\delta A$ (``A'`` carries no error). This is the exact form
    (``q = 0``); ``params_ref`` are the reference's errors (zero, or the current estimate when
    iterating)."""
    order = (0, 1, 3, 4)  # rows/cols of (alpha1, alpha2, V1', V2') in X

    def f(x, p):
        return rig.vector_field(0.0, x, p, conditions)

    jx = jax.jacfwd(f, argnums=0)(state_ref, params_ref)
    jp = jax.jacfwd(f, argnums=1)(state_ref, params_ref)
    jp = jnp.stack([jp[n] for n in INSTRUMENT_NAMES], axis=1)  # (6, 9)
    # error state -> dX: (dalpha1, dalpha2, dA_z = -dA, dV1, dV2, dA' = 0)
    m = jnp.zeros((6, 5)).at[0, 0].set(1.0).at[1, 1].set(1.0).at[2, 4].set(-1.0)
    m = m.at[3, 2].set(1.0).at[4, 3].set(1.0)
    rows = jnp.stack([*(jx[i] for i in order), -jx[2]])  # d/dt of (a1, a2, V1, V2, dA = -dA_z)
    rows_p = jnp.stack([*(jp[i] for i in order), -jp[2]])
    top = jnp.concatenate([rows @ m, rows_p, jnp.zeros((5, 3))], axis=1)
    return jnp.concatenate([top, jnp.zeros((12, 17))], axis=0)


def initial_error_state(params):
    """$\\mathbf x(t_0) = T\\boldsymbol\\theta$: the errors, with states 1, 2, 5 equal to the
    initial tilts and azimuth error."""
    theta = jnp.stack([params[n] for n in PARAM_NAMES])
    return jnp.concatenate([jnp.stack([params["alpha10"], params["alpha20"], 0.0 * theta[0],
                                       0.0 * theta[0], params["dA0"]]), theta])


def propagate_error_model(rig: SchulerRig, conditions: SchulerConditions, params, ts, *,
                          params_ref=None, rtol: float = 1e-10, atol: float = 1e-12):
    """Integrate the reference (S7) with ``params_ref`` (default error-free) together with the
    linear error model $\\dot{\\mathbf x} = A(t)\\mathbf x$ from ``x(t0)`` for the errors
    ``params`` (relative to the reference). Returns ``(X_ref, x)``, shapes ``(N, 6)``, ``(N, 17)``.
    """
    ref = rig.param_space.make({}) if params_ref is None else params_ref
    ts = jnp.asarray(ts, dtype=float)
    x0 = initial_error_state(params) - initial_error_state(ref)

    def field(t, y, args):
        xr, e = y[:6], y[6:]
        return jnp.concatenate([rig.vector_field(t, xr, ref, conditions),
                                error_matrix(rig, ref, conditions, xr) @ e])

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field), diffrax.Dopri8(), ts[0], ts[-1], None,
        jnp.concatenate([rig.initial_state(ref, conditions), x0]), saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol), max_steps=200_000)
    return sol.ys[:, :6], sol.ys[:, 6:]


def add_measurement_noise(key: PRNGKeyArray, y: Float[ArrayLike, "n 5"], *, sigma_v: float = 0.05,
                          sigma_theta: float = units.ARCMIN) -> Float[Array, "n 5"]:
    """Noisy record channels: white noise of ``sigma_v`` (m/s) on the velocities, and a random
    small rotation of ``sigma_theta`` (rad) per axis composed with the measured relative rotation
    (so that the attitude residual (S12) sees exactly that noise)."""
    kv, ka = jax.random.split(key)
    y = jnp.asarray(y, dtype=float)
    v = y[..., :2] + sigma_v * jax.random.normal(kv, y[..., :2].shape)
    n = sigma_theta * jax.random.normal(ka, y[..., 2:].shape)
    flat_rot, flat_n = y[..., 2:].reshape(-1, 3), n.reshape(-1, 3)
    rot = jax.vmap(lambda r, e: matrix_to_rotvec(rotvec_to_matrix(e) @ rotvec_to_matrix(r)))(
        flat_rot, flat_n)
    return jnp.concatenate([v, rot.reshape(y[..., 2:].shape)], axis=-1)
