"""Strapdown IMU on a stand: static and multi-position records (gyro and accelerometer triads).

The stand holds the IMU still in a sequence of poses; between poses it is turned (by hand or a
table). In pose ``k`` the body-frame *up* unit vector is ``u_k``; the true specific force is
``f = g u_k`` and the true angular rate is the Earth rate, whose vertical part ``Omega sin(phi) u_k``
is known from the latitude (the horizontal part needs the heading, which hand-placed stands do not
record). The measurement model (SI; ``t`` from the record start):

    f_meas = b_a + (I + diag(s_a) + M_a) f                + d_a t + w_a exp(-t / tau_w)
    w_meas = b_g + (I + diag(s_g) + M_g) k_E Omega_v u_k + G f + d_g t + w_g exp(-t / tau_w)
             + k_Tg Delta T + k_Rg dT/dt              (accelerometer likewise)

plus noise: white (ARW/VRW, nominal), and the noise-model effects quantization (angle/velocity
quantization Q: a differenced white sequence), bias instability (flicker, simulated as a sum of
Gauss-Markov processes), rate random walk (K) and outliers (a contamination fraction).

**Nominal model** = the biases ``bgx.. baz`` with the nominal scale (the poses' directions are
nuisance parameters of the fit). **Effects** (stable names): ``earth_rate`` (``k_earth``, 1 = the
full vertical Earth rate; the diagnosis adds the horizontal part, one heading per chain of poses
joined by recorded turns: :mod:`gyrojax.diagnose`), ``scale_factor``, ``misalignment`` (6
off-diagonal terms per triad: the symmetric part is non-orthogonality, the antisymmetric part an
axis rotation, which the poses absorb for the accelerometer), ``g_sensitivity`` (9 terms),
``time_drift``, ``warmup_transient`` (decay time ``tau_w`` on a grid), ``temperature`` and
``temperature_rate`` (biases per ``Delta T`` and per ``dT/dt``, one per channel; they need the
IMU's temperature: a ``temp*`` channel in the diagnosis, ``temperature_c`` in the simulator),
``quantization``, ``bias_instability``, ``rate_random_walk``, ``outliers``.

The IMU is algebraic on a static stand (no equations of motion), so :class:`IMURig` gives the
parameter space and the measurement function, not a diffrax vector field; :func:`simulate_imu`
integrates the attitude through the turns between poses exactly (piecewise-constant rates). A
pose may also turn at a constant rate-table rate about the vertical (:class:`Pose`
``rate_dps``; design D4 of docs/goals.md): the up vector stays put and the gyros see the table rate along it.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .. import units
from ..earth import check_gravity, normal_gravity
from ..params import ParameterSpace, param
from ..record import BenchRecord, freeze
from ..rotations import rotvec_to_matrix

__all__ = ["IMURig", "IMUConditions", "imu_measure", "true_rate", "true_force",
           "simulate_imu", "IMU_CHANNELS",
           "MEAN_EFFECTS", "NOISE_EFFECTS", "Pose", "cube_poses", "gyro_matrix", "accel_matrix",
           "pose_frame"]

IMU_CHANNELS = ("wx", "wy", "wz", "ax", "ay", "az")
AX = "xyz"
OFF = ("xy", "xz", "yx", "yz", "zx", "zy")
MEAN_EFFECTS = ("earth_rate", "scale_factor", "misalignment", "g_sensitivity", "time_drift",
                "warmup_transient", "temperature", "temperature_rate")
THERMAL_EFFECTS = ("temperature", "temperature_rate")  # need a temperature channel
T_REF_C = 25.0  # deg C, the reference of the temperature effect's Delta T
NOISE_EFFECTS = ("quantization", "bias_instability", "rate_random_walk", "outliers")


def _space() -> ParameterSpace:
    dph = units.DEG_PER_HOUR
    mg = 1e-3 * units.G0
    ps = [param(f"bg{a}", "rad/s", "deg/h", 10 * dph, description=f"gyro {a} bias")
          for a in AX]
    ps += [param(f"ba{a}", "m/s^2", "mg", 10 * mg, description=f"accelerometer {a} bias")
           for a in AX]
    ps += [param("k_earth", "1", "1", 1.0, effect="earth_rate",
                 description="fraction of the vertical Earth rate Omega sin(lat) seen (1 = all)")]
    ps += [param(f"sg{a}", "1", "ppm", 1e-3, effect="scale_factor",
                 description=f"gyro {a} scale-factor error") for a in AX]
    ps += [param(f"sa{a}", "1", "ppm", 1e-3, effect="scale_factor",
                 description=f"accelerometer {a} scale-factor error") for a in AX]
    ps += [param(f"ma{o}", "rad", "mrad", 1e-3, effect="misalignment",
                 description=f"accelerometer misalignment: {o[0]} output per {o[1]} input")
           for o in OFF]
    ps += [param(f"mg{o}", "rad", "mrad", 1e-3, effect="misalignment",
                 description=f"gyro misalignment: {o[0]} output per {o[1]} input") for o in OFF]
    ps += [param(f"gs{a}{b}", "s/m", "deg/h/g", 10 * dph / units.G0, effect="g_sensitivity",
                 description=f"gyro {a} drift per specific force along {b}")
           for a in AX for b in AX]
    ps += [param(f"dg{a}", "rad/s^2", "deg/h/h", 1 * dph / 3600, effect="time_drift",
                 description=f"gyro {a} bias drift rate") for a in AX]
    ps += [param(f"da{a}", "m/s^3", "mg/h", 0.1 * mg / 3600, effect="time_drift",
                 description=f"accelerometer {a} bias drift rate") for a in AX]
    ps += [param(f"wg{a}", "rad/s", "deg/h", 10 * dph, effect="warmup_transient",
                 description=f"gyro {a} warm-up amplitude (decays as exp(-t/tau_w))") for a in AX]
    ps += [param(f"wa{a}", "m/s^2", "mg", 1 * mg, effect="warmup_transient",
                 description=f"accelerometer {a} warm-up amplitude") for a in AX]
    ps += [param("tau_w", "s", "h", 600.0, null=600.0, effect="warmup_transient",
                 description="warm-up decay time (a grid in the diagnosis)")]
    ps += [param(f"tg{a}", "rad/s/K", "deg/h/degC", dph, effect="temperature",
                 description=f"gyro {a} bias per degree of temperature (Delta T from 25 deg C)")
           for a in AX]
    ps += [param(f"ta{a}", "m/s^2/K", "mg/degC", 0.1 * mg, effect="temperature",
                 description=f"accelerometer {a} bias per degree of temperature") for a in AX]
    ps += [param(f"rg{a}", "rad/K", "deg/h/(degC/min)", 60 * dph, effect="temperature_rate",
                 description=f"gyro {a} bias per rate of temperature change (dT/dt)")
           for a in AX]
    ps += [param(f"ra{a}", "m/s/K", "mg/(degC/min)", 6 * mg, effect="temperature_rate",
                 description=f"accelerometer {a} bias per rate of temperature change")
           for a in AX]
    ps += [param("q_g", "rad", "arcsec", units.ARCSEC, effect="quantization",
                 description="gyro angle quantization Q (each axis)"),
           param("q_a", "m/s", "m/s", 1e-4, effect="quantization",
                 description="accelerometer velocity quantization Q (each axis)")]
    ps += [param("b_g", "rad/s", "deg/h", 1 * dph, effect="bias_instability",
                 description="gyro bias instability B (Allan floor / 0.664)"),
           param("b_a", "m/s^2", "mg", 0.05 * mg, effect="bias_instability",
                 description="accelerometer bias instability B")]
    ps += [param("k_g", "rad/s/sqrt(s)", "deg/h/sqrt(h)", 1 * dph / 60, effect="rate_random_walk",
                 description="gyro rate random walk K"),
           param("k_a", "m/s^2/sqrt(s)", "mg/sqrt(h)", 0.01 * mg / 60, effect="rate_random_walk",
                 description="accelerometer acceleration random walk K")]
    ps += [param("eps_out", "1", "1", 1e-3, effect="outliers",
                 description="fraction of samples replaced by outliers (10-30 sigma)")]
    return ParameterSpace(tuple(ps))


_SPACE = _space()


class IMUConditions(eqx.Module):
    """Test conditions. ``latitude_deg`` (NaN if unknown: no Earth-rate effect), local gravity
    ``gravity`` (m/s^2), sampling rate ``rate_hz``."""

    latitude_deg: float = eqx.field(static=True, default=float("nan"))
    gravity: float = eqx.field(static=True, default=units.G0)
    rate_hz: float = eqx.field(static=True, default=100.0)

    def __check_init__(self):
        lat = float(self.latitude_deg)
        if not (np.isnan(lat) or -90.0 <= lat <= 90.0):
            raise ValueError(f"latitude {lat:g} deg is outside [-90, 90]; give the test site's "
                             "latitude (--latitude) in degrees North, or none for no Earth rate")
        check_gravity(self.gravity, "the record's gravity_mps2")

    @property
    def vertical_earth_rate(self) -> float:
        lat = self.latitude_deg
        return 0.0 if np.isnan(lat) else float(units.EARTH_RATE * np.sin(np.radians(lat)))

    @staticmethod
    def create(latitude_deg: float = float("nan"), *, gravity: float | None = None,
               rate_hz: float = 100.0) -> IMUConditions:
        """The conditions at ``latitude_deg`` (NaN: unknown), gravity (default: the normal
        gravity there, or g0), sampling rate ``rate_hz``."""
        if gravity is None:
            gravity = (units.G0 if np.isnan(latitude_deg)
                       else float(normal_gravity(np.radians(latitude_deg))))
        return IMUConditions(float(latitude_deg), float(gravity), float(rate_hz))

    @staticmethod
    def from_record(record: BenchRecord) -> IMUConditions:
        """The conditions a record's attributes give (``latitude_deg``, ``gravity_mps2``,
        ``rate_hz``; the rate from the sample times where absent)."""
        c = record.conditions
        lat = float(c.get("latitude_deg", float("nan")))
        if "gravity_mps2" in c:
            g = float(c["gravity_mps2"])
        elif not np.isnan(lat):
            g = float(normal_gravity(np.radians(lat)))
        else:
            g = units.G0
        dt = np.median(np.diff(np.asarray(record.t)))
        return IMUConditions(lat, g, float(c.get("rate_hz", 1.0 / dt)))


class IMURig(eqx.Module):
    """The strapdown IMU rig's parameter catalogue and measurement model (see module docstring)."""

    # a rate table turns at most a few hundred deg/s; an accelerometer on a stand reads ~1 g
    # (the names in full: an auxiliary channel such as aux1 or a supply voltage is not bounded)
    CHANNEL_BOUNDS: ClassVar[dict] = {
        **{c: (100.0, "gyro rates are in rad/s (from deg/s: x 0.0174533)")
           for c in ("wx", "wy", "wz")},
        **{c: (1000.0, "specific forces are in m/s^2 (from g: x 9.80665; from mg: x "
                       "0.00980665)") for c in ("ax", "ay", "az")}}
    CHANNEL_UNITS: ClassVar[dict] = {"wx": "rad s-1", "wy": "rad s-1", "wz": "rad s-1",
                                     "ax": "m s-2", "ay": "m s-2", "az": "m s-2"}

    @property
    def param_space(self) -> ParameterSpace:
        return _SPACE

    @property
    def channels(self) -> tuple[str, ...]:
        return IMU_CHANNELS

    def measure(self, params, up, t, conditions: IMUConditions, rate=None, thermal=None):
        return imu_measure(params, up, t, conditions, rate, thermal)


def _vec(params, prefix):
    return jnp.stack([jnp.asarray(params[f"{prefix}{a}"], float) for a in AX])


def _mat(params, prefix, scale_prefix):
    m = jnp.diag(_vec(params, scale_prefix))
    for o in OFF:
        i, j = AX.index(o[0]), AX.index(o[1])
        m = m.at[i, j].set(params[f"{prefix}{o}"])
    return jnp.eye(3) + m


def gyro_matrix(params):
    """``I + diag(s_g) + M_g``: true rate -> gyro output."""
    return _mat(params, "mg", "sg")


def accel_matrix(params):
    """``I + diag(s_a) + M_a``: true specific force -> accelerometer output."""
    return _mat(params, "ma", "sa")


def imu_measure(params, up: Float[ArrayLike, "n 3"], t: Float[ArrayLike, " n"],
                conditions: IMUConditions, rate: Float[ArrayLike, "n 3"] | None = None,
                thermal=None) -> Float[Array, "n 6"]:
    """Noise-free outputs ``(n, 6)`` = ``wx wy wz ax ay az`` for body-frame up vectors ``up``
    ``(n, 3)`` (unit) at times ``t`` ``(n,)``; ``rate`` ``(n, 3)`` adds a body rotation rate
    (turns between poses) to the Earth rate; ``thermal`` ``(dT, dT/dt)``, two ``(n,)`` arrays
    (K from the reference, K/s), drives the temperature effects (none if not given)."""
    up = jnp.asarray(up, float)
    t = jnp.asarray(t, float)[:, None]
    f = conditions.gravity * up
    w = params["k_earth"] * conditions.vertical_earth_rate * up
    if rate is not None:
        w = w + rate
    g = jnp.stack([_vec(params, f"gs{a}") for a in AX])
    decay = jnp.exp(-t / params["tau_w"])
    wm = (_vec(params, "bg") + w @ gyro_matrix(params).T + f @ g.T + _vec(params, "dg") * t
          + _vec(params, "wg") * decay)
    fm = (_vec(params, "ba") + f @ accel_matrix(params).T + _vec(params, "da") * t
          + _vec(params, "wa") * decay)
    if thermal is not None:
        d_t, rate_t = (jnp.asarray(x, float)[:, None] for x in thermal)
        wm = wm + _vec(params, "tg") * d_t + _vec(params, "rg") * rate_t
        fm = fm + _vec(params, "ta") * d_t + _vec(params, "ra") * rate_t
    return jnp.concatenate([wm, fm], axis=1)


def true_force(params, f_meas, t, thermal=None):
    """The specific force that :func:`imu_measure`'s accelerometer model turns into ``f_meas``:
    ``A_a^-1 (f_meas - b_a - d_a t - w_a exp(-t / tau_w) [- t_a dT - r_a dT/dt])``, exact.
    ``f_meas`` ``(..., 3)`` m/s^2, ``t`` ``(...)`` s, ``thermal`` two ``(...)`` arrays or
    ``None``; returns ``(..., 3)`` m/s^2."""
    t = jnp.asarray(t, float)[..., None]
    raw = (jnp.asarray(f_meas, float) - _vec(params, "ba") - _vec(params, "da") * t
           - _vec(params, "wa") * jnp.exp(-t / params["tau_w"]))
    if thermal is not None:
        d_t, rate_t = (jnp.asarray(x, float)[..., None] for x in thermal)
        raw = raw - _vec(params, "ta") * d_t - _vec(params, "ra") * rate_t
    return raw @ jnp.linalg.inv(accel_matrix(params)).T


def true_rate(params, w_meas, f, t, thermal=None):
    """The body rate that :func:`imu_measure`'s gyro model turns into ``w_meas``: ``A_g^-1
    (w_meas - b_g - G f - d_g t - w_g exp(-t / tau_w) [- t_g dT - r_g dT/dt])``, exact (the
    model is linear in the rate). ``w_meas``, ``f`` ``(..., 3)`` (rad/s, the specific force in
    m/s^2), ``t`` ``(...)`` (s), ``thermal`` two ``(...)`` arrays or ``None``; returns
    ``(..., 3)`` rad/s."""
    t = jnp.asarray(t, float)[..., None]
    g = jnp.stack([_vec(params, f"gs{a}") for a in AX])
    raw = (jnp.asarray(w_meas, float) - _vec(params, "bg") - jnp.asarray(f, float) @ g.T
           - _vec(params, "dg") * t - _vec(params, "wg") * jnp.exp(-t / params["tau_w"]))
    if thermal is not None:
        d_t, rate_t = (jnp.asarray(x, float)[..., None] for x in thermal)
        raw = raw - _vec(params, "tg") * d_t - _vec(params, "rg") * rate_t
    return raw @ jnp.linalg.inv(gyro_matrix(params)).T


class Pose(eqx.Module):
    """A pose: body-frame up vector (normalised) and dwell time in s; ``rate_dps`` turns the
    IMU at a constant table rate (deg/s) about the vertical, i.e. about its up axis (right-handed
    about up: positive is counter-clockwise seen from above), which leaves the up vector
    constant. The IMU sits at the table's centre (no centripetal acceleration)."""

    up: tuple
    dwell_s: float
    rate_dps: float = 0.0


def cube_poses(n: int = 12, dwell_s: float = 10.0, seed: int = 0) -> list[Pose]:
    """``n`` poses: the six axis-up poses first, then random tilted ones (seeded)."""
    base = [(0, 0, 1), (0, 0, -1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)]
    rng = np.random.default_rng(seed)
    out = [Pose(tuple(float(x) for x in b), dwell_s) for b in base[:n]]
    while len(out) < n:
        v = rng.normal(size=3)
        out.append(Pose(tuple(float(x) for x in v / np.linalg.norm(v)), dwell_s))
    return out


def pose_frame(up):
    """Two unit vectors across each up vector of ``up`` ``(n, 3)``: ``e1`` (x or, near the x
    axis, y crossed into the plane across up) and ``e2 = up x e1``. The diagnosis' pose terms tilt
    along them; the simulator's ``heading_deg`` counts from ``e1``."""
    up = np.asarray(up, float)
    e1 = np.cross(up, np.where(np.abs(up[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(up, e1)


def _turn(u0, u1):
    """Rotation vector (body frame) taking body up-vector u0 to u1 by the shortest turn."""
    u0, u1 = np.asarray(u0, float), np.asarray(u1, float)
    c = np.clip(u0 @ u1, -1, 1)
    axis = np.cross(u1, u0)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        if c > 0:
            return np.zeros(3)
        perp = np.cross(u0, [1.0, 0, 0] if abs(u0[0]) < 0.9 else [0, 1.0, 0])
        return np.pi * perp / np.linalg.norm(perp)
    return np.arctan2(s, c) * axis / s


_rotvecs_to_matrices = jax.jit(jax.vmap(rotvec_to_matrix))


def _about(v, axis, angles):
    """``v`` turned about the unit ``axis`` by each of ``angles`` (rad, right-handed):
    ``(len(angles), 3)`` (Rodrigues)."""
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    return v * c + np.cross(axis, v) * s + axis * np.dot(axis, v) * (1 - c)


def simulate_imu(params, poses, *, rate_hz: float = 100.0, turn_s: float = 2.0,
                 latitude_deg: float = float("nan"), gravity: float = units.G0,
                 arw=0.0, vrw=0.0, key=None, noise=None,
                 heading_deg: float | None = None, temperature_c=None) -> BenchRecord:
    """A multi-position record: static poses joined by constant-rate turns of ``turn_s``.

    **Arguments:**
    - `params`: full parameter dict (``IMURig().param_space.make(...)``), SI.
    - `poses`: list of :class:`Pose`.
    - `arw`, `vrw`: white noise densities, gyro (rad/s/sqrt(Hz)) and accelerometer
      (m/s^2/sqrt(Hz)); the noise-model effects' strengths come from ``params`` (``q_g``, ``b_g``,
      ``k_g``, ``q_a``, ``b_a``, ``k_a``, ``eps_out``).
    - `key`: PRNG key (required when any noise is non-zero).
    - `heading_deg`: where given (with ``latitude_deg``), the horizontal Earth rate
      ``k_earth Omega cos(lat)`` is added along north, which lies at ``heading_deg`` from the
      first pose's :func:`pose_frame` ``e1`` about up at the record's start and stays fixed in
      space: in the body frame it turns with every turn between poses and every table run (at
      minus the table rate), as a real stand's Earth rate does. Off by default (no horizontal
      Earth rate).
    - `temperature_c`: the IMU's temperature (deg C) as a function of time (s), where the
      temperature effects act (``Delta T`` from ``T_REF_C`` and ``dT/dt``); the record does not
      carry it (add a ``temp`` channel as a real test would measure it).

    **Returns:** a BenchRecord with conditions ``latitude_deg``, ``gravity_mps2``, ``rate_hz``,
    ``static_s`` (flat (t0, t1, ...) spans of the poses, turning ones included: the truth for
    the detector and the harness) and, where a pose turns on the table, ``table_rate_s`` (flat
    (t0, t1, rate_dps, ...) triples: the table's commanded rates, a test input the diagnosis
    reads).
    """
    dt = 1.0 / rate_hz
    ups, rates, spans, table, t_now = [], [], [], [], 0.0
    north = None  # the body-frame north unit vector, carried through every pose and turn
    if heading_deg is not None and not np.isnan(latitude_deg) and poses:
        e1, e2 = pose_frame(np.asarray(poses[0].up, float)[None])
        h = np.radians(heading_deg)
        north = np.cos(h) * e1[0] + np.sin(h) * e2[0]
        horizontal = (float(params["k_earth"]) * units.EARTH_RATE
                      * np.cos(np.radians(latitude_deg)))
    for k, pose in enumerate(poses):
        u = np.asarray(pose.up, float) / np.linalg.norm(pose.up)
        n_s = int(round(pose.dwell_s * rate_hz))
        ups.append(np.tile(u, (n_s, 1)))
        w_k = np.tile(np.radians(pose.rate_dps) * u, (n_s, 1))
        if north is not None:
            # on the table north turns about up at minus the table rate (body frame)
            ang = -np.radians(pose.rate_dps) * np.arange(n_s + 1) * dt
            nk = _about(north, u, ang)
            w_k = w_k + horizontal * nk[:-1]
            north = nk[-1]
        rates.append(w_k)
        spans += [t_now, t_now + (n_s - 1) * dt]
        if pose.rate_dps != 0.0:
            table += [t_now, t_now + (n_s - 1) * dt, float(pose.rate_dps)]
        t_now += n_s * dt
        if k + 1 < len(poses):
            u1 = np.asarray(poses[k + 1].up, float) / np.linalg.norm(poses[k + 1].up)
            rv = _turn(u, u1)
            n_t = int(round(turn_s * rate_hz))
            w = rv / (n_t * dt)
            # attitude during the turn: u(t) = R(-w t) u  (up vector in the turning body frame)
            tt = (np.arange(n_t) + 0.5) * dt
            mats = np.asarray(_rotvecs_to_matrices(jnp.asarray(-w * tt[:, None])))
            ups.append(mats @ u)
            w_t = np.tile(w, (n_t, 1))
            if north is not None:
                w_t = w_t + horizontal * (mats @ north)
                north = np.asarray(rotvec_to_matrix(jnp.asarray(-rv))) @ north
            rates.append(w_t)
            t_now += n_t * dt
    up = np.concatenate(ups)
    rate = np.concatenate(rates)
    t = np.arange(len(up)) * dt
    cond = IMUConditions(latitude_deg, gravity, rate_hz)
    thermal = None
    if temperature_c is not None:
        temp = np.asarray(temperature_c(t), float)
        thermal = (temp - T_REF_C, np.gradient(temp, t))
    y = np.asarray(imu_measure(params, up, t, cond, rate, thermal))
    if key is not None:
        y = y + np.asarray(imu_noise(key, params, len(t), rate_hz, arw, vrw, noise))
    attrs = {"latitude_deg": latitude_deg, "gravity_mps2": gravity, "rate_hz": rate_hz,
             "static_s": tuple(spans)}
    if table:
        attrs["table_rate_s"] = tuple(table)
    return BenchRecord(jnp.asarray(t), jnp.asarray(y), IMU_CHANNELS, freeze(attrs))


def imu_noise(key, params, n: int, rate_hz: float, arw=0.0, vrw=0.0, noise=None):
    """Noise ``(n, 6)``: white (ARW/VRW densities N: per-sample std N/sqrt(dt)), quantization
    (the first difference of a white angle error of std Q, over dt: Allan variance 3Q^2/tau^2), bias
    instability (three Gauss-Markov processes spanning 1-1000 s matched to a flat Allan floor
    0.664 B), rate random walk (K sqrt(dt) increments) and outliers (fraction ``eps_out``,
    amplitude 20 sigma of the white noise)."""
    dt = 1.0 / rate_hz
    p = {k: float(np.asarray(params[k])) for k in ("q_g", "q_a", "b_g", "b_a", "k_g", "k_a",
                                                    "eps_out")}
    ks = jax.random.split(key, 8)
    white_sd = jnp.array([arw] * 3 + [vrw] * 3) / np.sqrt(dt)
    out = jax.random.normal(ks[0], (n, 6)) * white_sd
    q = jnp.array([p["q_g"]] * 3 + [p["q_a"]] * 3)
    if np.any(np.asarray(q) > 0):
        # angle quantization: the integrated output is rounded, so the rate error is the
        # first difference of a white sequence of variance Q^2 (IEEE: Q^2 = (step^2)/12)
        e = jax.random.normal(ks[1], (n + 1, 6)) * q
        out = out + jnp.diff(e, axis=0) / dt
    b = np.array([p["b_g"]] * 3 + [p["b_a"]] * 3)
    if np.any(b > 0):
        out = out + _flicker(ks[2], n, dt, b)
    kk = jnp.array([p["k_g"]] * 3 + [p["k_a"]] * 3)
    if np.any(np.asarray(kk) > 0):
        out = out + jnp.cumsum(jax.random.normal(ks[3], (n, 6)) * kk * np.sqrt(dt), axis=0)
    if p["eps_out"] > 0:
        hit = jax.random.uniform(ks[4], (n, 6)) < p["eps_out"]
        amp = 20 * jnp.where(white_sd > 0, white_sd, 1.0) * jax.random.choice(
            ks[5], jnp.array([-1.0, 1.0]), (n, 6)) * jax.random.uniform(ks[6], (n, 6), minval=0.5,
                                                                        maxval=1.5)
        out = out + jnp.where(hit, amp, 0.0)
    return out


def flicker_spectral(key, n, dt, b, *, span: int = 8):
    """Flicker noise ``(n, len(b))`` of bias-instability coefficient ``B`` by spectral synthesis:
    one-sided PSD ``B^2 / (pi f)`` (IEEE 952's two-sided ``B^2 / (2 pi f)``; Allan deviation
    floor ``sqrt(2 ln 2 / pi) B = 0.664 B``) at every Fourier frequency of a series ``span``
    times as long (so the record also carries the power below ``1 / (n dt)``), random Gaussian
    coefficients, a random length-``n`` piece kept. A
    construction independent of the GM-sum model (:func:`_flicker`, and the diagnosis'
    :mod:`gyrojax.analysis.flicker`): the robustness suite's misspecified noise."""
    b = np.asarray(b, float)
    m = span * n
    f = np.fft.rfftfreq(m, dt)[1:]
    amp = np.sqrt(m / (4 * dt) * b[None, :] ** 2 / (np.pi * f[:, None]))
    k1, k2, k3 = jax.random.split(key, 3)
    z = (jax.random.normal(k1, amp.shape) + 1j * jax.random.normal(k2, amp.shape)) * amp
    z = jnp.concatenate([jnp.zeros((1, len(b))), z], axis=0)
    x = jnp.fft.irfft(z, n=m, axis=0)
    start = jax.random.randint(k3, (), 0, m - n + 1)
    return jax.lax.dynamic_slice_in_dim(x, start, n, axis=0)


def _flicker(key, n, dt, b, t0: float = 1.0):
    """Bias instability B as a sum of first-order Gauss-Markov processes with correlation times
    one decade apart (``t0`` ... 10^4 ``t0``; default 1 s ... 10^4 s), each of variance chosen so
    the Allan deviation is flat at about 0.664 B over the covered range, ~2 ``t0`` to ~2000
    ``t0`` (the standard GM-sum approximation of flicker noise)."""
    from ..analysis.flicker import FLICKER_STD_PER_B, flicker_taus

    taus = flicker_taus(t0)
    s = FLICKER_STD_PER_B * np.asarray(b)
    keys = jax.random.split(key, len(taus))
    tot = 0.0
    for kk, T in zip(keys, taus):
        phi = np.exp(-dt / T)
        w = jax.random.normal(kk, (n, len(b))) * s * np.sqrt(1 - phi ** 2)
        x0 = jax.random.normal(jax.random.fold_in(kk, 1), (len(b),)) * s

        def step(x, wk, phi=phi):
            x = phi * x + wk
            return x, x

        _, xs = jax.lax.scan(step, x0, w)
        tot = tot + xs
    return tot
