"""The gyrotheodolite north-seeking run as the diagnosis sees it (``--rig gyrotheodolite``).

Record: the azimuth pick-off ``alpha`` (rad) of a sensing element released near the meridian,
sampled over several north-seeking periods. Nominal model: the 4-state rig (1) of
:class:`gyrojax.models.GyrotheodoliteRig` with the physical constants of spec §8 frozen and five
test parameters free - the index offset (the azimuth the instrument measures), the release state
``alpha0``, ``alpha_dot0``, and the slow mode's stiffness and damping through ``kappa`` and
``F_KC`` - fitted by Gauss-Newton through diffrax (``Kvaerno5``: the 8.7 Hz nutation mode makes
the rig stiff for explicit solvers). Catalogue: the rig's effect groups, torques about the vertical
(``tape_torque``, ``torque_ramp``, ``drift_transient`` with its decay time on a grid,
``torque_step`` with its onset on a grid) and the pick-off scale ``pickoff_scale``.

Structure the diagnosis must find: a constant torque ``M`` about the vertical shifts the
equilibrium by ``M / (H omega3 cos phi)``, exactly as the index offset does, and its release
transient is the release state's, so ``tape_torque`` has no signature in one run (alias
``index_offset`` +1/k0, ``alpha0`` -1/k0 per N m); no change of the compensation gain separates it
(the link acts on the pick-off, so the forcing stays ``M + k0 A``), a second run at another rotor
momentum does. The pick-off scale is absorbed by the offset and release state except through
the millisecond release of the tilt: practically confounded under every design here.

Designs for the advisor are tuples of runs ``(label, H factor, added kappa)`` sharing the index
offset, the stiffness and damping and the effects, each with its own release state.
Held-out split: time-ordered, the last ``holdout`` of the record.
"""

from __future__ import annotations

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..io import check_radians
from ..models.gyrotheodolite import (
    ODE_OPTIONS,
    TEST_PARAMS,
    GyrotheodoliteConditions,
    GyrotheodoliteRig,
)
from ..record import BenchRecord
from ..simulate import integrate
from ._stats import Signature, onset_grid

__all__ = ["GyrotheodoliteProblem", "GYROTHEODOLITE_LIBRARY", "north_seeking_period"]

# effect -> (family, grid parameter or None); prior scales are the rig's Param.scale
GYROTHEODOLITE_LIBRARY = {
    "tape_torque": ("constant", None),
    "torque_ramp": ("trend", None),
    "drift_transient": ("transient", "tau_tr"),
    "torque_step": ("step", "t_step"),
    "pickoff_scale": ("scale", None),
}
NOMINAL = TEST_PARAMS
RUN_STATE = ("alpha0", "alpha_dot0")  # per run in a multi-run design
TRANSIENT_TIMES_MIN = tuple(float(x) for x in np.geomspace(3.0, 30.0, 8))


def north_seeking_period(rig, params, conditions) -> float:
    """Period (s) of the slow (north-seeking) mode: the complex eigenvalue pair of (3) with the
    smaller modulus."""
    a, *_ = rig.state_space(params, conditions)
    ev = np.linalg.eigvals(np.asarray(a))
    slow = ev[np.argmin(np.abs(ev))]
    return float(2 * np.pi / abs(slow.imag)) if slow.imag != 0 else float("inf")


@eqx.filter_jit
def _model(rig, params, conditions, ts, names, scales):
    """The pick-off over ``ts`` and its Jacobian in ``params[names] / scales`` (forward mode
    through diffrax): one compilation serves the fits, the screening and the designs."""
    def f(u):
        p = params | {k: params[k] + u[i] * scales[i] for i, k in enumerate(names)}
        y = integrate(rig, p, conditions, ts, adjoint=diffrax.ForwardMode(), throw=False,
                      **ODE_OPTIONS)[:, 0]
        return y, y

    jac, y = jax.jacfwd(f, has_aux=True)(jnp.zeros(len(names)))
    return y, jac


class GyrotheodoliteProblem:
    """One north-seeking run split by time into train / held-out."""

    rig_name = "gyrotheodolite"

    def __init__(self, record: BenchRecord, *, holdout: float = 0.25, noise_std=None,
                 effects=None, order=None):
        if tuple(record.channels) != ("alpha",):
            raise ValueError(f"channels {tuple(record.channels)}: the gyrotheodolite diagnosis "
                             "needs one channel 'alpha' (azimuth pick-off, rad)")
        c = record.conditions
        if float(c.get("n_m", 0.0)) != 0.0:
            raise ValueError(f"n_m={c.get('n_m')} g: the gyrotheodolite diagnosis models static "
                             "runs; diagnose a record without base vibration")
        self.record = record
        self.rig = GyrotheodoliteRig()
        self.space = self.rig.param_space
        self.conditions = GyrotheodoliteConditions.create(float(c.get("latitude_deg", 50.45)))
        self.t = np.asarray(record.t, float)
        self.y = np.asarray(record.y, float)
        # the sensing element's model is for small angles (it swings by degrees): a record in
        # arcsec fits it as a scaled copy, with a north offset of hundreds of "radians"
        check_radians(self.y, tuple(record.channels), 1.0, "the small-angle model's range")
        self.channels = ("alpha",)
        n = len(self.t)
        self.n_train = n - int(round(holdout * n)) if holdout > 0 else n
        base = {k: float(c[k]) for k in ("H", "J_y", "J_z", "mgl", "f_alpha", "f_beta", "F_KC",
                                         "kappa") if k in c}
        self.base = self.rig.default_params(**base)
        period = north_seeking_period(self.rig, self.base, self.conditions)
        span = self.t[self.n_train - 1] - self.t[0]
        if span < period:
            raise ValueError(f"the train part spans {span:.0f} s, less than one north-seeking "
                             f"period ({period:.0f} s): record at least {2 * period / 60:.0f} "
                             "min or lower --holdout (t is in s: a record in min spans 60x less)")
        self.noise_std = noise_std
        self.effects = tuple(effects) if effects is not None else tuple(GYROTHEODOLITE_LIBRARY)
        sp = self.space
        self.nominal_names = NOMINAL
        self.nominal_scales = sp.scales(NOMINAL)
        self.nominal_units = tuple(sp[k].display_unit for k in NOMINAL)
        self.nominal_display_scales = self.nominal_scales / np.array(
            [sp[k].display_factor for k in NOMINAL])
        self.effect_names = {e: tuple(k for k in sp.effect_names(e)
                                      if k != GYROTHEODOLITE_LIBRARY[e][1]) for e in self.effects}
        # every coefficient the fits and the screening differentiate (grid parameters excepted)
        self.all_names = NOMINAL + tuple(k for e in GYROTHEODOLITE_LIBRARY
                                         for k in sp.effect_names(e)
                                         if k != GYROTHEODOLITE_LIBRARY[e][1])
        self.all_scales = sp.scales(self.all_names)
        # one onset every 5 % of the record over the train span (14 on the 40-min design; 8,
        # 11 % of the span apart, before stop 44; a torque step's visible fraction rises from
        # 0.003 at 11 % of the span through 0.05 at ~19 % to 0.09 at 22 %)
        self.step_grid_s = tuple(float(x) for x in onset_grid(self.t, self.n_train))
        self.lines = {"north-seeking period": period}
        self.notes: list[str] = []

    # -- the model and its Jacobian over every free name ----------------------------------
    def _eval(self, params, ts=None):
        """(pick-off, Jacobian in every nominal and effect coefficient per Param.scale) over
        ``ts`` (default the record's times)."""
        ts = jnp.asarray(self.t if ts is None else ts, dtype=float)
        params = {k: jnp.asarray(v, dtype=float) for k, v in params.items()}  # one trace
        y, jac = _model(self.rig, params, self.conditions, ts, self.all_names,
                        jnp.asarray(self.all_scales))
        return np.asarray(y), np.asarray(jac)

    def _fit(self, names, start, *, what: str, max_iter: int = 20, tol: float = 1e-8,
             rtol_cost: float = 1e-10):
        """Gauss-Newton over ``names`` on the train rows (the held-out rows weigh nothing);
        the Jacobian's other columns are dropped, so every fit reuses one compilation.

        Converged when the step is below ``tol`` (in parameter scales) or when it would lower
        the sum of squares by less than ``rtol_cost`` of it: near the optimum the adaptive ODE
        solve's own step choices move the model by ~1e-7 scales, and a step criterion alone
        then cycles between two such points (found on one of 1000 blind null records).

        A step is taken whole unless it leaves the sum of squares rising along it faster than
        half the rate at which it fell at the start (it went well past the minimum along the
        step) or higher than at the start (beyond its ~1e-6 evaluation noise); then it is cut to
        the root of the slope's secant (or halved), up to 8 times. A record with a large
        unmodelled effect leaves a large residual, where whole steps overshoot and oscillate (a
        3 nN m torque step, 150 arcsec, made the nominal fit alternate for 20 steps before
        stop 65). A fit that does not converge, or finds no step that lowers the sum of
        squares, stops at its last point and says so in :attr:`notes`."""
        n = self.n_train
        cols = [self.all_names.index(k) for k in names]
        p = dict(start)

        def move(t, step):
            return p | {k: jnp.asarray(float(p[k]) + t * step[i] * self.all_scales[c])
                        for i, (k, c) in enumerate(zip(names, cols, strict=True))}

        pred, jac = self._eval(p)
        for _ in range(max_iter):
            r = self.y[:n, 0] - pred[:n]
            cost = float(r @ r)
            step, *_ = np.linalg.lstsq(jac[:n, cols], r, rcond=None)
            decrement = float(np.sum((jac[:n, cols] @ step) ** 2))
            if np.max(np.abs(step)) < tol or decrement <= rtol_cost * cost:
                return move(1.0, step)
            t = 1.0
            for _ in range(9):
                try:
                    pred_t, jac_t = self._eval(trial := move(t, step))
                except eqx.EquinoxRuntimeError:  # a trial the model's solver cannot reach
                    t *= 0.5
                    continue
                r_t = self.y[:n, 0] - pred_t[:n]
                # the slope of the sum of squares along the step at t (per unit t); -2 decrement
                # at t = 0. The cost itself is noisy at ~1e-7 of itself (the adaptive solver's
                # step choices), its slope is not: judge a step by the slope it leaves
                slope = -2.0 * float(r_t @ (jac_t[:n, cols] @ step))
                if float(r_t @ r_t) <= cost * (1 + 1e-6) and slope <= decrement:
                    p, pred, jac = trial, pred_t, jac_t
                    break
                if slope > decrement:  # well past the minimum: to the slope's secant root
                    t *= float(np.clip(2 * decrement / (2 * decrement + slope), 0.1, 0.67))
                else:  # the sum of squares rose: half the step
                    t *= 0.5
            else:
                self.notes.append(f"{what}: no step along Gauss-Newton's direction lowered the "
                                  "sum of squares; its figures are those of the last point")
                return p
        self.notes.append(f"{what}: Gauss-Newton did not converge in {max_iter} steps; its "
                          "figures are those of the last step (is the record a north-seeking "
                          "run released near the meridian?)")
        return p

    def fit_nominal(self) -> dict:
        # start: offset from the record's last tenth of the train part, release from sample 0
        tail = float(np.mean(self.y[int(0.9 * self.n_train): self.n_train, 0]))
        start = self.base | {"index_offset": jnp.asarray(tail),
                             "alpha0": jnp.asarray(float(self.y[0, 0]) - tail)}
        p = self._fit(NOMINAL, start, what="the nominal fit")
        return {k: p[k] for k in NOMINAL}

    def _params(self, params):
        return self.base | {k: jnp.asarray(params[k]) for k in NOMINAL}

    def predict(self, params: dict, extra=None) -> np.ndarray:
        return self._eval(self.base | dict(params))[0][:, None]

    # -- Jacobians -------------------------------------------------------------------------
    def _grid(self, e):
        if e == "drift_transient":
            return (TRANSIENT_TIMES_MIN, "decay time", "min",
                    [m * 60 for m in TRANSIENT_TIMES_MIN])
        if e == "torque_step":
            return tuple(x / 60 for x in self.step_grid_s), "onset", "min", self.step_grid_s
        return (), "", "", [None]

    design_grid_choice = True  # jacobians(grid=...) evaluates one grid value per effect

    def jacobians(self, params, sigma, *, conditions=None, t=None, grid=None):
        """Whitened Jacobians, rows (time, channel): nominal (per Param.scale) and one
        :class:`Signature` per catalogued effect (per prior scale, grid slices). ``conditions``:
        a design from :meth:`designs` (a tuple of runs), default the record's single run.
        ``grid``: effect -> grid index to evaluate alone (the design advisor's screened values;
        the other grid effects at index 0), instead of every grid value."""
        sp = self.space
        runs = conditions if conditions is not None else (("record", 1.0, 0.0),)
        w = 1.0 / float(np.asarray(sigma).reshape(-1)[0])
        shared = ("index_offset", "kappa", "F_KC")
        col = {k: i for i, k in enumerate(self.all_names)}
        base = self._params(params)
        blocks, run_cols, sig_rows = [], [], {e: [] for e in self.effects}
        for _, h_factor, d_kappa in runs:
            p = base | {"H": base["H"] * h_factor, "kappa": base["kappa"] + d_kappa}
            jac = self._eval(p, t)[1] * w
            blocks.append(jac[:, [col[k] for k in shared]])
            run_cols.append(jac[:, [col[k] for k in RUN_STATE]])
            for e in self.effects:
                idx = [col[k] for k in self.effect_names[e]]
                gpar = GYROTHEODOLITE_LIBRARY[e][1]
                if gpar is None:
                    sig_rows[e].append(jac[:, idx][None])
                else:
                    values = self._grid(e)[3]
                    if grid is not None:
                        values = [values[min(grid.get(e, 0), len(values) - 1)]]
                    sig_rows[e].append(np.stack([
                        self._eval(p | {gpar: jnp.asarray(v)}, t)[1][:, idx] * w
                        for v in values]))
        m = blocks[0].shape[0]
        per_run = np.zeros((m * len(runs), len(RUN_STATE) * len(runs)))
        for i, rc in enumerate(run_cols):
            per_run[i * m:(i + 1) * m, i * len(RUN_STATE):(i + 1) * len(RUN_STATE)] = rc
        jn = np.concatenate([np.concatenate(blocks, axis=0), per_run], axis=1)
        if len(runs) == 1:  # the record: columns in NOMINAL order
            order = [len(shared) + RUN_STATE.index(k) if k in RUN_STATE else shared.index(k)
                     for k in NOMINAL]
            jn = jn[:, order]
        sigs = []
        for e in self.effects:
            en = self.effect_names[e]
            gvals, gname, gunit, _ = self._grid(e)
            if gvals and grid is not None:  # the one evaluated value
                gvals = (gvals[min(grid.get(e, 0), len(gvals) - 1)],)
            sigs.append(Signature(e, GYROTHEODOLITE_LIBRARY[e][0], en,
                                  tuple(sp[k].display_unit for k in en),
                                  sp.scales(en) / np.array([sp[k].display_factor for k in en]),
                                  np.concatenate(sig_rows[e], axis=1), gvals, gname, gunit))
        return jn, sigs

    # -- refits ----------------------------------------------------------------------------
    def refit(self, params0: dict, sig_choices: list[tuple[Signature, int]], sigma):
        """Gauss-Newton on the rig over the five test parameters plus the chosen effects' terms
        (grid values fixed at the screened best), on the train split; returns (model over the
        whole record, effect coefficients in display units, params)."""
        sp = self.space
        names = list(NOMINAL)
        start = self._params(params0)
        for sig, g in sig_choices:
            names += list(sig.names)
            gpar = GYROTHEODOLITE_LIBRARY[sig.name][1]
            if gpar is not None:
                start = start | {gpar: jnp.asarray(self._grid(sig.name)[3][g])}
        p = self._fit(tuple(names), start,
                      what="the refit with " + " + ".join(s.name for s, _ in sig_choices))
        coeffs = {k: float(sp[k].to_display(p[k])) for sig, _ in sig_choices for k in sig.names}
        return self.predict(p), coeffs, p

    # -- designs for the advisor -----------------------------------------------------------
    def designs(self):
        """Candidate tests: the run twice as long at half the rate; a second run with the compensation link on
        (kappa + 10); a second run at half the rotor momentum (H/2)."""
        dt = (self.t[-1] - self.t[0]) / (len(self.t) - 1)
        span = (self.t[-1] - self.t[0]) / 60
        return [  # the longer run keeps the sample count (one compilation): half the rate
            (f"{2 * span:.0f} min run ({2 * dt:g} s samples)", (("run", 1.0, 0.0),),
             self.t[0] + 2 * dt * np.arange(len(self.t))),
            ("second run with the compensation link on (kappa + 10)",
             (("run", 1.0, 0.0), ("kappa+10", 1.0, 10.0)), self.t),
            ("second run at half the rotor momentum (H/2)",
             (("run", 1.0, 0.0), ("H/2", 0.5, 0.0)), self.t),
        ]

    def display_nominal(self, params) -> dict:
        return {k: float(self.space[k].to_display(params[k])) for k in NOMINAL}
