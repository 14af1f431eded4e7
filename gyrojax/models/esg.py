"""Non-contact (electrostatic) gyro in a two-axis gyrostabilizer — docs/rigs/esg.md.

Conventions (docs/rigs/esg.md): normalized time ``tau = U t`` (``U`` = Earth's sidereal rate, so one
sidereal day is ``2 pi``); drift coefficients ``m`` are normalized torques, ``drift[deg/h] =
15.0411 m``; angles in rad. Frames: ``eta`` geographic ENU; ``zeta`` the stabilizer base
(``C_eta_zeta = R3(chi3) R2(chi2) R1(chi1)``, Table 1 gives the nominal ``chi`` of the four
mounting schemes); ``x`` the platform (``C_zeta_x = R1(alpha1) R2(alpha2)``). State: the gimbal angles
``alpha = (alpha1, alpha2)``; they are also the measured channels.

Parameters (names as in docs/rigs/esg.md):

| group | names | unit (report) |
|---|---|---|
| nominal | ``alpha10 alpha20`` (first-sample angles), ``m11 ... mc2`` | rad (deg), 1 (deg/h) |
| ``rotor_tilt`` | ``theta1 theta2`` (spin-axis non-perpendicularity) | rad (arcsec) |
| ``base_misalignment`` | ``eps*`` or ``dchi1..3`` by ``base_param`` | rad (arcsec) |
| ``drift_transient`` | ``dm11_0 ... dmc2_0`` (``m0 - m*``), ``k_tr`` (law 7.4) | 1 (deg/h), 1/tau (1/h) |
| ``drift_ramp`` | ``rmc1 rmc2``: case-fixed drift growing linearly from t = 0 | 1/tau (deg/h/h) |
| ``drift_step`` | ``smc1 smc2``: case-fixed drift step at ``t_step`` (re-levitation) | 1 (deg/h), tau (h) |

``base_param`` chooses how the base misalignment is parametrized:

- ``"eps"`` (default): ``eps = u_zeta x dchi`` constrained normal to ``u`` (docs/rigs/esg.md): two free
  components, the third (``eps_dependent``) solved from ``eps . u = 0``; the base is rotated exactly
  by ``dchi = eps x u``.
- ``"eps_free"``: the paper's (6.9), all three ``eps`` free and acting additively on the Earth-rate
  vector (``u + eps``, ``g`` unchanged): for observability studies of the uncostrained form.
- ``"rotvec"``: ``dchi`` a small rotation vector in base components (exact rotation of ``u`` and ``g``).
- ``"euler"``: ``dchi`` Euler-angle increments, ``chi = chi* + dchi`` (the reading behind Tables 2-3).

``order="first"`` gives the paper's first-order model (3.1): the exact model linearized in the
mounting errors (``theta`` and the base parameters) with the ``O(m dchi)`` effect on ``g`` dropped.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..earth import earth_rate_unit_enu, gravity_unit_enu
from ..params import Param, ParameterSpace, param
from ..rotations import euler321_to_matrix, rotvec_to_matrix, sincos, skew
from ._base import AbstractRig

__all__ = ["ESGRig", "ESGConditions", "SCHEMES", "scheme_angles", "DRIFT_NAMES", "check_angle_units"]

U = units.EARTH_RATE
DRIFT_NAMES = ("m11", "m12", "m21", "m22", "mc1", "mc2")
_M_FACTOR = 1.0 / units.EARTH_RATE_DEG_PER_HOUR  # normalized m per deg/h
SCHEMES = ("polar", "equatorial", "horizontal", "vertical")


def scheme_angles(scheme: str, latitude):
    """Nominal base angles ``(chi1, chi2, chi3)`` of Table 1 (rad) for a scheme name."""
    half = jnp.pi / 2
    lat = jnp.asarray(latitude, dtype=float)
    table = {
        "polar": (0.0, lat - half, -half),
        "equatorial": (0.0, -lat, half),
        "horizontal": (0.0, -half, -half),
        "vertical": (0.0, 0.0, 0.0),
    }
    if scheme not in table:
        raise ValueError(f"unknown mounting scheme {scheme!r}; use one of {', '.join(SCHEMES)}")
    return jnp.stack([jnp.asarray(a, dtype=float) + 0.0 * lat for a in table[scheme]])


class ESGConditions(eqx.Module):
    """Test conditions of the ESG rig: latitude (rad) and nominal base angles ``chi`` (rad).

    Both are arrays, so conditions batch with ``vmap`` (e.g. over the four schemes).
    """

    latitude: jax.Array
    chi: jax.Array

    @staticmethod
    def create(scheme: str, latitude_deg: float) -> ESGConditions:
        """The conditions of mounting ``scheme`` (polar, equatorial, horizontal, vertical) at
        ``latitude_deg`` (deg North)."""
        lat = jnp.asarray(latitude_deg * units.DEG, dtype=float)
        if not (-90.0 < float(latitude_deg) < 90.0):
            raise ValueError(f"latitude {latitude_deg} deg is outside (-90, 90); give --latitude "
                             "in degrees North")
        return ESGConditions(lat, scheme_angles(scheme, lat))

    # the paper's name for the same constructor
    from_scheme = create

    @staticmethod
    def from_record(record) -> ESGConditions:
        """The conditions a record's attributes give (``scheme``, ``latitude_deg``)."""
        c = record.conditions
        missing = [k for k in ("latitude_deg", "scheme") if k not in c]
        if missing:
            raise ValueError(f"record lacks the condition(s) {missing}; give --latitude DEG and "
                             "--scheme NAME (or store them as NetCDF attributes)")
        return ESGConditions.create(str(c["scheme"]), float(c["latitude_deg"]))

    def base_vectors(self):
        """Nominal ``u_zeta`` (unit Earth rate) and ``g_zeta`` (unit gravity) in base components."""
        c = euler321_to_matrix(self.chi)
        return c.T @ earth_rate_unit_enu(self.latitude), c.T @ gravity_unit_enu()


def _default_dependent(u_zeta) -> int:
    """Index of the eps component solved from eps . u = 0: the one with the largest |u_i|."""
    return int(np.argmax(np.abs(np.asarray(u_zeta))))


class ESGRig(AbstractRig):
    """The non-contact gyro in a two-axis gyrostabilizer (docs/rigs/esg.md).

    **Arguments:**
    - `base_param`: ``"eps"`` | ``"eps_free"`` | ``"rotvec"`` | ``"euler"`` (see module docstring).
    - `eps_dependent`: for ``base_param="eps"``, the index (0, 1, 2) of the eps component fixed by
      ``eps . u = 0``; build with :meth:`for_scheme` to choose it from the scheme.
    - `order`: ``"exact"`` (model 5.1) or ``"first"`` (model 3.1).
    """

    CHANNEL_UNITS: ClassVar[dict] = {"alpha": "rad"}

    base_param: Literal["eps", "eps_free", "rotvec", "euler"] = eqx.field(static=True,
                                                                        default="eps")
    eps_dependent: int = eqx.field(static=True, default=2)
    order: Literal["exact", "first"] = eqx.field(static=True, default="exact")

    def __check_init__(self):
        if self.base_param not in ("eps", "eps_free", "rotvec", "euler"):
            raise ValueError(f"base_param={self.base_param!r}; use 'eps', 'eps_free', 'rotvec' "
                             "or 'euler'")
        if self.order not in ("exact", "first"):
            raise ValueError(f"order={self.order!r}; use 'exact' or 'first'")
        if self.eps_dependent not in (0, 1, 2):
            raise ValueError(f"eps_dependent={self.eps_dependent}; use 0, 1 or 2")

    @staticmethod
    def for_scheme(scheme: str, latitude_deg: float = 55.75, **kwargs) -> ESGRig:
        """A rig whose constrained ``eps`` drops the component along ``u`` for this scheme."""
        u, _ = ESGConditions.from_scheme(scheme, latitude_deg).base_vectors()
        kwargs.setdefault("eps_dependent", _default_dependent(u))
        return ESGRig(**kwargs)

    # -- parameters ------------------------------------------------------------------------
    @property
    def base_names(self) -> tuple[str, ...]:
        if self.base_param == "eps":
            return tuple(f"eps{i + 1}" for i in range(3) if i != self.eps_dependent)
        if self.base_param == "eps_free":
            return ("eps1", "eps2", "eps3")
        return ("dchi1", "dchi2", "dchi3")

    @property
    def param_space(self) -> ParameterSpace:
        return _param_space(self.base_param, self.base_names)

    @property
    def channels(self) -> tuple[str, ...]:
        return ("alpha1", "alpha2")

    @property
    def time_scale(self) -> float:
        return U

    # -- physics ---------------------------------------------------------------------------
    def _eps_vector(self, params, u_zeta):
        names = self.base_names
        if self.base_param == "eps_free":
            return jnp.stack([params[n] for n in names])
        comps = [None, None, None]
        free = [i for i in range(3) if i != self.eps_dependent]
        for i, n in zip(free, names):
            comps[i] = params[n]
        d = self.eps_dependent
        comps[d] = -sum(u_zeta[i] * comps[i] for i in free) / u_zeta[d]
        return jnp.stack(comps)

    def actual_base_vectors(self, params, conditions, *, rotate_gravity: bool = True):
        """``u_zeta`` and ``g_zeta`` in the actual (misaligned) base frame."""
        u0, g0 = conditions.base_vectors()
        if self.base_param == "euler":
            dchi = jnp.stack([params[n] for n in self.base_names])
            c = euler321_to_matrix(conditions.chi + dchi)
            u, g = c.T @ earth_rate_unit_enu(conditions.latitude), c.T @ gravity_unit_enu()
            return (u, g) if rotate_gravity else (u, g0)
        if self.base_param == "eps_free":
            return u0 + self._eps_vector(params, u0), g0
        if self.base_param == "eps":
            dchi = jnp.cross(self._eps_vector(params, u0), u0)
        else:
            dchi = jnp.stack([params[n] for n in self.base_names])
        r = rotvec_to_matrix(dchi)
        return r.T @ u0, (r.T @ g0 if rotate_gravity else g0)

    def jump_times(self, params, conditions):
        """The drift step's onset(s) ``t_step`` (internal time)."""
        return jnp.reshape(jnp.asarray(params["t_step"], dtype=float), (-1,))

    def _drift(self, params, tau):
        """The drift coefficients at internal time ``tau``. The transient's amplitudes with
        ``k_tr``, and the step's sizes with ``t_step``, may also be vectors of one length: a sum
        of transients (steps), one per entry (the diagnosis linearizes at every grid value of
        the decay time and the onset in one solve)."""
        decay = jnp.exp(-params["k_tr"] * tau)
        m = [params[n] + jnp.sum(params[f"d{n}_0"] * decay) for n in DRIFT_NAMES]
        # drift_ramp / drift_step on the case-fixed drifts; like the transient, they run from t = 0
        on = jnp.where(tau >= params["t_step"], 1.0, 0.0)
        for i, n in enumerate(("mc1", "mc2")):
            m[4 + i] = m[4 + i] + params[f"r{n}"] * tau + jnp.sum(params[f"s{n}"] * on)
        return m

    def _exact_rates(self, alpha, m, theta, u_zeta, g_zeta):
        # Written on scalar components, not 3-vectors: under vmap every operation is then one
        # contiguous loop over the batch. With (batch, 3) arrays (cross products, 3x3 rotation
        # matrices) XLA's CPU backend works along a minor axis of length 3 and the batched
        # solve ran 1.6x slower (notes: "Speed of the ESG simulation").
        a1, a2 = alpha[0], alpha[1]
        (s1, c1), (s2, c2) = sincos(a1), sincos(a2)

        def cross(a, b):
            return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                    a[0] * b[1] - a[1] * b[0])

        def dot(a, b):
            return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

        u, g = (_platform_components(s1, c1, s2, c2, v) for v in (u_zeta, g_zeta))
        e_vec = rotvec_to_matrix(jnp.stack([theta[0], theta[1], jnp.zeros_like(theta[0])]))[:, 2]
        e = (e_vec[0], e_vec[1], e_vec[2])
        m11, m12, m21, m22, mc1, mc2 = m
        cosg = -dot(g, e)
        eg = cross(e, g)
        eeg = cross(e, eg)
        k1, k2 = m11 - 2 * m12 * cosg, m21 - 2 * m22 * cosg
        torque = tuple(k1 * eg[i] + k2 * eeg[i] + c for i, c in enumerate((mc1, mc2, 0.0)))
        te = dot(torque, e)
        ue = cross(u, e)
        v1, v2 = (torque[i] - te * e[i] - ue[i] for i in (0, 1))
        a1dot = v2 / (s2 * e[0] - c2 * e[2])
        a2dot = (v1 + a1dot * s2 * e[1]) / e[2]
        return jnp.stack([a1dot, a2dot])

    def initial_state(self, params, conditions):
        return jnp.stack([params["alpha10"], params["alpha20"]])

    def vector_field(self, t, state, params, conditions):
        """$d\\alpha/d\\tau$ of the exact precessional model (docs/rigs/esg.md) or of (3.1)."""
        m = self._drift(params, t)
        theta = jnp.stack([params["theta1"], params["theta2"]])
        if self.order == "exact":
            u, g = self.actual_base_vectors(params, conditions)
            return self._exact_rates(state, m, theta, u, g)
        # first order in the mounting errors (3.1): tangent of the exact model at zero error,
        # with the O(m dchi) effect of dchi on g dropped (gravity stays nominal).
        _, g0 = conditions.base_vectors()
        errs = {n: params[n] for n in ("theta1", "theta2", *self.base_names)}

        def rates(e):
            p = dict(params) | e
            u, _ = self.actual_base_vectors(p, conditions, rotate_gravity=False)
            return self._exact_rates(state, m, jnp.stack([p["theta1"], p["theta2"]]), u, g0)

        zeros = jax.tree.map(jnp.zeros_like, errs)
        f0, df = jax.jvp(rates, (zeros,), (errs,))
        return f0 + df

    def observe(self, t, state, params, conditions):
        return state

    # -- the linear-in-parameters form (6.1) used by regression and the Kalman filter ---------
    @property
    def drift_names(self) -> tuple[str, ...]:
        """The drift coefficients; ``d{name}_0`` are their start-up transients (law 7.4)."""
        return DRIFT_NAMES

    @property
    def regression_names(self) -> tuple[str, ...]:
        """Parameters ``p`` of the linear model (6.1): drift, rotor tilt, base misalignment."""
        return (*DRIFT_NAMES, "theta1", "theta2", *self.base_names)

    def regression_terms(self, alpha, conditions):
        """``c(alpha)`` (2,) and ``F(alpha)`` (2, k) of $\\alpha' = c + F p$ (docs/rigs/esg.md (6.7), (6.10)).

        Written out from the equations (with the corrected ``f18``) rather than differentiated; tests
        check it against the autodiff tangent of the exact model. ``alpha`` may carry leading batch
        axes. The stacked form of :meth:`regression_columns`.
        """
        c, f1, f2 = self.regression_columns(alpha, conditions)
        zero = jnp.zeros_like(c[0])
        f = jnp.stack([jnp.stack([zero if x is None else x for x in row], axis=-1)
                       for row in (f1, f2)], axis=-2)
        return jnp.stack(c, axis=-1), f

    def regression_columns(self, alpha, conditions):
        """:meth:`regression_terms` as lists of arrays shaped like ``alpha[..., 0]``: ``(c1, c2)``,
        then the ``k`` columns of the first row of ``F``, then of the second; ``None`` where an
        entry is zero whatever the angles (e.g. ``mc1`` in the first row), so the regression can
        factor each row's design on its own nonzero columns.

        The hot path of the integral regression. The trigonometry of the measured angles is
        computed once and stored (XLA would otherwise re-evaluate it inside every column's fused
        loop, and a stacking concatenate evaluates every operand per element); each column is then
        a few multiplications of stored arrays.
        """
        u_zeta, g_zeta = conditions.base_vectors()
        a1, a2 = alpha[..., 0], alpha[..., 1]
        s2, c2 = sincos(a2)
        sec = 1.0 / c2
        trig = (*sincos(a1), s2, c2, sec, s2 * sec)
        store = jnp.zeros((len(trig), *a1.shape), a1.dtype)
        for i, v in enumerate(trig):  # in-place updates: one loop per value, nothing repeated
            store = store.at[i].set(v)
        s1, c1, s2, c2, sec, t2 = store

        u1, u2, u3 = _platform_components(s1, c1, s2, c2, u_zeta)
        g1, g2, g3 = _platform_components(s1, c1, s2, c2, g_zeta)
        o = jnp.ones_like(a1)
        row1 = [-g1 * sec, -2 * g1 * g3 * sec, g2 * sec, 2 * g2 * g3 * sec, None, -sec,
                None, (u3 - u1 * t2) * sec]
        row2 = [-g2, -2 * g2 * g3, -g1, -2 * g1 * g3, o, None, u1 * t2 - u3, None]
        # eps columns (6.10): -x1/cos(alpha2) and -x2 in base components
        e1 = (-o, -s1 * t2, c1 * t2)
        e2 = (None, -c1, -s1)
        if self.base_param == "eps_free":
            b1, b2 = list(e1), list(e2)
        elif self.base_param == "eps":
            d = self.eps_dependent
            free = [i for i in range(3) if i != d]
            # eps_d = -(sum_i u_i eps_i) / u_d  ->  column_i - u_i / u_d column_d
            b1 = [_combine(e1, {i: 1.0, d: -u_zeta[i] / u_zeta[d]}) for i in free]
            b2 = [_combine(e2, {i: 1.0, d: -u_zeta[i] / u_zeta[d]}) for i in free]
        else:
            # eps = u x dchi = skew(u) dchi  (rotation vector); Euler increments through J
            jac = skew(u_zeta)
            if self.base_param == "euler":
                c1x, s1x = jnp.cos(conditions.chi[0]), jnp.sin(conditions.chi[0])
                c2x, s2x = jnp.cos(conditions.chi[1]), jnp.sin(conditions.chi[1])
                jac = jac @ jnp.array([[1.0, 0.0, -s2x], [0.0, c1x, s1x * c2x],
                                       [0.0, -s1x, c1x * c2x]])
            b1 = [_combine(e1, {i: jac[i, j] for i in range(3)}) for j in range(3)]
            b2 = [_combine(e2, {i: jac[i, j] for i in range(3)}) for j in range(3)]
        return (-u1 * sec, -u2), row1 + b1, row2 + b2


# the gimbals follow the Earth's rotation plus the drifts (a few deg/h at most, a fraction of the
# Earth rate): a record whose angles move faster than this over its span is not in s and rad
# (a day's polar record with t in hours moves at 36 Earth rates; a cell of 1e300 rad, faster)
MAX_GIMBAL_RATE = 10.0 * units.EARTH_RATE  # rad/s


def check_angle_units(y, t=None):
    """Refuse gimbal angles ``y`` ``(n, 2)`` that cannot be radians over times ``t`` (s) that
    cannot be seconds.

    The model's ``alpha2`` lies within +-pi/2 (the gimbal lock, docs/rigs/esg.md), so a
    record reaching beyond it is in other units (a 24-h record in deg or arcsec: the fits end
    in inf/NaN, "not converged"); ``alpha1`` turns freely (720 deg in two days on the
    equatorial scheme), but no faster than the Earth turns plus the drifts: with ``t``, the
    range of either angle over the record's span is at most :data:`MAX_GIMBAL_RATE` (10 times
    the Earth rate). **Raises:** `ValueError` naming the channel, the rate and the units to
    check."""
    from ..io import check_radians

    y = np.asarray(y, float)
    check_radians(y[:, 1:2], ("alpha2",), np.pi / 2, "the gimbal lock",
                  convert=("alpha1", "alpha2"))
    if t is None:
        return
    span = float(np.asarray(t)[-1] - np.asarray(t)[0])
    rate = np.ptp(y, axis=0) / span
    j = int(np.argmax(rate))
    if rate[j] > MAX_GIMBAL_RATE:
        raise ValueError(
            f"the record's alpha{j + 1} moves {np.ptp(y[:, j]):.3g} rad in {span:.3g} s, "
            f"{rate[j] / units.EARTH_RATE:.3g} times the Earth rate: a gyrostabilizer's gimbals "
            "follow the Earth's rotation, so the record is not in s and rad; check t's unit "
            "(s: a record in hours moves 3600x too fast) and the angles' (rad), and that no "
            "cell is corrupt")


def _combine(columns, coefficients):
    """``sum_i coefficients[i] * columns[i]`` over the entries that are not ``None`` (a
    structural zero); ``None`` when every term is."""
    terms = [coefficients[i] * columns[i] for i in coefficients if columns[i] is not None]
    return sum(terms[1:], terms[0]) if terms else None


def _platform_components(s1, c1, s2, c2, v):
    """``x_i . v`` of a base-frame vector ``v`` on the platform axes x1 = (c2, s1 s2, -c1 s2),
    x2 = (0, c1, s1), x3 = (s2, -s1 c2, c1 c2) (docs/rigs/esg.md), from the sines and cosines of the
    gimbal angles: three arrays shaped like the angles."""
    return (c2 * v[0] + s1 * s2 * v[1] - c1 * s2 * v[2], c1 * v[1] + s1 * v[2],
            s2 * v[0] - s1 * c2 * v[1] + c1 * c2 * v[2])


def _drift_param(name, effect=None, scale=0.01, description=""):
    return Param(name=name, unit="1", display_unit="deg/h", display_factor=_M_FACTOR, scale=scale,
                 null=0.0, effect=effect, description=description)


_DRIFT_DESC = {
    "m11": "conservative drift, first harmonic", "m12": "conservative drift, second harmonic",
    "m21": "non-conservative drift, first harmonic", "m22": "non-conservative drift, 2nd harmonic",
    "mc1": "case-fixed drift about platform axis x1", "mc2": "case-fixed drift about axis x2",
}


def _param_space(base_param: str, base_names: tuple[str, ...]) -> ParameterSpace:
    ps = [
        param("alpha10", "rad", "deg", units.ARCMIN, description="alpha1 at the first sample"),
        param("alpha20", "rad", "deg", units.ARCMIN, description="alpha2 at the first sample"),
        *[_drift_param(n, description=_DRIFT_DESC[n]) for n in DRIFT_NAMES],
        param("theta1", "rad", "arcsec", 10 * units.ARCMIN, effect="rotor_tilt",
              description="spin-axis tilt about platform x1"),
        param("theta2", "rad", "arcsec", 10 * units.ARCMIN, effect="rotor_tilt",
              description="spin-axis tilt about platform x2"),
    ]
    what = {"eps": "eps = u x dchi (normal to u)", "eps_free": "eps (Earth-rate error, free)",
            "rotvec": "dchi base rotation vector", "euler": "dchi Euler-angle increment"}[base_param]
    ps += [param(n, "rad", "arcsec", units.ARCMIN, effect="base_misalignment",
                 description=f"{what}, component {n[-1]}") for n in base_names]
    ps += [_drift_param(f"d{n}_0", "drift_transient", 0.02, f"start-up excess of {n} (m0 - m*)")
           for n in DRIFT_NAMES]
    ps.append(Param(name="k_tr", unit="1/tau", display_unit="1/h",
                    display_factor=1.0 / (U * units.HOUR), scale=1.0, null=1.0,
                    effect="drift_transient", description="decay rate of the start-up transient"))
    ramp = _M_FACTOR / (U * units.HOUR)  # normalized m per tau, for 1 deg/h per hour
    ps += [Param(name=f"r{n}", unit="1/tau", display_unit="deg/h/h", display_factor=ramp,
                 scale=0.002 * ramp, null=0.0, effect="drift_ramp",
                 description=f"linear growth of {n} from t = 0") for n in ("mc1", "mc2")]
    ps += [_drift_param(f"s{n}", "drift_step", 0.005, f"step of {n} at t_step")
           for n in ("mc1", "mc2")]
    ps.append(Param(name="t_step", unit="tau", display_unit="h", display_factor=U * units.HOUR,
                    scale=U * units.HOUR, null=np.pi, effect="drift_step",
                    description="onset of the drift step (grid parameter)"))
    return ParameterSpace(tuple(ps))
