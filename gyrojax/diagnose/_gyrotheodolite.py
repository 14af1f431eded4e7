"""The gyrotheodolite north-seeking run as the diagnosis sees it (``--rig gyrotheodolite``).

Record: the azimuth pick-off ``alpha`` (rad) of a sensing element released near the meridian,
sampled over several north-seeking periods. Nominal model: the 4-state rig (1) of
:class:`gyrojax.models.GyrotheodoliteRig` with the physical constants of docs/rigs/gyrotheodolite.md frozen
and five test parameters free - the index offset (the azimuth the instrument measures), the release state
``alpha0``, ``alpha_dot0``, and the slow mode's stiffness and damping through ``kappa`` and
``F_KC`` - fitted by Levenberg-Marquardt (optimistix) through diffrax (``Kvaerno5``: the 8.7 Hz
nutation mode makes the rig stiff for explicit solvers). Catalogue: the rig's effect groups,
torques about the vertical (``tape_torque``, ``torque_ramp``, ``drift_transient`` with its decay
time on a grid, ``torque_step`` with its onset on a grid) and the pick-off scale ``pickoff_scale``.

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
import jax.numpy as jnp
import numpy as np

from .. import units
from ..estimate import convergence_note, solve_least_squares
from ..io import check_radians
from ..models.gyrotheodolite import (
    ODE_OPTIONS,
    TEST_PARAMS,
    GyrotheodoliteConditions,
    GyrotheodoliteRig,
)
from ..record import BenchRecord
from ..simulate import integrate
from ._problem import AbstractGapProblem
from ._signatures import Signature, check_effects, onset_grid

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
def _fit_masked(rig, params, conditions, ts, y, w, names, scales, mask, budget):
    """The pick-off over ``ts`` fitted to ``y`` (rows weighted by ``w``: 0 leaves a row out)
    over ``params[names]`` (per ``scales``; ``mask`` 0: held) in at most ``budget`` optimistix
    steps. One compilation (forward sensitivities through diffrax's Kvaerno5) serves the nominal
    fit, every refit and -- ``budget`` 1, ``y`` 0, ``w`` 1 -- the model and its Jacobian for
    the screening and the designs (:meth:`GyrotheodoliteProblem._eval`). Returns (parameters,
    the :class:`~gyrojax.estimate.LeastSquaresSolution`)."""
    args = (params, conditions, ts, y, w, scales, mask)
    sol = solve_least_squares(_Residual(rig, names), jnp.zeros(len(names)), args,
                              max_steps=_MAX_STEPS, budget=budget)
    return _at(names, sol.value, *args), sol


def _at(names, u, params, conditions, ts, y, w, scales, mask):
    return params | {k: params[k] + u[i] * mask[i] * scales[i] for i, k in enumerate(names)}


class _Residual(eqx.Module):
    """The weighted pick-off residual of :func:`_fit_masked` (data in ``args``: one trace)."""

    rig: GyrotheodoliteRig
    names: tuple[str, ...] = eqx.field(static=True)

    def __call__(self, u, args):
        params, conditions, ts, y, w, scales, mask = args
        p = _at(self.names, u, *args)
        return (y - integrate(self.rig, p, conditions, ts, adjoint=diffrax.ForwardMode(),
                              throw=False, **ODE_OPTIONS)[:, 0]) * w


_MAX_STEPS = 40  # optimistix steps of the nominal fit and each refit


class GyrotheodoliteProblem(AbstractGapProblem):
    """One north-seeking run split by time into train / held-out."""

    NOISE_UNITS = {"": (units.ARCSEC, "arcsec")}

    @classmethod
    def catalogue(cls, **options) -> dict:
        """The catalogue: effect name -> family."""
        return {k: v[0] for k, v in GYROTHEODOLITE_LIBRARY.items()}

    def __init__(self, record: BenchRecord, *, holdout: float = 0.25, noise_std=None,
                 effects=None):
        check_effects(effects, GYROTHEODOLITE_LIBRARY, "gyrotheodolite")
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
        self.conditions = GyrotheodoliteConditions.from_record(record)
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
        # one onset every 5 % of the record over the train span (14 on the 40-min design; a
        # grid 11 % of the span apart is too coarse: a torque step's visible fraction rises from
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
        ones = jnp.ones(len(self.all_names))
        _, sol = _fit_masked(self.rig, params, self.conditions, ts, jnp.zeros(ts.shape),
                             jnp.ones(ts.shape), self.all_names, jnp.asarray(self.all_scales),
                             ones, jnp.asarray(1))
        return -np.asarray(sol.residual), -np.asarray(sol.jacobian)

    def _fit(self, names, start, *, what: str) -> dict:
        """Levenberg-Marquardt (optimistix, :func:`~gyrojax.estimate.solve_least_squares`) over
        ``names`` on the train rows (the held-out rows weigh nothing), from ``start``: one
        compiled fit over every coefficient (:attr:`all_names`), the others masked (held at
        their start). A fit that does not
        converge stops at its last accepted point and says so in :attr:`notes`."""
        w = (np.arange(len(self.t)) < self.n_train).astype(float)  # the train rows
        mask = np.array([float(k in names) for k in self.all_names])
        start = {k: jnp.asarray(v, dtype=float) for k, v in start.items()}  # one trace
        p, sol = _fit_masked(self.rig, start, self.conditions, jnp.asarray(self.t),
                             jnp.asarray(self.y[:, 0]), jnp.asarray(w), self.all_names,
                             jnp.asarray(self.all_scales), jnp.asarray(mask),
                             jnp.asarray(_MAX_STEPS))
        note = convergence_note(sol, what)
        if note is not None:
            self.notes.append(note + " (is the record a north-seeking run released near the "
                              "meridian?)")
        return dict(p)

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
        """Levenberg-Marquardt on the rig over the five test parameters plus the chosen effects' terms
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
