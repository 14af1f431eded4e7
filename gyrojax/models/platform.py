"""Three-gimbal inertial platform under linear vibration — docs/rigs/platform.md.

Frames (docs/rigs/platform.md): geographic ENU ``r``; base ``b`` on the vibration table (default mounting:
``x_b`` North, ``y_b`` Up = vibration axis, ``z_b`` East, ``C_r^b`` of (S1)); platform ``p`` with
$C_p^b = P_1(\\alpha) P_2(\\beta) P_3(\\gamma)$ (frame rotations ``P_k(t) = rot_k(-t)``, (S2)).
State: the gimbal angles ``(alpha, beta, gamma)`` (rad); time in s. The servo loops null the gyro
outputs, so the platform turns at minus the drift (S11) and the angles follow (S12):
$\\dot{(\\alpha,\\beta,\\gamma)} = M(\\beta,\\gamma)(-\\varepsilon - C_b^p \\omega_{ie}^b)$.

Gyro ``j`` (input axis = platform axis ``j``; output/spin axes cyclic, ``I x O = S``) drifts by
the 10-coefficient g-sensitive law (S10) with the specific force ``(1 + A_1(t)) n^p`` in g,
``n^p = C_b^p u^b``. ``drift_model="instantaneous"`` uses the vibration
``A_1 = a0 sin(omega t + phase)`` itself; ``"averaged"`` ((S14)) the period average, i.e. the
quadratic and cross terms times ``kappa = 1 + a0^2/2`` (``conditions.kappa``).

Parameters (internal rad/s; reports in deg/h, deg/h/g, deg/h/g^2): ``D_f_x ... D_os_z`` (30, the
canonical gyro-major order). Effects with null values: ``accel_bias`` (``b_x b_y b_z``, g),
``accel_scale`` (``dk_x dk_y dk_z``), ``accel_misalignment`` (``M_xy M_xz M_yx M_yz M_zx M_zy``,
rad): the accelerometer errors of (S20a), which act on the accelerometer channels only; and the
bench effects the gap diagnosis catalogues (docs/diagnosis.md), with the test time
``T = t0 + t`` (``conditions.t0``: the dwell's start in the test):

- ``base_misalignment``: ``dchi_x dchi_y dchi_z`` (rad, base axes): the base is turned by
  ``C_r^b' = R(-dchi) C_r^b`` (exact rotation), which moves the Earth rate and the gravity
  direction the platform sees;
- ``warmup_transient``: drift ``dm_j exp(-T / tau_w)`` (rad/s, platform axes), ``tau_w`` (s);
- ``drift_ramp``: drift ``ramp_j T`` (rad/s per s);
- ``vibration_rectification``: drift ``rect_j`` in vibrated dwells (``a0 > 0``) only (rad/s).

Channels: ``alpha beta gamma`` (rad) and ``ax ay az`` (specific force on the platform axes, g).
"""

from __future__ import annotations

from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..params import Param, ParameterSpace
from ..rotations import rot1, rot2, rot3, rotvec_to_matrix
from ._base import AbstractRig

__all__ = ["PlatformRig", "PlatformConditions", "COEFF_NAMES", "TABLE1_DEG", "TRUE_TABLE2",
           "DEFAULT_MOUNTING", "ENU_MOUNTING", "EARTH_RATE_SOURCE", "platform_matrix",
           "specific_force_direction", "kinematic_matrix", "drift_regressor", "drift_rates",
           "schedule", "ShockMount"]

EARTH_RATE_SOURCE = 7.2921151467e-5
AXES = ("x", "y", "z")
TERMS = ("f", "i", "o", "s", "ii", "oo", "ss", "io", "is", "os")
COEFF_NAMES = tuple(f"D_{term}_{ax}" for ax in AXES for term in TERMS)
"""The 30 coefficients in the canonical gyro-major order."""

DEFAULT_MOUNTING = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
"""``C_r^b`` of (S1): x_b North, y_b Up, z_b East."""
ENU_MOUNTING = np.eye(3)
"""``z_b`` Up (b = ENU): the design under which Table 1 cannot identify three cross terms."""

TABLE1_DEG = np.array([
    [0, 0, 0], [0, 0, 45], [0, 0, 90], [0, 0, 180], [180, 0, 45], [45, 0, 0], [45, 0, 90],
    [90, 0, 90], [90, 0, 180], [180, 0, 270], [270, 0, 0], [270, 0, 90], [-45, 0, 0],
    [-45, 0, 90]], dtype=float)
"""The 14 test positions (alpha, beta, gamma) in deg (docs/rigs/platform.md, Table 1)."""

_TRUE_X = (1, -1, -1, 1, 0.03, 0.03, -0.03, 0.03, -0.03, -0.03)
TRUE_TABLE2 = dict(zip(COEFF_NAMES, _TRUE_X + tuple(-v for v in _TRUE_X) + _TRUE_X, strict=True))
"""True coefficients of the source's simulation (docs/rigs/platform.md), display units."""


def _param_space() -> ParameterSpace:
    dh = units.DEG_PER_HOUR
    ps = []
    for ax in AXES:
        for term in TERMS:
            order = 0 if term == "f" else (1 if len(term) == 1 else 2)
            unit = ("deg/h", "deg/h/g", "deg/h/g^2")[order]
            scale = (1.0, 1.0, 0.03)[order] * dh
            ps.append(Param(name=f"D_{term}_{ax}", unit="rad/s", display_unit=unit,
                            display_factor=dh, scale=scale, null=0.0, effect=None,
                            description=f"gyro {ax}: " + ("bias" if order == 0 else
                                                          f"g-sensitive term {term}")))
    for ax in AXES:
        ps.append(Param(name=f"b_{ax}", unit="g", display_unit="g", display_factor=1.0,
                        scale=1e-4, effect="accel_bias", description=f"accelerometer {ax} bias"))
    for ax in AXES:
        ps.append(Param(name=f"dk_{ax}", unit="1", display_unit="ppm", display_factor=units.PPM,
                        scale=1e-4, effect="accel_scale",
                        description=f"accelerometer {ax} scale error"))
    for a in AXES:
        for b in AXES:
            if a != b:
                ps.append(Param(name=f"M_{a}{b}", unit="rad", display_unit="arcsec",
                                display_factor=units.ARCSEC, scale=100 * units.ARCSEC,
                                effect="accel_misalignment",
                                description=f"accelerometer misalignment {a}{b}"))
    for ax in AXES:
        ps.append(Param(name=f"dchi_{ax}", unit="rad", display_unit="arcsec",
                        display_factor=units.ARCSEC, scale=60 * units.ARCSEC,
                        effect="base_misalignment",
                        description=f"base rotation about base axis {ax}"))
    for ax in AXES:
        ps.append(Param(name=f"dm_{ax}", unit="rad/s", display_unit="deg/h", display_factor=dh,
                        scale=0.3 * dh, effect="warmup_transient",
                        description=f"gyro {ax}: warm-up drift excess at the test start"))
    ps.append(Param(name="tau_w", unit="s", display_unit="min", display_factor=60.0,
                    scale=600.0, null=600.0, effect="warmup_transient",
                    description="decay time of the warm-up transient"))
    for ax in AXES:
        ps.append(Param(name=f"ramp_{ax}", unit="rad/s^2", display_unit="deg/h/h",
                        display_factor=dh / units.HOUR, scale=0.3 * dh / units.HOUR,
                        effect="drift_ramp", description=f"gyro {ax}: linear drift growth"))
    for ax in AXES:
        ps.append(Param(name=f"rect_{ax}", unit="rad/s", display_unit="deg/h", display_factor=dh,
                        scale=0.1 * dh, effect="vibration_rectification",
                        description=f"gyro {ax}: constant drift under vibration"))
    return ParameterSpace(tuple(ps))


_SPACE = _param_space()


def platform_matrix(angles):
    """``C_p^b = P1(alpha) P2(beta) P3(gamma)`` with the frame rotations of (S2)."""
    a, b, c = angles[0], angles[1], angles[2]
    return rot1(-a) @ rot2(-b) @ rot3(-c)


def kinematic_matrix(beta, gamma):
    """``M(beta, gamma)`` of (S12): gimbal-angle rates from the platform-to-base rate in p axes."""
    cb, sg, cg, tb = jnp.cos(beta), jnp.sin(gamma), jnp.cos(gamma), jnp.tan(beta)
    z, o = jnp.zeros_like(beta), jnp.ones_like(beta)
    return jnp.stack([jnp.stack([-cg / cb, -sg / cb, z]), jnp.stack([sg, -cg, z]),
                      jnp.stack([-cg * tb, -sg * tb, -o])])


def specific_force_direction(angles, mounting):
    """``n^p = C_b^p u^b`` (S3): the unit Up direction in platform axes."""
    u_b = jnp.asarray(mounting) @ jnp.array([0.0, 0.0, 1.0])
    return platform_matrix(angles).T @ u_b


def _drift_terms(n, f1, f2):
    """(3, 10): each gyro's ten g-law terms (the order of its coefficients in ``COEFF_NAMES``)."""
    terms = []
    for k in range(3):
        ai, ao, as_ = n[k], n[(k + 1) % 3], n[(k + 2) % 3]
        terms.append(jnp.stack([jnp.ones_like(ai), ai * f1, ao * f1, as_ * f1, ai * ai * f2,
                                ao * ao * f2, as_ * as_ * f2, ai * ao * f2, ai * as_ * f2,
                                ao * as_ * f2]))
    return jnp.stack(terms)


def drift_regressor(n, f1, f2):
    """``G`` (3 x 30): drift of the three gyros per unit coefficient, for specific-force direction
    ``n`` (platform axes) with factor ``f1`` on the linear and ``f2`` on the quadratic/cross terms
    (averaged model: 1 and kappa; instantaneous: 1 + A1 and (1 + A1)^2)."""
    # block-diagonal placement by a product with the identity (no scatter: cheap under vmap)
    return (jnp.eye(3)[:, :, None] * _drift_terms(n, f1, f2)[None, :, :]).reshape(3, 30)


def drift_rates(n, f1, f2, coefficients):
    """``G @ coefficients`` of :func:`drift_regressor` (3,) without forming ``G``: each gyro's
    terms times its own ten coefficients. Under ``vmap`` XLA's CPU backend runs the product of
    a 3 x 30 block-diagonal ``G`` as a batched matrix-vector product, ~2x slower."""
    return jnp.sum(_drift_terms(n, f1, f2) * jnp.reshape(coefficients, (3, 10)), axis=1)


class PlatformConditions(eqx.Module):
    """One dwell of the test: latitude (rad), base mounting ``C_r^b``, the angles at ``t = 0``
    (rad), platform vibration amplitude ``a0`` (g), angular frequency ``omega`` (rad/s) and phase
    (rad), the ``kappa`` the averaged model uses (default ``1 + a0^2/2``; in identification the
    accelerometers' estimate) and the dwell's start ``t0`` in the test (s; the time-dependent
    effects run on test time ``t0 + t``). Stack them (leading axis) for a schedule of
    positions."""

    latitude: jax.Array
    mounting: jax.Array
    angles0: jax.Array
    a0: jax.Array
    omega: jax.Array
    phase: jax.Array
    kappa: jax.Array
    t0: jax.Array

    @staticmethod
    def from_record(record) -> PlatformConditions:
        """The conditions of one dwell a record's attributes give (its gimbal position
        ``alpha0_deg beta0_deg gamma0_deg``, ``latitude_deg``, ...); a whole test's record carries
        its schedule instead (:func:`~gyrojax.models.platform_schedule.schedule_conditions`)."""
        c = record.conditions
        missing = [k for k in ("alpha0_deg", "beta0_deg", "gamma0_deg") if k not in c]
        if missing:
            raise ValueError(f"record lacks the condition(s) {missing}: the dwell's gimbal "
                             "position (deg)")
        return PlatformConditions.create(
            [c["alpha0_deg"], c["beta0_deg"], c["gamma0_deg"]],
            latitude_deg=float(c.get("latitude_deg", 45.75)), a0=float(c.get("a0_g", 0.0)),
            frequency_hz=float(c.get("frequency_hz", 15.0)), t0=float(c.get("t0_s", 0.0)))

    @staticmethod
    def create(angles0_deg, *, latitude_deg: float = 45.75, a0: float = 0.0,
               frequency_hz: float = 15.0, phase: float = 0.0, kappa=None,
               mounting=DEFAULT_MOUNTING, t0: float = 0.0) -> PlatformConditions:
        m = np.asarray(mounting, float)
        if m.shape != (3, 3) or not np.allclose(m @ m.T, np.eye(3), atol=1e-9) \
                or np.linalg.det(m) < 0:
            raise ValueError("mounting: C_r^b must be a proper rotation matrix (3x3, orthonormal, "
                             f"det +1); got {m.tolist()}")
        if a0 < 0:
            raise ValueError(f"a0={a0}: the vibration amplitude (g) must be >= 0")
        k = 1.0 + 0.5 * a0**2 if kappa is None else kappa
        f = jnp.asarray
        return PlatformConditions(f(np.radians(latitude_deg)), f(m), f(np.radians(angles0_deg)),
                                  f(float(a0)), f(2 * np.pi * frequency_hz), f(float(phase)),
                                  f(float(k)), f(float(t0)))

    def earth_rate_base(self, mounting=None):
        """``omega_ie^b`` (rad/s), (S1); ``mounting`` overrides ``C_r^b``."""
        lat = self.latitude
        w_r = EARTH_RATE_SOURCE * jnp.stack([jnp.zeros_like(lat), jnp.cos(lat), jnp.sin(lat)])
        return (self.mounting if mounting is None else mounting) @ w_r

    def vibration(self, t):
        """``A_1(t)`` in g (steady state)."""
        return self.a0 * jnp.sin(self.omega * t + self.phase)


class PlatformRig(AbstractRig):
    """The platform rig. ``drift_model``: ``"averaged"`` (S14) or ``"instantaneous"`` (S10)."""

    CHANNEL_UNITS: ClassVar[dict] = {"alpha": "rad", "beta": "rad", "gamma": "rad", "ax": "m s-2",
                                     "ay": "m s-2", "az": "m s-2", "position": "1", "amplitude": "1"}

    drift_model: Literal["averaged", "instantaneous"] = eqx.field(static=True,
                                                                   default="averaged")

    def __check_init__(self):
        if self.drift_model not in ("averaged", "instantaneous"):
            raise ValueError(f"drift_model={self.drift_model!r}; use 'averaged' or "
                             "'instantaneous'")

    @property
    def param_space(self) -> ParameterSpace:
        return _SPACE

    @property
    def channels(self) -> tuple[str, ...]:
        return ("alpha", "beta", "gamma", "ax", "ay", "az")

    @property
    def time_scale(self) -> float:
        return 1.0

    def coefficients(self, params):
        return jnp.stack([params[n] for n in COEFF_NAMES])

    @staticmethod
    def mounting(params, conditions):
        """The base as it stands: ``R(-dchi) C_r^b`` (``C_r^b`` itself at ``dchi = 0``)."""
        dchi = jnp.stack([params[f"dchi_{ax}"] for ax in AXES])
        return rotvec_to_matrix(-dchi) @ conditions.mounting

    def drift(self, t, angles, params, conditions):
        """Gyro drifts (rad/s, platform axes) at time ``t`` and attitude ``angles``: the g-law
        plus the bench effects (warm-up, ramp on test time ``t0 + t``; rectification)."""
        n = specific_force_direction(angles, self.mounting(params, conditions))
        if self.drift_model == "averaged":
            f1, f2 = jnp.ones_like(conditions.kappa), conditions.kappa
        else:
            f1 = 1.0 + conditions.vibration(t)
            f2 = f1 * f1
        big_t = conditions.t0 + t
        vec = lambda pre: jnp.stack([params[f"{pre}_{ax}"] for ax in AXES])  # noqa: E731
        bench = (vec("dm") * jnp.exp(-big_t / params["tau_w"]) + vec("ramp") * big_t
                 + vec("rect") * jnp.where(conditions.a0 > 0, 1.0, 0.0))
        return drift_rates(n, f1, f2, self.coefficients(params)) + bench

    def initial_state(self, params, conditions):
        return conditions.angles0

    def vector_field(self, t, state, params, conditions):
        c_bp = platform_matrix(state).T
        w_ie = conditions.earth_rate_base(self.mounting(params, conditions))
        w_bp = -self.drift(t, state, params, conditions) - c_bp @ w_ie
        return kinematic_matrix(state[1], state[2]) @ w_bp

    def observe(self, t, state, params, conditions):
        n = specific_force_direction(state, self.mounting(params, conditions))
        f = (1.0 + conditions.vibration(t)) * n
        m = jnp.stack([jnp.stack([params["dk_x"], params["M_xy"], params["M_xz"]]),
                       jnp.stack([params["M_yx"], params["dk_y"], params["M_yz"]]),
                       jnp.stack([params["M_zx"], params["M_zy"], params["dk_z"]])])
        bias = jnp.stack([params["b_x"], params["b_y"], params["b_z"]])
        return jnp.concatenate([state, f + m @ f + bias])


def schedule(positions_deg=TABLE1_DEG, *, a0: float = 0.0, latitude_deg: float = 45.75,
             frequency_hz: float = 15.0, phases=None, kappa=None,
             mounting=DEFAULT_MOUNTING, t0s=None) -> PlatformConditions:
    """Stacked :class:`PlatformConditions` for a schedule of positions (rows alpha, beta, gamma in
    deg; default Table 1) at one platform vibration amplitude ``a0`` (g). ``phases``: vibration
    phase per position (rad; default 0); ``t0s``: each dwell's start in the test (s; default
    0)."""
    pos = np.asarray(positions_deg, float)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions: expected rows (alpha, beta, gamma) in deg, got shape "
                         f"{pos.shape}")
    if np.any(np.abs(np.abs(pos[:, 1]) - 90.0) < 1.0):
        raise ValueError("a position with |beta| near 90 deg is in gimbal lock (S12 singular)")
    phases = np.zeros(len(pos)) if phases is None else np.asarray(phases, float)
    t0s = np.zeros(len(pos)) if t0s is None else np.asarray(t0s, float)
    conds = [PlatformConditions.create(p, latitude_deg=latitude_deg, a0=a0,
                                       frequency_hz=frequency_hz, phase=float(ph), kappa=kappa,
                                       mounting=mounting, t0=float(t))
             for p, ph, t in zip(pos, phases, t0s, strict=True)]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *conds)


class ShockMount(eqx.Module):
    """The second-order shock mount of docs/rigs/platform.md between the table and the platform (S4):
    ``(m + k2) X'' + k1 X' + k0 X = k2 Y'' + k1 Y' + k0 Y`` with the table acceleration
    ``Y'' = a sin(omega t)``. Fields in SI: mass ``m`` (kg), stiffness ``k0`` (N/m), damping ``k1``
    (N s/m), inertance ``k2`` (kg)."""

    m: float
    k0: float
    k1: float
    k2: float = 0.0

    def __check_init__(self):
        if not (self.m > 0 and self.k0 > 0 and self.k1 > 0 and self.k2 >= 0):
            raise ValueError(f"shock mount: m={self.m}, k0={self.k0}, k1={self.k1} must be > 0 and "
                             f"k2={self.k2} >= 0 (kg, N/m, N s/m, kg)")

    @staticmethod
    def from_resonance(natural_hz: float, damping_ratio: float, m: float = 1.0) -> ShockMount:
        """A mount with ``k2 = 0`` of the given natural frequency and damping ratio."""
        wn = 2 * np.pi * natural_hz
        return ShockMount(m=m, k0=m * wn**2, k1=2 * damping_ratio * np.sqrt(m * m * wn**2))

    def response(self, omega):
        """Amplitude ratio ``a0/a`` (S6) and phase ``arg H`` (S7, four-quadrant) at ``omega``."""
        k1w = self.k1 * omega
        big_k1 = self.k0 - (self.m + self.k2) * omega**2
        big_k2 = self.k0 - self.k2 * omega**2
        ratio = jnp.sqrt((big_k2**2 + k1w**2) / (big_k1**2 + k1w**2))
        phase = jnp.arctan2(k1w * (big_k1 - big_k2), big_k1 * big_k2 + k1w**2)
        return ratio, phase

    def roots(self):
        """Roots ``lambda_1,2`` of ``(m + k2) l^2 + k1 l + k0 = 0`` (complex)."""
        mm = self.m + self.k2
        disc = np.sqrt(complex(self.k1**2 - 4 * mm * self.k0))
        return (-self.k1 + disc) / (2 * mm), (-self.k1 - disc) / (2 * mm)

    def platform_acceleration(self, t, a, omega):
        """Platform acceleration ``X''(t)`` (m/s^2) for a platform at rest at ``t = 0``: the steady
        state ``a0 sin(omega t + phi)`` plus the start transient (S8)-(S9)."""
        ratio, phase = self.response(omega)
        a0 = a * ratio
        l1, l2 = self.roots()
        c1 = a0 * (omega * jnp.cos(phase) - l2 * jnp.sin(phase)) / (omega**2 * (l1 - l2))
        c2 = -a0 * (omega * jnp.cos(phase) - l1 * jnp.sin(phase)) / (omega**2 * (l1 - l2))
        t = jnp.asarray(t, dtype=complex)
        trans = l1**2 * c1 * jnp.exp(l1 * t) + l2**2 * c2 * jnp.exp(l2 * t)
        return jnp.real(trans) + a0 * jnp.sin(omega * jnp.real(t) + phase)
