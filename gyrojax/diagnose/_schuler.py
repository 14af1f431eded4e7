"""The platform INS Schuler test as the diagnosis sees it (``--rig schuler``, design D5).

Nominal model: the 12 errors the test identifies (gyro drifts, torquer scales, accelerometer
biases and scales, initial tilts and azimuth error), fitted on the train split by the iterated
Gauss-Newton of :func:`gyrojax.estimate.schuler.fit_schuler` (its weak prior of docs/rigs/schuler.md only
regularises; the data outweigh it by orders of magnitude). Catalogue: the rig's unmodelled-effect
groups (:data:`gyrojax.models.schuler.EFFECT_NAMES`) — gyro drift ramp, warm-up transient (decay
time on a grid), drift step (onset on a grid), accelerometer bias ramp, g-sensitive drift,
accelerometer cross-axis and vertical-axis tilts — each entering the nonlinear model (S7).

Residuals are the test's own (docs/rigs/schuler.md): velocity differences and the attitude residual (S12) of
the measured against the modelled rotation since t0, whitened per channel; so ``predict`` returns
``y - residual`` (the record's frame), and every Jacobian is the derivative of the modelled
channels in those residual coordinates, by forward-mode autodiff through diffrax.
Held-out split: time-ordered, the last ``holdout`` of the record.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..estimate import convergence_note
from ..estimate.schuler import (
    THETA_NAMES,
    _fit_prior,
    check_rotation_units,
    fit_schuler,
    schuler_residuals,
)
from ..models.schuler import SchulerConditions, SchulerRig
from ..record import BenchRecord
from ..simulate import integrate
from ._problem import AbstractGapProblem
from ._signatures import Signature, check_effects, onset_grid

__all__ = ["SchulerProblem", "SCHULER_LIBRARY"]

# effect -> (family, grid parameter or None); prior scales are the rig's Param.scale
SCHULER_LIBRARY = {
    "drift_ramp": ("trend", None),
    "drift_transient": ("transient", "tau_tr"),
    "drift_step": ("step", "t_step"),
    "accelerometer_ramp": ("trend", None),
    "g_sensitivity": ("g", None),
    "accelerometer_cross_axis": ("mounting", None),
    "accelerometer_tilt": ("mounting", None),
}
CHANNELS = ("V1", "V2", "rot1", "rot2", "rot3")
TRANSIENT_TIMES_H = tuple(float(x) for x in np.geomspace(0.25, 3.0, 8))
DEFAULT_NOISE = (0.05, 0.05, units.ARCMIN, units.ARCMIN, units.ARCMIN)  # docs/rigs/schuler.md
_NOMINAL_MAX_ITER = 40  # optimistix steps per pass: evaluations, rejected trials included
_REFIT_MAX_ITER = 150  # a large unmodelled step: a trial rejected twice for each step taken


@eqx.filter_jit
def _model_jacobian(rig, cond, ts, y, base, names, scales, weights):
    """d(modelled channels)/d(params[names] / scales), whitened, rows (time, channel)."""
    def resid(u):
        p = base | {k: base[k] + u[i] * scales[i] for i, k in enumerate(names)}
        r = schuler_residuals(rig, cond, ts, y, p, adjoint=diffrax.ForwardMode())
        return (r * weights).reshape(-1)

    return -jax.jacfwd(resid)(jnp.zeros(len(names)))


@eqx.filter_jit
def _residual(rig, cond, ts, y, params):
    return schuler_residuals(rig, cond, ts, y, params)


class SchulerProblem(AbstractGapProblem):
    """One Schuler-test record split by time into train / held-out."""

    NOISE_UNITS = {"V": (1.0, "m/s"), "": (units.ARCMIN, "arcmin")}

    @classmethod
    def catalogue(cls, **options) -> dict:
        """The catalogue: effect name -> family."""
        return {k: v[0] for k, v in SCHULER_LIBRARY.items()}

    def __init__(self, record: BenchRecord, *, holdout: float = 0.25, noise_std=None,
                 effects=None):
        check_effects(effects, SCHULER_LIBRARY, "schuler")
        if tuple(record.channels) != CHANNELS:
            raise ValueError(f"channels {tuple(record.channels)}: the Schuler diagnosis needs "
                             f"{CHANNELS} (model velocities in m/s, platform rotation since t0 "
                             "in rad)")
        self.record = record
        self.rig = SchulerRig()
        self.space = self.rig.param_space
        self.conditions = SchulerConditions.from_record(record)
        self.t = np.asarray(record.t, float)
        self.y = np.asarray(record.y, float)
        check_rotation_units(self.y)
        self.channels = CHANNELS
        n = len(self.t)
        self.n_train = n - int(round(holdout * n)) if holdout > 0 else n
        period = float(self.conditions.schuler_period)
        if self.t[self.n_train - 1] - self.t[0] < 0.5 * period:
            raise ValueError(f"the train part spans {self.t[self.n_train - 1] - self.t[0]:.0f} s, "
                             f"less than half a Schuler period ({0.5 * period:.0f} s): record "
                             "1-4 periods or lower --holdout")
        self.noise_std = noise_std
        self.fit_noise = np.asarray(noise_std if noise_std is not None else DEFAULT_NOISE, float)
        self.effects = tuple(effects) if effects is not None else tuple(SCHULER_LIBRARY)
        sp = self.space
        self.nominal_names = THETA_NAMES
        self.nominal_scales = sp.scales(self.nominal_names)
        self.nominal_units = tuple(sp[k].display_unit for k in self.nominal_names)
        self.nominal_display_scales = self.nominal_scales / np.array(
            [sp[k].display_factor for k in self.nominal_names])
        self.effect_names = {e: tuple(k for k in sp.effect_names(e)
                                      if k != SCHULER_LIBRARY[e][1]) for e in self.effects}
        # one onset every 5 % of the record over the train span (14 on D5)
        self.step_grid_s = tuple(float(x) for x in onset_grid(self.t, self.n_train))
        self.lines = {"Schuler period": period, "half Schuler period": period / 2}
        self.notes: list[str] = []

    # -- nominal fit -----------------------------------------------------------------------
    def fit_nominal(self) -> dict:
        n = self.n_train
        s = self.fit_noise
        est = fit_schuler(self.rig, self.t[:n], self.y[:n], self.conditions, sigma_v=float(s[0]),
                          sigma_theta=float(np.mean(s[2:])), max_iter=_NOMINAL_MAX_ITER)
        self._note(est.note("the nominal fit"))
        return dict(zip(THETA_NAMES, est.values, strict=True))

    def _note(self, note):
        if note is not None:
            self.notes.append(note)

    def predict(self, params: dict, extra=None) -> np.ndarray:
        """``y - residual`` over the whole record (the residual is the test's, docs/rigs/schuler.md)."""
        r = np.asarray(_residual(self.rig, self.conditions, jnp.asarray(self.t),
                                 jnp.asarray(self.y), params))
        return self.y - r

    # -- Jacobians -------------------------------------------------------------------------
    def _grid(self, e):
        if e == "drift_transient":
            return TRANSIENT_TIMES_H, "decay time", "h", [h * 3600 for h in TRANSIENT_TIMES_H]
        if e == "drift_step":
            return (tuple(x / 3600 for x in self.step_grid_s), "onset", "h", self.step_grid_s)
        return (), "", "", [None]

    def jacobians(self, params, sigma, *, conditions=None, t=None):
        """Whitened Jacobians over ``t`` (default the record's times): nominal (per Param.scale)
        and one :class:`Signature` per catalogued effect (per prior scale, grid slices). Under
        another design the model's own prediction stands in for the record."""
        sp = self.space
        cond = self.conditions if conditions is None else conditions
        base = sp.make() | {k: jnp.asarray(params[k]) for k in THETA_NAMES}
        if t is None and conditions is None:
            ts, y = self.t, self.y
        else:
            ts = self.t if t is None else np.asarray(t, float)
            y = np.asarray(integrate(self.rig, base, cond, jnp.asarray(ts)))
        ts, y = jnp.asarray(ts), jnp.asarray(y)
        w = jnp.asarray(1.0 / np.asarray(sigma, float))
        # one compiled Jacobian over every name: the k-th call sets each gridded effect to its
        # k-th grid value (the last one past its grid's end); a gridded effect's columns do not
        # depend on another effect's grid value, since every effect amplitude is 0 here
        names = THETA_NAMES + tuple(k for e in self.effects for k in self.effect_names[e])
        col = {k: i for i, k in enumerate(names)}
        grids = {SCHULER_LIBRARY[e][1]: self._grid(e)[3] for e in self.effects
                 if SCHULER_LIBRARY[e][1] is not None}
        jacs = [np.asarray(_model_jacobian(
            self.rig, cond, ts, y,
            base | {g: jnp.asarray(float(v[min(k, len(v) - 1)])) for g, v in grids.items()},
            names, jnp.asarray(sp.scales(names)), w))
            for k in range(max((len(v) for v in grids.values()), default=1))]
        jn = jacs[0][:, : len(THETA_NAMES)]
        sigs = []
        for e in self.effects:
            en = self.effect_names[e]
            grid, gname, gunit, gvals = self._grid(e)
            cols = [col[k] for k in en]
            slices = [jacs[k][:, cols] for k in range(len(gvals))]
            sigs.append(Signature(e, SCHULER_LIBRARY[e][0], en,
                                  tuple(sp[k].display_unit for k in en),
                                  sp.scales(en) / np.array([sp[k].display_factor for k in en]),
                                  np.stack(slices), grid, gname, gunit))
        return jn, sigs

    # -- refits ----------------------------------------------------------------------------
    def refit(self, params0: dict, sig_choices: list[tuple[Signature, int]], sigma):
        """Gauss-Newton on the nonlinear model over the 12 errors plus the chosen effects' terms
        (grid values fixed at the screened best), on the train split; returns (``y - residual``
        over the whole record, effect coefficients in display units, params)."""
        sp = self.space
        # one superset of names for every refit, the effects not chosen masked (held at 0), and
        # every grid parameter fixed (at the chosen value, else its first): one compiled solver
        names = THETA_NAMES + tuple(k for e in self.effects for k in self.effect_names[e])
        chosen = set(THETA_NAMES) | {k for sig, _ in sig_choices for k in sig.names}
        fixed = {}
        for e in self.effects:
            gpar = SCHULER_LIBRARY[e][1]
            if gpar is not None:
                g = next((g for sig, g in sig_choices if sig.name == e), 0)
                fixed[gpar] = jnp.asarray(float(self._grid(e)[3][g]))
        scale = jnp.asarray(sp.scales(names))
        u0 = jnp.asarray([float(params0.get(k, 0.0)) for k in names]) / scale
        n = self.n_train
        gn = _fit_prior(
            self.rig, self.conditions, self.t[:n], self.y[:n], 1.0 / np.asarray(sigma, float),
            scale, u0, _REFIT_MAX_ITER, 1e-4, names, fixed, [float(k in chosen) for k in names])
        self._note(convergence_note(
            gn.solution, "the refit with " + " + ".join(s.name for s, _ in sig_choices)))
        p = fixed | dict(zip(names, gn.theta, strict=True))
        coeffs = {k: float(sp[k].to_display(p[k])) for sig, _ in sig_choices for k in sig.names}
        return self.predict(p), coeffs, p

    # -- designs for the advisor -----------------------------------------------------------
    def designs(self):
        """Candidate tests: the record twice as long, the other sign of V2', the start azimuth
        turned by 90 deg, and twice the initial velocities."""
        c = self.conditions
        lat = float(c.latitude) / units.DEG
        a0 = float(c.a0) / units.DEG
        v1, v2 = float(c.v10), float(c.v20)
        dt = (self.t[-1] - self.t[0]) / (len(self.t) - 1)
        mk = lambda **kw: SchulerConditions.create(  # noqa: E731
            lat, g=float(c.g), **({"v10": v1, "v20": v2, "azimuth0_deg": a0} | kw))
        return [
            (f"{2 * (self.t[-1] - self.t[0]) / 60:.0f} min record", c,
             self.t[0] + dt * np.arange(2 * len(self.t) - 1)),
            (f"initial velocities ({v1:g}, {-v2:g}) m/s", mk(v20=-v2), self.t),
            (f"start azimuth {a0 + 90:g} deg", mk(azimuth0_deg=a0 + 90), self.t),
            (f"initial velocities ({2 * v1:g}, {2 * v2:g}) m/s", mk(v10=2 * v1, v20=2 * v2),
             self.t),
        ]

    def display_nominal(self, params) -> dict:
        return {k: float(self.space[k].to_display(params[k])) for k in THETA_NAMES}
