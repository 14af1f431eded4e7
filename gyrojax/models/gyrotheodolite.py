"""Gyrotheodolite sensing element — docs/rigs/gyrotheodolite.md.

State ``x = (alpha, alpha_dot, beta, beta_dot)`` (rad, rad/s); only ``alpha`` is measured. Frame:
SE frame x = main axis (North), y = Up, z = East; ``alpha`` about the vertical, ``beta`` tilt about
z; the centre of mass a distance l below the suspension. Equations (1) with
``k_alpha = H omega3 cos(phi)(1 + kappa)``, ``D = F_KC + f_alpha``:

$J_y \\ddot\\alpha + H\\dot\\beta + D\\dot\\alpha + k_\\alpha \\alpha = mgl(\\gamma n_X + \\beta n_Z)$,
$J_z \\ddot\\beta - H\\dot\\alpha + f_\\beta\\dot\\beta + mgl\\,\\beta = mgl\\,n_X + H\\omega_3\\sin\\varphi$.

Vibration: ``n_X = n_m cos(eps_v + psi0) sin(omega t)``,
``n_Z = n_m sin(eps_v + psi0) sin(omega t)`` in g.

Roll ``gamma`` about the main axis (**assumed**; the source gives no model): the steady-state
response of a pendulous roll mode driven like the tilt mode of (1),
$J_x\\ddot\\gamma + f_\\gamma\\dot\\gamma + mgl\\,\\gamma = mgl\\,n_Z$ (roll about the spin axis
has no gyroscopic coupling). With ``roll_rate_coupling=True`` (default) the azimuth equation also
carries the kinematic term: the azimuth rate seen about the horizontal axis ``z`` of the rolled
SE, $-\\dot\\alpha\\gamma$, adds to the Earth-rate term, i.e. ``+ H alpha_dot gamma`` on the right
of the first equation. This is the mechanism behind the compensation formula; without vibration
both additions vanish and the rig is exactly (1).

Parameters (nominal; the assumed values of docs/rigs/gyrotheodolite.md are the defaults of
:meth:`default_params`): ``H`` (N m s), ``J_y``, ``J_z``, ``J_x`` (kg m^2), ``mgl`` (N m),
``f_alpha``, ``f_beta``, ``f_gamma``, ``F_KC`` (N m s), ``kappa`` (1). ``J_x`` and ``f_gamma``
(roll mode) are assumed equal to ``J_z``, ``f_beta``.

Bench-test parameters (null 0, so the defaults are exactly (1) released from rest in the
meridian): ``index_offset`` A, the azimuth of the meridian from the instrument's index line (the
quantity a gyrotheodolite measures; the pick-off reads ``alpha + A``, and the compensation link,
driven by the pick-off, applies ``-K_KC (alpha + A)``); the release state ``alpha0``,
``alpha_dot0``.

Unmodelled-effect groups (torques about the vertical, and the pick-off scale), all null 0:
``tape_torque`` (constant torque of the suspension tape's zero offset, ``M_tape``),
``torque_ramp`` (``M_ramp t``), ``drift_transient`` (warm-up ``M_tr exp(-t/tau_tr)``),
``torque_step`` (``M_step`` from ``t_step``, a 10 s tanh rise) and ``pickoff_scale`` (the
pick-off reads ``(1 + k_pick)(alpha + A)``). A constant torque shifts the equilibrium by
``M/(H omega3 cos phi)``, exactly as an index offset does, so ``tape_torque`` has no signature
in a single run: only a second run at another rotor momentum ``H`` separates them.
"""

from __future__ import annotations

from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .. import units
from ..params import Param, ParameterSpace, param
from ._base import AbstractRig

__all__ = ["GyrotheodoliteRig", "GyrotheodoliteConditions", "DEFAULTS", "ODE_OPTIONS",
           "TEST_PARAMS"]

DEFAULTS = {"H": 0.1, "J_y": 1.0e-3, "J_z": 3.5e-3, "mgl": 0.48, "f_alpha": 1e-5,
            "f_beta": 1e-2, "F_KC": 3e-4, "kappa": 0.0, "J_x": 3.5e-3, "f_gamma": 1e-2}
"""Assumed parameter set of docs/rigs/gyrotheodolite.md (north-seeking period ~8 min); ``J_x``, ``f_gamma``
of the roll mode are gyrojax's assumption (not in the source)."""

ODE_OPTIONS = {"solver": diffrax.Kvaerno5(), "rtol": 1e-8, "atol": 1e-12, "max_steps": 200_000}
"""Integration settings for bench-length runs (``integrate``/``simulate``/``trajectory_jacobian``
keywords): the 8.7 Hz nutation mode makes the rig stiff, so explicit solvers step at ~0.1 s;
the implicit ``Kvaerno5`` steps with the slow mode."""
TEST_PARAMS = ("index_offset", "alpha0", "alpha_dot0", "kappa", "F_KC")
"""What a north-seeking run determines besides the unmodelled effects: the index offset, the
release state, and the slow mode's stiffness and damping (the diagnosis' nominal model)."""

POSITIVE = ("H", "J_y", "J_z", "J_x", "mgl")
NON_NEGATIVE = ("f_alpha", "f_beta", "f_gamma", "F_KC")

_UNITS = {"H": "N m s", "J_y": "kg m^2", "J_z": "kg m^2", "mgl": "N m", "f_alpha": "N m s",
          "f_beta": "N m s", "F_KC": "N m s", "kappa": "1", "J_x": "kg m^2", "f_gamma": "N m s"}
_DESC = {"H": "rotor angular momentum", "J_y": "SE inertia about the vertical (azimuth)",
         "J_z": "SE inertia about the tilt axis", "mgl": "pendulous moment",
         "f_alpha": "viscous friction in azimuth", "f_beta": "viscous friction in tilt",
         "F_KC": "damping of the compensation link", "kappa": "relative compensation gain",
         "J_x": "SE inertia about the main axis (roll mode, assumed)",
         "f_gamma": "viscous friction in roll (assumed)"}
_SCALES = {"kappa": 0.1, "F_KC": 3e-5, "f_alpha": 1e-6}
STEP_WIDTH = 10.0
"""Rise time (s) of the tanh step of ``torque_step``."""
_NULL_TORQUE = 0.2e-9  # ~10 arcsec of equilibrium shift at the default H and Kyiv latitude
_SPACE = ParameterSpace(tuple(
    Param(name=n, unit=_UNITS[n], display_unit=_UNITS[n], display_factor=1.0,
          scale=_SCALES.get(n, max(abs(v), 1e-6)), null=v, description=_DESC[n])
    for n, v in DEFAULTS.items()) + (
    param("index_offset", "rad", "arcsec", units.ARCMIN,
          description="azimuth of the meridian from the index line (pick-off zero)"),
    param("alpha0", "rad", "arcmin", 10 * units.ARCMIN,
          description="azimuth deflection from the meridian at release"),
    param("alpha_dot0", "rad/s", "arcsec/s", 10 * units.ARCSEC,
          description="azimuth rate at release"),
    param("M_tape", "N m", "nN m", _NULL_TORQUE, effect="tape_torque",
          description="constant torque about the vertical (suspension-tape zero)"),
    param("M_ramp", "N m/s", "nN m/h", _NULL_TORQUE / units.HOUR, effect="torque_ramp",
          description="torque about the vertical growing linearly in time"),
    param("M_tr", "N m", "nN m", _NULL_TORQUE, effect="drift_transient",
          description="warm-up torque at t = 0, decaying as exp(-t/tau_tr)"),
    param("tau_tr", "s", "min", 600.0, null=600.0, effect="drift_transient",
          description="decay time of the warm-up torque"),
    param("M_step", "N m", "nN m", _NULL_TORQUE, effect="torque_step",
          description="torque step about the vertical"),
    param("t_step", "s", "min", 1200.0, null=1200.0, effect="torque_step",
          description="onset of the torque step"),
    param("k_pick", "1", "ppm", 1e-3, effect="pickoff_scale",
          description="scale error of the azimuth pick-off"),
))


class GyrotheodoliteConditions(eqx.Module):
    """Latitude (rad) and the translational vibration: amplitude ``n_m`` (g), angular frequency
    ``omega`` (rad/s), direction ``eps_v`` and offset ``psi0`` (rad)."""

    latitude: jax.Array
    n_m: jax.Array
    omega: jax.Array
    eps_v: jax.Array
    psi0: jax.Array

    @staticmethod
    def from_record(record) -> GyrotheodoliteConditions:
        """The conditions a record's attributes give (``latitude_deg``, ``n_m``, ``omega``)."""
        c = record.conditions
        return GyrotheodoliteConditions.create(float(c.get("latitude_deg", 50.45)),
                                               n_m=float(c.get("n_m", 0.0)),
                                               omega=float(c.get("omega", 0.0)))

    @staticmethod
    def create(latitude_deg: float = 50.45, *, n_m: float = 0.0, omega: float = 0.0,
               eps_v: float = 0.0, psi0: float = 0.0) -> GyrotheodoliteConditions:
        if not -90.0 < float(latitude_deg) < 90.0:
            raise ValueError(f"latitude {latitude_deg} deg is outside (-90, 90); give degrees North")
        if n_m < 0 or omega < 0:
            raise ValueError(f"vibration amplitude n_m={n_m} g and omega={omega} rad/s must be >= 0")
        f = lambda x: jnp.asarray(x, dtype=float)  # noqa: E731
        return GyrotheodoliteConditions(f(latitude_deg * units.DEG), f(n_m), f(omega), f(eps_v),
                                        f(psi0))

    def overloads(self, t):
        """``(n_X, n_Z)`` in g at time ``t`` (s)."""
        s = jnp.sin(self.omega * t)
        return (self.n_m * jnp.cos(self.eps_v + self.psi0) * s,
                self.n_m * jnp.sin(self.eps_v + self.psi0) * s)


class GyrotheodoliteRig(AbstractRig):
    """The 4-state sensing element (1)/(3); time in seconds.

    ``roll_rate_coupling``: include the kinematic ``H alpha_dot gamma`` term (see the module
    docstring). ``vibration_torque``: include the pendulous products ``mgl (gamma n_X + beta n_Z)``
    of (1); switching it off leaves only the mechanism the compensation formula describes.
    """

    CHANNEL_UNITS: ClassVar[dict] = {"alpha": "rad"}

    roll_rate_coupling: bool = eqx.field(static=True, default=True)
    vibration_torque: bool = eqx.field(static=True, default=True)

    @property
    def param_space(self) -> ParameterSpace:
        return _SPACE

    @property
    def channels(self) -> tuple[str, ...]:
        return ("alpha",)

    @property
    def time_scale(self) -> float:
        return 1.0

    def default_params(self, **overrides) -> dict:
        """The assumed parameters (docs/rigs/gyrotheodolite.md), with overrides in SI; validated by
        :meth:`check_params`."""
        return self.check_params(_SPACE.make(overrides))

    @staticmethod
    def check_params(params) -> dict:
        """Raise ``ValueError`` naming the parameter when an inertia, ``H`` or ``mgl`` is not
        positive, a friction is negative, or ``kappa <= -1`` (no north-seeking stiffness).
        Traced values (inside ``jit``/``vmap``) are not checked."""
        for name in POSITIVE + NON_NEGATIVE + ("kappa",):
            v = params[name]
            if isinstance(v, jax.core.Tracer):
                continue
            v = jnp.asarray(v)
            if name in POSITIVE and not bool(jnp.all(v > 0)):
                raise ValueError(f"{name}={v} {_UNITS[name]} must be > 0 ({_DESC[name]})")
            if name in NON_NEGATIVE and not bool(jnp.all(v >= 0)):
                raise ValueError(f"{name}={v} {_UNITS[name]} must be >= 0 ({_DESC[name]})")
            if name == "kappa" and not bool(jnp.all(v > -1)):
                raise ValueError(f"kappa={v} must be > -1: k_alpha = H omega3 cos(phi)(1 + kappa) "
                                 "must stay positive")
        return params

    def initial_state(self, params, conditions):
        """Released at ``(alpha0, alpha_dot0)`` with the tilt at zero (the clamped position)."""
        z = jnp.zeros_like(params["alpha0"])
        return jnp.stack([params["alpha0"], params["alpha_dot0"], z, z])

    @staticmethod
    def azimuth_torque(t, params):
        """Unmodelled torque about the vertical (N m) at time ``t`` (s): the sum of the
        ``tape_torque``, ``torque_ramp``, ``drift_transient`` and ``torque_step`` effects."""
        rise = 0.5 * (1 + jnp.tanh((t - params["t_step"]) / STEP_WIDTH))
        return (params["M_tape"] + params["M_ramp"] * t
                + params["M_tr"] * jnp.exp(-t / params["tau_tr"]) + params["M_step"] * rise)

    @staticmethod
    def k_alpha(params, conditions):
        """Azimuth stiffness ``H omega3 cos(phi) (1 + kappa)`` (N m)."""
        return params["H"] * units.EARTH_RATE * jnp.cos(conditions.latitude) * (1 + params["kappa"])

    def vector_field(self, t, state, params, conditions):
        """Equations (1) with the vibration inputs, the constant ``H omega3 sin(phi)`` input, the
        compensation link's torque on the index offset and the unmodelled azimuth torques."""
        a, ad, b, bd = state
        h, jy, jz, mgl = params["H"], params["J_y"], params["J_z"], params["mgl"]
        d = params["F_KC"] + params["f_alpha"]
        nx, nz = conditions.overloads(t)
        gamma = self.roll_angle(t, params, conditions)
        coupling = h * ad * gamma if self.roll_rate_coupling else 0.0
        k_kc = params["kappa"] * h * units.EARTH_RATE * jnp.cos(conditions.latitude)
        add = (-h * bd - d * ad - self.k_alpha(params, conditions) * a
               - k_kc * params["index_offset"] + self.azimuth_torque(t, params)
               + (mgl * (gamma * nx + b * nz) if self.vibration_torque else 0.0) + coupling) / jy
        bdd = (h * ad - params["f_beta"] * bd - mgl * b + mgl * nx
               + h * units.EARTH_RATE * jnp.sin(conditions.latitude)) / jz
        return jnp.stack([ad, add, bd, bdd])

    def observe(self, t, state, params, conditions):
        """The pick-off: ``(1 + k_pick)(alpha + index_offset)`` (rad)."""
        return (1 + params["k_pick"]) * (state[:1] + params["index_offset"])

    @staticmethod
    def roll_response(params, omega):
        """Complex gain ``gamma / n_Z`` (rad per g) of the assumed roll mode at ``omega`` (rad/s)."""
        mgl = params["mgl"]
        return mgl / (mgl - params["J_x"] * omega**2 + 1j * params["f_gamma"] * omega)

    def roll_angle(self, t, params, conditions):
        """Steady-state roll ``gamma(t)`` (rad) under the vibration of ``conditions``."""
        amp = conditions.n_m * jnp.sin(conditions.eps_v + conditions.psi0)
        phasor = self.roll_response(params, conditions.omega) * amp
        return jnp.imag(phasor * jnp.exp(1j * conditions.omega * t))

    def state_space(self, params, conditions):
        """``(A, C, G, b)`` of (3), (7): $\\dot x = A x + G n_X + b$, $y = C x$, written from the
        equations (tests check ``A`` against the autodiff Jacobian of :meth:`vector_field`)."""
        h, jy, jz, mgl = params["H"], params["J_y"], params["J_z"], params["mgl"]
        d = params["F_KC"] + params["f_alpha"]
        ka = self.k_alpha(params, conditions)
        z, o = jnp.zeros_like(h), jnp.ones_like(h)
        a = jnp.array([[z, o, z, z], [-ka / jy, -d / jy, z, -h / jy], [z, z, z, o],
                       [z, h / jz, -mgl / jz, -params["f_beta"] / jz]])
        c = jnp.array([[1.0, 0.0, 0.0, 0.0]])
        g = jnp.stack([z, z, z, mgl / jz])
        b = jnp.stack([z, z, z, h * units.EARTH_RATE * jnp.sin(conditions.latitude) / jz])
        return a, c, g, b

    def open_loop_coefficients(self, params, conditions):
        """``(a0, a1, a2, a3)`` of ``det(pE - A)`` (docs/rigs/gyrotheodolite.md)."""
        h, jy, jz, mgl, fb = (params[k] for k in ("H", "J_y", "J_z", "mgl", "f_beta"))
        d = params["F_KC"] + params["f_alpha"]
        ka = self.k_alpha(params, conditions)
        jj = jy * jz
        return (ka * mgl / jj, (d * mgl + ka * fb) / jj, (d * fb + jy * mgl + ka * jz + h**2) / jj,
                (d * jz + fb * jy) / jj)

    def observer_gains(self, params, conditions, omega0, *, printed: bool = False):
        """Closed-form observer gains ``K`` for all four poles at ``-omega0`` (docs/rigs/gyrotheodolite.md,
        corrected).

        With ``printed=True`` the source's (dimensionally wrong) ``k3``, ``k4`` are returned, which
        give an unstable observer; kept to demonstrate the correction.
        """
        h, jy, jz, mgl, fb = (params[k] for k in ("H", "J_y", "J_z", "mgl", "f_beta"))
        d = params["F_KC"] + params["f_alpha"]
        ka = self.k_alpha(params, conditions)
        a0, a1, a2, a3 = self.open_loop_coefficients(params, conditions)
        w = jnp.asarray(omega0, dtype=float)
        k1 = 4 * w - d / jy - fb / jz
        k2 = 6 * w**2 - a2 - k1 * a3
        if printed:  # k3 without J_z in the omega0^4 term; k4 without 1/J_z in its later terms
            k3 = (w**4 * jy / mgl - ka - k1 * d - k2 * jy) / h
            k4 = jy / h * (a1 * jz + k1 * (d * fb + h**2 + jy * mgl) / jy + k2 * fb) - 4 * w**3 * jy / h
        else:
            k3 = (w**4 * jy * jz / mgl - ka - k1 * d - k2 * jy) / h
            k4 = jy / h * (a1 + k1 * (d * fb + h**2 + jy * mgl) / (jy * jz) + k2 * fb / jz
                           - 4 * w**3)
        return jnp.stack([k1, k2, k3, k4])
