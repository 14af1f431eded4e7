"""A sixth rig from outside the package, to prove the extension path: a single-axis rate gyro on
a turntable. Its output angle (the integrated rate, channel ``angle``, rad) obeys
``d angle / dt = (1 + k) Omega(t) + b + r t`` with the table's rate
``Omega(t) = Omega0 sin(2 pi t / P)``; the nominal model fits the bias ``b`` and the scale
error ``k``, and the one catalogued effect is a bias ramp ``r`` (null 0). It implements the
model, diagnosis and command interfaces and registers itself (:func:`register`): nothing in
``gyrojax/`` names it."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from gyrojax import rigs, units
from gyrojax.cli import AbstractRigCommands, emit_json, load, parse_sets
from gyrojax.diagnose import AbstractGapProblem, Signature
from gyrojax.estimate import fit_trajectory, trajectory_jacobian
from gyrojax.models import AbstractRig
from gyrojax.params import ParameterSpace, param

CHANNELS = ("angle",)
SPACE = ParameterSpace((
    param("b", "rad/s", "deg/h", 1.0 * units.DEG_PER_HOUR, description="bias"),
    param("k", "1", "ppm", 1e-3, description="scale-factor error"),
    param("r", "rad/s^2", "deg/h/h", 1.0 * units.DEG_PER_HOUR / 3600, effect="bias_ramp",
          description="bias ramp"),
))


class TurntableConditions(eqx.Module):
    omega0: jax.Array  # rad/s, the table's rate amplitude
    period: jax.Array  # s

    @staticmethod
    def create(omega0_dps: float = 10.0, period_s: float = 600.0):
        return TurntableConditions(jnp.asarray(np.radians(omega0_dps)), jnp.asarray(period_s))

    @staticmethod
    def from_record(record):
        c = record.conditions
        return TurntableConditions.create(float(c.get("omega0_dps", 10.0)),
                                          float(c.get("period_s", 600.0)))


class TurntableRig(AbstractRig):
    CHANNEL_UNITS = {"angle": "rad"}
    param_space = SPACE
    channels = CHANNELS
    time_scale = 1.0

    def initial_state(self, params, conditions):
        return jnp.zeros(1)

    def vector_field(self, t, state, params, conditions):
        rate = conditions.omega0 * jnp.sin(2 * jnp.pi * t / conditions.period)
        return jnp.atleast_1d((1 + params["k"]) * rate + params["b"] + params["r"] * t)

    def observe(self, t, state, params, conditions):
        return state


NOMINAL = ("b", "k")


class TurntableProblem(AbstractGapProblem):
    """The diagnosis of a turntable record: nominal b, k; catalogue: bias_ramp."""

    @classmethod
    def catalogue(cls, **options):
        return {"bias_ramp": "trend"}

    def __init__(self, record, *, holdout=0.25, noise_std=None, effects=None):
        self.rig, self.record = TurntableRig(), record
        self.conditions = TurntableConditions.from_record(record)
        self.t, self.y = np.asarray(record.t, float), np.asarray(record.y, float)
        self.channels, self.noise_std = CHANNELS, noise_std
        self.n_train = len(self.t) - int(round(holdout * len(self.t)))
        self.effects = tuple(effects or ("bias_ramp",))
        self.nominal_names = NOMINAL
        self.nominal_units = tuple(SPACE[n].display_unit for n in NOMINAL)
        self.nominal_display_scales = SPACE.scales(NOMINAL) / np.array(
            [SPACE[n].display_factor for n in NOMINAL])
        self.lines, self.notes = {}, []

    def _fit(self, free, start):
        rec = self.record.slice(0, self.n_train)
        res = fit_trajectory(self.rig, rec, self.conditions, start, free=free, throw=False)
        if not bool(res.converged):
            self.notes.append(f"the fit of {', '.join(free)} did not converge")
        return {k: float(v) for k, v in res.params.items()}

    def fit_nominal(self):
        return self._fit(NOMINAL, SPACE.make())

    def predict(self, params, extra=None):
        from gyrojax.simulate import integrate

        return np.asarray(integrate(self.rig, params, self.conditions, self.t))

    def jacobians(self, params, sigma, *, conditions=None, t=None):
        cond = self.conditions if conditions is None else conditions
        ts = self.t if t is None else t
        jac = np.asarray(trajectory_jacobian(self.rig, params, cond, ts, NOMINAL + ("r",)))
        jac = jac * np.concatenate([SPACE.scales(NOMINAL), [SPACE["r"].scale]]) / sigma[0]
        ramp = Signature("bias_ramp", "trend", ("r",), ("deg/h/h",), np.ones(1),
                         jac[None, :, 2:])
        return jac[:, :2], [ramp]

    def refit(self, params0, sig_choices, sigma):
        p = self._fit(NOMINAL + ("r",), dict(params0))
        return self.predict(p), {"r": float(SPACE["r"].to_display(p["r"]))}, p

    def designs(self):
        span = self.t[-1] - self.t[0]
        return [("record twice as long", self.conditions,
                 self.t[0] + 2 * span * np.linspace(0, 1, len(self.t)))]

    def display_nominal(self, params):
        return {n: float(SPACE[n].to_display(params[n])) for n in NOMINAL}


class TurntableCommands(AbstractRigCommands):
    name = "turntable"
    COMMANDS = ("simulate", "fit", "observability", "diagnose")

    def add_arguments(self, command, group):
        if command in ("simulate", "observability"):
            group.add_argument("--omega0", type=float, default=10.0,
                               help="turntable: rate amplitude in deg/s (default 10)")

    def _times(self, args):
        return np.arange(0.0, 3600.0 * (args.hours or 1.0) + 1e-9, args.sample or 1.0)

    def simulate(self, args):
        from gyrojax.io import save_record
        from gyrojax.simulate import simulate

        cond = TurntableConditions.create(args.omega0)
        params = SPACE.make(parse_sets(args.set, SPACE))
        rec = simulate(TurntableRig(), params, cond, self._times(args),
                       key=jax.random.key(args.seed),
                       noise_std=(args.noise_arcsec or 1.0) * units.ARCSEC,
                       attrs={"rig": "turntable", "omega0_dps": args.omega0})
        save_record(rec, args.out, units=TurntableRig.CHANNEL_UNITS)
        emit_json({"record": args.out}, args.json)

    def fit(self, args):
        rec = self.load(args)
        res = fit_trajectory(TurntableRig(), rec, TurntableConditions.from_record(rec),
                             SPACE.make(), free=NOMINAL)
        se = res.stderr_dict()
        print(SPACE.table(res.params, se, names=NOMINAL))
        emit_json({"parameters": {n: {"value": float(SPACE[n].to_display(res.params[n])),
                                      "stderr": float(SPACE[n].to_display(se[n]))}
                                  for n in NOMINAL}}, args.json)

    def observability(self, args):
        from gyrojax.analysis.observability import observability

        rep = observability(TurntableRig(), SPACE.make(), TurntableConditions.create(args.omega0),
                            self._times(args), free=NOMINAL + ("r",))
        print(rep.summary())
        emit_json(rep.to_json(), args.json)

    def load(self, args):
        return load(args, CHANNELS)


ENTRY = rigs.RigEntry("turntable", "single-axis rate gyro on a turntable (a test's own rig)",
                      "toy_rig:TurntableRig", "toy_rig:TurntableConditions",
                      "toy_rig:TurntableProblem", "toy_rig:TurntableCommands")


def register():
    rigs.register(ENTRY, replace=True)
