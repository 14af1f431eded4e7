"""The three-gimbal platform under vibration as the diagnosis sees it (``--rig platform``).

The record is a test schedule (``gyrojax simulate --rig platform``: dwells at the positions of the
schedule, one amplitude after another, the schedule in the ``schedule_json`` attribute). The
model is the batch regression (S22) of the averaged drift law: per dwell, the gimbal angles
minus the integrated Earth rate, centred, are linear in the drift coefficients, with ``kappa``
per amplitude from the accelerometers (as ``gyrojax fit --rig platform`` does). Rows are block
means of the centred angles (``blocks`` per dwell; exact for a linear model, the angle noise is
white), so a 14 x 2 x 100 s test at 40 Hz gives 2,800 x 3 rows.

Nominal model: the 30 coefficients less the ``D_oo`` (quadrature anisoelastic) terms, the model
a single amplitude can fit (the source's test); ``nominal_terms`` picks another (e.g.
:data:`FIRST_ORDER_TERMS`, bias and g terms), and every coefficient it leaves out is then
screened as an effect of its own (:func:`platform_library`) in place of ``anisoelastic_oo``.
Catalogue (drift terms in the platform frame, each
with a null value, entering the angles through the kinematics of (S12)):

- ``anisoelastic_oo``: ``D_oo_x,y,z`` (deg/h/g^2). On one amplitude it is absorbed exactly as
  ``D_f + (a^2/2 + 1) D_oo``, ``D_ii - D_oo``, ``D_ss - D_oo`` (structurally confounded); a
  second amplitude makes it visible.
- ``base_misalignment``: a small rotation of the base (``C_r^b``) about its three axes (arcsec):
  an Earth-rate error fixed in the base, which the positions turn against the platform-fixed
  biases.
- ``warmup_transient``: ``dm_j exp(-t/tau)`` from the start of the test (deg/h), tau on a grid.
- ``drift_ramp``: ``r_j t`` (deg/h per h).
- ``vibration_rectification``: a constant drift in vibrated dwells only (deg/h): with
  every dwell vibrated it is exactly ``D_f``; a 0 g amplitude makes it visible.

Held-out splits (``split``):

- ``"same-design"`` (default): the last ``holdout`` of every dwell. Each dwell's angle offsets
  are fitted on its train part (centring by the train-block mean); the diagnosis is told their
  dof (``nuisance_dof``) and their share of the held-out gap (``heldout_extra``). Holding out
  whole positions instead would leave the 27-coefficient model underdetermined on Table 1.
- ``"design-shift"``: the last vibration amplitude's run held out whole (another vibration
  level, docs/rigs/platform.md stage 4), the other runs wholly train. Every dwell is centred by its own
  mean; the held-out dwells' offsets are fitted on the held-out rows (``heldout_dof``). A
  confusable pick (a ramp for a transient, rectification for ``D_f``) that fits the train
  runs extrapolates wrongly to the new level and time, which the same-design split cannot see.
"""

from __future__ import annotations

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..estimate.platform import cumulative_trapezoid, position_design, record_kappas
from ..models.platform import (
    COEFF_NAMES,
    TERMS,
    PlatformRig,
    drift_rates,
    kinematic_matrix,
    platform_matrix,
    schedule,
    specific_force_direction,
)
from ..models.platform_schedule import CHANNELS as REC_CHANNELS
from ..models.platform_schedule import (
    dwell_span,
    dwell_times,
    load_schedule,
    schedule_conditions,
    split_record,
)
from ..record import BenchRecord
from ._problem import AbstractGapProblem
from ._signatures import Signature, check_effects

__all__ = ["PlatformProblem", "PLATFORM_LIBRARY", "platform_library", "FIRST_ORDER_TERMS"]

CHANNELS = ("alpha", "beta", "gamma")
LABELS = ("position", "amplitude")
# effect -> (family, prior scale per coefficient in display units)
PLATFORM_LIBRARY = {
    "anisoelastic_oo": ("g2", 0.03),  # deg/h/g^2
    "base_misalignment": ("mounting", 60.0),  # arcsec
    "warmup_transient": ("transient", 0.3),  # deg/h
    "drift_ramp": ("trend", 0.3),  # deg/h per h
    "vibration_rectification": ("vibration", 0.1),  # deg/h
}
_UNITS = {"anisoelastic_oo": "deg/h/g^2", "base_misalignment": "arcsec",
          "warmup_transient": "deg/h", "drift_ramp": "deg/h/h",
          "vibration_rectification": "deg/h"}
_SI = {"anisoelastic_oo": units.DEG_PER_HOUR, "base_misalignment": units.ARCSEC,
       "warmup_transient": units.DEG_PER_HOUR, "drift_ramp": units.DEG_PER_HOUR / 3600.0,
       "vibration_rectification": units.DEG_PER_HOUR}
_GRID_EFFECTS = ("warmup_transient",)
N_GRID = 8
NOMINAL_TERMS = tuple(t for t in TERMS if t != "oo")
NOMINAL = tuple(n for n in COEFF_NAMES if not n.startswith("D_oo"))
FIRST_ORDER_TERMS = ("f", "i", "o", "s")  # bias and the g-sensitive terms, no g^2 terms


def _coefficient_effect(name: str):
    """``(family, prior, unit)`` of one drift coefficient screened as an effect: the g terms
    (deg/h/g) and the g^2 terms (deg/h/g^2) at the rig's prior scales."""
    term = name.split("_")[1]
    return ("g", 1.0, "deg/h/g") if len(term) == 1 else ("g2", 0.03, "deg/h/g^2")


def platform_library(nominal_terms=None) -> dict:
    """The catalogue the diagnosis screens for a nominal model of ``nominal_terms`` (drift-law
    terms of :data:`~gyrojax.models.platform.TERMS` carried for every gyro; default all but
    ``oo``, the source's model): effect -> ``(family, prior scale per coefficient)``. The default
    keeps the source's grouping (:data:`PLATFORM_LIBRARY`, ``D_oo`` of the three gyros as one
    effect); any other nominal screens every coefficient it leaves out as an effect of its
    own (``D_ii_y``: which gyro needs which term) beside the four non-drift-law effects."""
    terms = _check_terms(nominal_terms)
    if terms == NOMINAL_TERMS:
        return dict(PLATFORM_LIBRARY)
    out = {n: _coefficient_effect(n)[:2] for n in COEFF_NAMES if n.split("_")[1] not in terms}
    return out | {k: v for k, v in PLATFORM_LIBRARY.items() if k != "anisoelastic_oo"}


def nominal_coefficients(nominal_terms=None) -> tuple:
    """The drift coefficients a nominal of ``nominal_terms`` fits, in canonical order."""
    terms = _check_terms(nominal_terms)
    return tuple(n for n in COEFF_NAMES if n.split("_")[1] in terms)


def _check_terms(nominal_terms) -> tuple:
    """The nominal's terms in canonical order; a clear error for an unknown or missing one."""
    if nominal_terms is None:
        return NOMINAL_TERMS
    terms = tuple(str(t).strip() for t in nominal_terms)
    bad = [t for t in terms if t not in TERMS]
    if bad:
        raise ValueError(f"nominal_terms {bad} unknown; the platform drift law's terms are "
                         f"{', '.join(TERMS)} (e.g. f,i,o,s: the first-order model)")
    if "f" not in terms:
        raise ValueError(f"nominal_terms {list(terms)} lack 'f': every platform nominal "
                         "carries the gyro biases D_f; add f")
    return tuple(t for t in TERMS if t in terms)


_BASE = len(COEFF_NAMES)  # the base misalignment's first column in :func:`_dwell`'s columns


def _misalignment_rate(a, cond, theta):
    """(3, 3): the averaged model's angle rate at attitude ``a`` per rad of base rotation
    ``delta``, at the drift coefficients ``theta``: the Earth rate and the gravity direction both
    move (the rig's base, ``R(-delta) C_r^b``)."""

    def rate(delta):
        m = PlatformRig.mounting(dict(zip(("dchi_x", "dchi_y", "dchi_z"), delta)), cond)
        n = specific_force_direction(a, m)
        drift = drift_rates(n, jnp.ones_like(cond.kappa), cond.kappa, theta)
        w_ie = cond.earth_rate_base(m)
        return kinematic_matrix(a[1], a[2]) @ (-drift - platform_matrix(a).T @ w_ie)
    return jax.jacfwd(rate)(jnp.zeros(3))


def _centred_integral(g, ts):
    cols = cumulative_trapezoid(g, ts)
    return cols - cols.mean(0)


@eqx.filter_jit
def _dwell(ts, t0, angles, cond, vibrated, theta, taus):
    """One dwell: centred ``angles - h`` (n, 3), centred drift-coefficient columns (n, 3, 30) and
    the catalogue's columns (n, 3, k) per unit SI coefficient (base misalignment: per rad, at the
    drift coefficients ``theta``; the transient: one block of 3 per grid value)."""
    y, big_f = position_design(ts, angles, cond)
    t_abs = t0 + ts

    def per_sample(a, t):
        mk = kinematic_matrix(a[1], a[2])
        mis = _misalignment_rate(a, cond, theta)
        drift = -mk  # unit drift on each platform axis
        tr = jnp.concatenate([drift * jnp.exp(-t / tau) for tau in taus], axis=1) \
            if len(taus) else jnp.zeros((3, 0))
        return jnp.concatenate([mis, tr, drift * t, drift * vibrated],
                               axis=1)

    return y, big_f, _centred_integral(jax.vmap(per_sample)(angles, t_abs), ts)


@eqx.filter_jit
def _dwell_misalignment(ts, angles, cond, theta):
    """The base misalignment's columns of :func:`_dwell` alone (n, 3, 3): the only ones that
    depend on the drift coefficients ``theta``."""
    g = jax.vmap(_misalignment_rate, in_axes=(0, None, None))(angles, cond, theta)
    return _centred_integral(g, ts)


def _blocks(n, k):
    """Index groups of ``k`` nearly equal blocks of ``n`` samples (every sample in one block)."""
    return np.array_split(np.arange(n), k)


class PlatformProblem(AbstractGapProblem):
    """A platform test record reduced to block means of the centred angles.

    **Options:** `split`: ``"same-design"`` or ``"design-shift"`` (the last vibration
    amplitude's run held out whole); `nominal_terms`: the drift-law terms of the nominal model
    (default all but ``oo``; each coefficient left out is screened as an effect of its own);
    `blocks`: block means per dwell."""

    NOISE_UNITS = {"": (units.ARCSEC, "arcsec")}
    OPTIONS = {"split": "'same-design' (default) or 'design-shift'",
               "nominal_terms": "the drift-law terms of the nominal model, e.g. ('f', 'i', 'o', "
                                "'s')",
               "blocks": "block means per dwell (default 50)"}
    SPLITS = {"same-design": "same design: the last part of every dwell held out",
              "design-shift": "design shift: the last vibration amplitude's run held out"}

    @classmethod
    def catalogue(cls, *, nominal_terms=None, **options) -> dict:
        """The catalogue for the nominal model of ``nominal_terms``: effect name -> family
        (:func:`platform_library`)."""
        return {k: v[0] for k, v in platform_library(nominal_terms).items()}

    @classmethod
    def single_coefficients(cls, *, nominal_terms=None, **options) -> bool:
        return nominal_terms is not None

    def __init__(self, record: BenchRecord, *, holdout: float = 0.25, noise_std=None,
                 effects=None, blocks: int = 50, split: str = "same-design",
                 nominal_terms=None):
        if split not in self.SPLITS:
            raise ValueError(f"split={split!r} for --rig platform; use one of "
                             f"{', '.join(self.SPLITS)}")
        missing = [c for c in REC_CHANNELS if c not in record.channels]
        if missing:
            raise ValueError(f"platform record lacks channel(s) {missing}; a platform test record "
                             f"has {', '.join(REC_CHANNELS)} (see gyrojax simulate --rig platform)")
        if "schedule_json" not in record.conditions:
            raise ValueError("the record carries no schedule (attribute schedule_json); record "
                             "it with gyrojax simulate --rig platform or add the schedule")
        self.schedule = load_schedule(json.loads(record.conditions["schedule_json"]))
        y = np.stack([np.asarray(record.channel(c)) for c in REC_CHANNELS], axis=1)
        data = split_record(BenchRecord(record.t, jnp.asarray(y), REC_CHANNELS, record.attrs),
                      self.schedule)  # (A, P, n, 8)
        self.ts = np.asarray(dwell_times(self.schedule))
        s = self.schedule
        self.amps = [float(a) / s["attenuation"] for a in s["table_amplitudes_g"]]
        self.kappas = record_kappas(data, s)
        self.conds = [eqx.tree_at(lambda c: c.kappa, c, jnp.full(len(s["positions_deg"]), kap))
                      for c, kap in zip(schedule_conditions(s), self.kappas)]
        self.angles = jnp.asarray(data[..., :3])
        self.n_blocks = int(blocks)
        self.noise_std = noise_std
        self.terms = _check_terms(nominal_terms)
        self.library = platform_library(self.terms)
        self.effects = tuple(effects) if effects is not None else tuple(self.library)
        check_effects(self.effects, self.library, "platform")
        self.channels = CHANNELS
        self.lines = {}
        self.notes: list[str] = []
        self.rig = PlatformRig()
        space = self.rig.param_space
        self.nominal_names = nominal_coefficients(self.terms)
        self.nominal_scales = space.scales(self.nominal_names)  # the rig's Param scales (SI)
        self.nominal_units = tuple(space[n].display_unit for n in self.nominal_names)
        self.nominal_display_scales = self.nominal_scales / np.array(
            [space[n].display_factor for n in self.nominal_names])
        self.record = record
        n_dw = len(self.amps) * len(s["positions_deg"])
        self.dwell_s = dwell_span(s)
        span = n_dw * self.dwell_s
        self.taus = tuple(float(x) for x in np.geomspace(span / 40, span / 2, N_GRID))
        n_pos = len(s["positions_deg"])
        self._split = split
        if split == "design-shift":
            if len(self.amps) < 2:
                raise ValueError("split='design-shift' holds out the last vibration amplitude's "
                                 f"run; this record has one amplitude "
                                 f"({s['table_amplitudes_g'][0]:g} g): use "
                                 "split='same-design' or record a second amplitude")
            self.k_ho = 0  # whole runs: every block of a train dwell is train
            self.held_runs = (len(self.amps) - 1,)
            self.design_shift = True
        else:
            self.k_ho = int(round(holdout * self.n_blocks)) if holdout > 0 else 0
            if self.n_blocks - self.k_ho < 4:
                raise ValueError(f"holdout={holdout} leaves {self.n_blocks - self.k_ho} of "
                                 f"{self.n_blocks} blocks per dwell to fit; lower --holdout")
            self.held_runs = ()
        self.y, self.t, self._cols = self._design(self.angles, self.conds, self.amps,
                                                  jnp.zeros(30))
        k_tr = self.n_blocks - self.k_ho
        n_train_dw = n_dw - n_pos * len(self.held_runs)
        self.n_train = n_train_dw * k_tr
        self.nuisance_dof = 3 * n_train_dw  # one offset per angle and train dwell
        if self.held_runs:
            self.heldout_dof = 3 * (n_dw - n_train_dw)  # offsets fitted on the held-out rows
            self.heldout_extra = 0.0
        else:
            self.heldout_extra = 1.0 / k_tr  # the offsets' variance on the held-out rows, in G

    # -- the linear design --------------------------------------------------------------------
    def _design(self, angles, conds, amps, theta, *, misalignment_only=False):
        """Block means over every dwell (amplitude-major, as recorded), each centred by the mean
        of its train blocks (= its angle offsets fitted on the train rows; a held-out run's
        dwells by their own mean): the train blocks of every dwell in time order, then the
        held-out ones. Returns angles (N, 3), block times (N,) and the columns (N, 3, 30 + k);
        ``misalignment_only``: the base misalignment's columns alone (N, 3, 3), the part that
        depends on ``theta`` (columns ``_BASE:_BASE + 3`` of the full ones), with zeros for the
        angles (they do not depend on ``theta``)."""
        ts = jnp.asarray(self.ts)
        groups = _blocks(len(self.ts), self.n_blocks)
        starts = np.array([g[0] for g in groups])
        sizes = np.array([len(g) for g in groups], float)

        def block_means(x):  # the groups are contiguous: one reduceat per dwell
            return np.add.reduceat(x, starts, axis=0) / sizes.reshape((-1,) + (1,) * (x.ndim - 1))
        t_blocks = block_means(self.ts)
        parts = {"train": ([], [], []), "heldout": ([], [], [])}
        k = 0
        for a, (ang, cond) in enumerate(zip(angles, conds)):
            k_tr = 0 if a in self.held_runs else self.n_blocks - self.k_ho
            cond = jax.tree.map(np.asarray, cond)  # numpy slices: no dispatch per dwell
            for p in range(ang.shape[0]):
                c = jax.tree.map(lambda x, p=p: x[p], cond)
                t0 = k * self.dwell_s
                if misalignment_only:
                    y = np.zeros((len(self.ts), 3))  # not wanted: the angles do not change
                    full = np.asarray(_dwell_misalignment(ts, ang[p], c, theta))
                else:
                    y, f, e = _dwell(ts, jnp.asarray(t0), ang[p], c,
                                     jnp.asarray(float(amps[a] > 0)), theta, self.taus)
                    full = np.concatenate([np.asarray(f), np.asarray(e)], axis=2)
                    y = np.asarray(y)
                yb, cb = block_means(y), block_means(full)
                ref = slice(0, k_tr or None)
                yb, cb = yb - yb[ref].mean(0), cb - cb[ref].mean(0)
                tb = t0 + t_blocks
                for part, sl in (("train", slice(0, k_tr)), ("heldout", slice(k_tr, None))):
                    for lst, v in zip(parts[part], (yb, tb, cb)):
                        lst.append(v[sl])
                k += 1
        ys, tt, cols = (np.concatenate(parts["train"][i] + parts["heldout"][i])
                        for i in range(3))
        return ys, tt, cols

    def _effect_cols(self, cols, name, g=0):
        """(N, 3, k) SI columns of one effect (grid index ``g``)."""
        base = _BASE
        if name in COEFF_NAMES:
            i = COEFF_NAMES.index(name)
            return cols[:, :, i:i + 1]
        if name == "anisoelastic_oo":
            return cols[:, :, [COEFF_NAMES.index(f"D_oo_{ax}") for ax in "xyz"]]
        if name == "base_misalignment":
            return cols[:, :, base:base + 3]
        if name == "warmup_transient":
            i = base + 3 + 3 * g
            return cols[:, :, i:i + 3]
        i = base + 3 + 3 * N_GRID
        if name == "drift_ramp":
            return cols[:, :, i:i + 3]  # per rad/s per s
        if name == "vibration_rectification":
            return cols[:, :, i + 3:i + 6]
        raise KeyError(name)

    def _effect_names(self, name):
        if name in COEFF_NAMES:
            return (name,)
        return {"anisoelastic_oo": tuple(f"D_oo_{ax}" for ax in "xyz"),
                "base_misalignment": ("dchi_x", "dchi_y", "dchi_z"),
                "warmup_transient": ("dm_x", "dm_y", "dm_z"),
                "drift_ramp": ("ramp_x", "ramp_y", "ramp_z"),
                "vibration_rectification": ("rect_x", "rect_y", "rect_z")}[name]

    def _nominal_cols(self, cols):
        return cols[:, :, [COEFF_NAMES.index(n) for n in self.nominal_names]]

    @staticmethod
    def _unit_si(name):
        """Display unit and SI factor of one effect's coefficients."""
        if name in COEFF_NAMES:
            return _coefficient_effect(name)[2], units.DEG_PER_HOUR
        return _UNITS[name], _SI[name]

    # -- the diagnosis interface --------------------------------------------------------------
    def _theta(self, params):
        return jnp.asarray([params.get(n, 0.0) for n in COEFF_NAMES])

    def fit_nominal(self) -> dict:
        """Least squares of the nominal coefficients on the train rows; the base misalignment's
        columns are then rebuilt at the fit (their gravity part depends on it; no other column
        does)."""
        m = self.n_train
        k = len(self.nominal_names)
        a = self._nominal_cols(self._cols)[:m].reshape(-1, k) * self.nominal_scales
        x, *_ = np.linalg.lstsq(a, self.y[:m].reshape(-1), rcond=None)
        params = dict(zip(self.nominal_names, x * self.nominal_scales))
        _, _, mis = self._design(self.angles, self.conds, self.amps, self._theta(params),
                                 misalignment_only=True)
        self._cols = self._cols.copy()
        self._cols[:, :, _BASE:_BASE + 3] = mis
        return params

    # -- the gap map's position axis -----------------------------------------------------------
    def _train_dwells(self):
        """``(run, position)`` of every train dwell, in the train rows' order."""
        n_pos = len(self.schedule["positions_deg"])
        return [(a, p) for a in range(len(self.amps)) if a not in self.held_runs
                for p in range(n_pos)]

    def position_signatures(self, sigma):
        """Per train dwell, the whitened signature of a drift-rate offset at that position: the
        block times' ramp, centred like the data (an angle offset is the dwell's nuisance).
        Condition: the run's table amplitude."""
        k_tr = self.n_blocks - self.k_ho
        amps_g = self.schedule["table_amplitudes_g"]
        out = []
        for d, (a, p) in enumerate(self._train_dwells()):
            rows = slice(d * k_tr, (d + 1) * k_tr)
            w = np.zeros((self.n_train, 3))
            ramp = self.t[rows] - self.t[rows].mean()
            w[rows] = ramp[:, None] / np.asarray(sigma)[None, :]
            out.append((f"position {p + 1} at {amps_g[a]:g} g", f"{amps_g[a]:g} g", w))
        return out

    def nuisance_columns(self, sigma):
        """The angle offsets per train dwell and channel (the data are centred by them),
        whitened: ``(n_train 3, 3 dwells)``."""
        k_tr = self.n_blocks - self.k_ho
        n_dw = self.n_train // k_tr
        ind = np.repeat(np.eye(n_dw), k_tr, axis=0)  # (n_train, dwells)
        cols = ind[:, None, :, None] * np.eye(3)[None, :, None, :] / np.asarray(
            sigma)[None, :, None, None]
        return cols.reshape(self.n_train * 3, n_dw * 3)

    def noise_level(self, resid):
        """Per-channel angle noise (block-mean level) from second differences *within* dwells:
        a nominal misfit jumps between dwells (centred separately) and is a ramp inside one
        (a drift error), which second differences remove; white noise gives var = 6 sigma^2."""
        if self.noise_std is not None:
            s = np.broadcast_to(np.asarray(self.noise_std, float), (3,)).copy()
            return s, np.inf, "given"
        s = self._second_difference_level(resid[None])[0]
        n_d = resid.shape[0] - 2 * (resid.shape[0] // (self.n_blocks - self.k_ho))
        # dof of the second-difference estimate: n (sum a_k^2)^2 / sum over lags of acf^2 ~ n/1.94
        return s, n_d / 1.94, ("estimated from second differences of the residual within "
                               "dwells")

    def _second_difference_level(self, resid):
        """Per-channel level of train residuals ``(B, n_train, 3)`` from second differences
        within dwells (white noise: var = 6 sigma^2): the data's and the null draws' estimator."""
        k_tr = self.n_blocks - self.k_ho
        d = np.diff(resid.reshape(resid.shape[0], -1, k_tr, 3), n=2, axis=2)
        return np.sqrt(np.mean(d * d, axis=(1, 2)) / 6)

    @property
    def split_kind(self) -> str:
        return self.SPLITS[self._split]

    def null_sampler(self, u, n, c, estimated):
        """The dwell-offset-aware draws of :meth:`null_residuals`."""
        return lambda rng, b: self.null_residuals(rng, b, u)

    def null_residuals(self, rng, b: int, u) -> np.ndarray:
        """``b`` whitened train residuals under the linearised null (the diagnosis' calibrated
        level): white block means, centred per train dwell like the data (the offsets), taken
        off the nominal span ``u``, and divided by :meth:`noise_level`'s estimate when the noise
        is not given. Shape ``(b, n_train, 3)``."""
        k_tr = self.n_blocks - self.k_ho
        z = rng.standard_normal((b, self.n_train // k_tr, k_tr, 3))
        z -= z.mean(axis=2, keepdims=True)
        z = z.reshape(b, -1)
        z -= (z @ u) @ u.T
        z = z.reshape(b, self.n_train, 3)
        if self.noise_std is None:
            z /= self._second_difference_level(z)[:, None, :]
        return z

    def predict(self, params: dict, extra=None) -> np.ndarray:
        v = np.array([params[n] for n in self.nominal_names])
        pred = np.einsum("nck,k->nc", self._nominal_cols(self._cols), v)
        return pred if extra is None else pred + extra

    def jacobians(self, params, sigma, *, conditions=None, t=None):
        """Whitened Jacobians over the record's rows (or a design's, ``conditions`` = a
        ``(angles, conds, amps)`` tuple from :meth:`designs`)."""
        if conditions is None:
            cols = self._cols
        else:
            _, _, cols = self._design(*conditions, self._theta(params))
        n = cols.shape[0]
        # every column whitened in one pass (rows contiguous), then each effect's a view of it
        white = (cols * (1.0 / np.asarray(sigma))[None, :, None]).reshape(n * 3, -1)
        jn = self._nominal_cols(white[:, None, :])[:, 0] * self.nominal_scales
        sigs = []
        for e in self.effects:
            fam, prior = self.library[e]
            unit, si = self._unit_si(e)
            f = prior * si
            gs = range(N_GRID) if e in _GRID_EFFECTS else range(1)
            jac = np.stack([self._effect_cols(white[:, None, :], e, g)[:, 0] for g in gs]) * f
            grid, gname, gunit = ((tuple(x / 3600 for x in self.taus), "decay time", "h")
                                  if e in _GRID_EFFECTS else ((), "", ""))
            names = self._effect_names(e)
            sigs.append(Signature(e, fam, names, (unit,) * len(names),
                                  np.full(len(names), prior), jac, grid, gname, gunit))
        return jn, sigs

    def refit(self, params0: dict, sig_choices, sigma):
        """Linear least squares on the train rows with the chosen effects' columns added."""
        m = self.n_train
        blocks = [self._nominal_cols(self._cols)]
        for sig, g in sig_choices:
            blocks.append(self._effect_cols(self._cols, sig.name, g))
        cols = np.concatenate(blocks, axis=2)
        w = (1.0 / np.asarray(sigma))[None, :, None]
        k = cols.shape[2]
        scale = np.concatenate([self.nominal_scales] + [
            np.full(len(s.names), self.library[s.name][1] * self._unit_si(s.name)[1])
            for s, _ in sig_choices])
        a = (cols[:m] * w).reshape(-1, k) * scale
        b = (self.y[:m] * w[:, :, 0]).reshape(-1)
        x, *_ = np.linalg.lstsq(a, b, rcond=None)
        x = x * scale
        pred = np.einsum("nck,k->nc", cols, x)
        p = dict(zip(self.nominal_names, x[:len(self.nominal_names)]))
        coeffs, i = {}, len(self.nominal_names)
        for sig, _ in sig_choices:
            for nm in sig.names:
                coeffs[nm] = float(x[i] / self._unit_si(sig.name)[1])
                i += 1
        return pred, coeffs, p

    def designs(self):
        """Alternative tests for the advisor (the record's positions, nominal angles): a
        second amplitude (one-amplitude records) and an added 0 g run (when every run is
        vibrated)."""
        s = self.schedule
        pos = np.asarray(s["positions_deg"], float)
        out = []

        def design(label, amps):
            conds = [schedule(pos, a0=a, latitude_deg=s["latitude_deg"],
                              frequency_hz=s["frequency_hz"], mounting=s["mounting_matrix"])
                     for a in amps]
            ang = jnp.broadcast_to(jnp.asarray(np.radians(pos))[None, :, None, :],
                                   (len(amps), len(pos), len(self.ts), 3))
            return (label, (ang, conds, list(amps)), None)

        if len(self.amps) == 1:
            a2 = self.amps[0] * 7 / 9 if self.amps[0] > 0 else 7 / s["attenuation"]
            out.append(design(f"second amplitude {a2 * s['attenuation']:.3g} g (table)",
                              self.amps + [a2]))
        if all(a > 0 for a in self.amps):
            out.append(design("an added 0 g (static) run", self.amps + [0.0]))
        return out

    def display_nominal(self, params) -> dict:
        space = self.rig.param_space
        return {k: float(space[k].to_display(params[k])) for k in self.nominal_names}
