"""Blind validation harness for the platform diagnosis (docs/diagnosis.md, design D2).

:func:`generate` writes platform test records (``case_<index>.nc``, the layout of
``gyrojax simulate --rig platform`` with the *nominal* schedule as attribute) and the sealed
manifest beside them (see :mod:`.bench`). D2: the 14 positions of Table 1 at a static
run and two vibration amplitudes (table 0, 9, 7 g), 100 s dwells at 40 Hz, 1 arcsec angle noise.
Each case draws the 27 nominal drift coefficients (the 30 of (S10) less ``D_oo``) from their
prior scales, adds a hidden effect and integrates the ODE model with it (the rig's effect
groups: the diagnosis's linear columns are not used here).

Case families: ``null``; each catalogue effect (``anisoelastic_oo``, ``base_misalignment``,
``warmup_transient`` with a log-uniform decay time over [1/30, 1/3] of the test,
``drift_ramp``, ``vibration_rectification``) in a random direction of its three coefficients;
the the source's structural case (``anisoelastic_oo_one_amplitude``: hidden ``D_oo`` at its prior
scale on a single-amplitude test, which has no signature: scored as silent); and two effects
the library omits: ``readout_line`` (a 20-min thermal line on the gamma pick-off) and
``readout_step`` (a slip of the alpha pick-off inside one dwell).

``PlatformDesign(nominal_terms=...)`` gives the diagnosis (and the generator's nominal draws) a
smaller nominal model, e.g. :data:`~gyrojax.diagnose._platform.FIRST_ORDER_TERMS` (bias and g
terms, 12 coefficients): every coefficient it leaves out is then a catalogue effect of its own
(:func:`~gyrojax.diagnose._platform.platform_library`, 22 effects for the first-order model) and a
case family, hidden one coefficient at a time (:func:`mean_families`).

Magnitudes: the noncentrality ``lambda`` of the effect's noise-free change of the record on the
train rows (block means of every dwell, each centred by its train part, whitened by the block
noise), with the nominal coefficients projected out through the estimator's own regression
columns (:func:`gyrojax.estimate.platform.position_design` of (S22)); the effect is then scaled
to the drawn ``lambda`` and integrated again.
"""

from __future__ import annotations

import dataclasses
import json
import re

import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..diagnose import PLATFORM_NOMINAL as NOMINAL
from ..diagnose import nominal_coefficients, platform_library
from ..estimate.platform import position_design
from ..models.platform import COEFF_NAMES, TABLE1_DEG, PlatformRig
from ..models.platform_schedule import (
    dwell_span,
    dwell_times,
    load_schedule,
    schedule_conditions,
    simulate_schedule,
)
from . import _harness
from ._harness import projector, run_cases, score_cases
from ._scoring import Sealer, truth_visibility

__all__ = ["PlatformDesign", "generate", "run", "score", "MEAN_FAMILIES", "OUT_OF_LIBRARY",
           "STRUCTURAL", "mean_families"]

MEAN_FAMILIES = ("anisoelastic_oo", "base_misalignment", "warmup_transient", "drift_ramp",
                 "vibration_rectification")
STRUCTURAL = ("anisoelastic_oo_one_amplitude",)
OUT_OF_LIBRARY = ("readout_line", "readout_step")
_PARAMS = {"anisoelastic_oo": "D_oo", "base_misalignment": "dchi", "warmup_transient": "dm",
           "drift_ramp": "ramp", "vibration_rectification": "rect"}
_RIG = PlatformRig()


@dataclasses.dataclass(frozen=True)
class PlatformDesign:
    """D2: Table 1 at a static run and two vibration amplitudes."""

    table_amplitudes_g: tuple = (0.0, 9.0, 7.0)
    dwell_s: float = 100.0
    sample_s: float = 0.025
    noise_arcsec: float = 1.0
    holdout: float = 0.25
    blocks: int = 50  # the diagnosis's default block count per dwell
    split: str = "same-design"  # or "design-shift": the last amplitude's run held out
    nominal_terms: tuple | None = None  # the diagnosis' nominal model (None: all but D_oo)

    def nominal_names(self) -> tuple:
        """The nominal coefficients the cases draw and the diagnosis fits."""
        return NOMINAL if self.nominal_terms is None else nominal_coefficients(self.nominal_terms)

    def schedule(self, amplitudes=None) -> dict:
        return load_schedule({"positions_deg": TABLE1_DEG.tolist(),
                              "table_amplitudes_g": list(amplitudes or self.table_amplitudes_g),
                              "dwell_s": self.dwell_s, "sample_s": self.sample_s})


def _noise_free(params, s):
    """Noise-free angles (A, P, n, 3)."""
    rec = simulate_schedule(params, s, jax.random.key(0), noise_arcsec=0.0, accel_noise_g=0.0)
    n_a, n_p = len(s["table_amplitudes_g"]), len(s["positions_deg"])
    return np.asarray(rec.y)[:, :3].reshape(n_a, n_p, -1, 3)


def _reduce(x, n_blocks, k_train):
    """Block means of one dwell's samples (n, ...), centred by the train-block mean; the train
    rows and the block sizes."""
    groups = np.array_split(np.arange(x.shape[0]), n_blocks)
    b = np.stack([x[g].mean(0) for g in groups])
    b = b - b[:k_train].mean(0)
    return b[:k_train], np.array([len(g) for g in groups[:k_train]])


def mean_families(design: PlatformDesign | None = None) -> tuple:
    """The in-library case families of ``design``: the catalogue the diagnosis screens (the
    default nominal: :data:`MEAN_FAMILIES`; a smaller one: each coefficient it leaves out, and
    the four non-drift-law effects)."""
    design = design or PlatformDesign()
    if design.nominal_terms is None:
        return MEAN_FAMILIES
    return tuple(platform_library(design.nominal_terms))


class _TrainRows:
    """The truth side's train rows of a test: its whitening and the nominal projector."""

    def __init__(self, design, s, params0):
        self.design, self.s = design, s
        self.k_train = design.blocks - int(round(design.holdout * design.blocks))
        y0 = _noise_free(params0, s)
        ts = jnp.asarray(dwell_times(s))
        cols = []
        for a, conds in enumerate(schedule_conditions(s)):
            for p in range(y0.shape[1]):
                c = jax.tree.map(lambda x, p=p: x[p], conds)
                _, f = position_design(ts, jnp.asarray(y0[a, p]), c)
                fb, sizes = _reduce(np.asarray(f), design.blocks, self.k_train)
                cols.append(fb * np.sqrt(sizes)[:, None, None])
        nominal = design.nominal_names()
        idx = [COEFF_NAMES.index(n) for n in nominal]
        scales = _RIG.param_space.scales(nominal)
        jn = np.concatenate(cols)[:, :, idx].reshape(-1, len(nominal)) * scales
        self.sigma = design.noise_arcsec * units.ARCSEC
        self.proj = projector(jn / self.sigma)
        self.y0 = y0

    def whitened(self, dy, projected: bool = True):
        """Train rows of a change of the angles (A, P, n, 3), whitened, nominal projected out
        (``projected=False``: not)."""
        rows = []
        for a in range(dy.shape[0]):
            for p in range(dy.shape[1]):
                b, sizes = _reduce(dy[a, p], self.design.blocks, self.k_train)
                rows.append(b * np.sqrt(sizes)[:, None])
        w = np.concatenate(rows).reshape(-1, 1) / self.sigma
        return (self.proj(w) if projected else w)[:, 0]


def generate(out_dir, n_cases: int, *, seed: int = 0, design: PlatformDesign | None = None,
             lambdas=(8.0, 16.0, 32.0, 64.0), null_fraction: float = 0.3,
             families=None) -> list:
    """Write ``n_cases`` blind platform test records into ``out_dir`` and the sealed manifest."""
    design = design or PlatformDesign()
    sealer = Sealer(out_dir, seed)
    rng = sealer.rng
    space = _RIG.param_space
    s = design.schedule()
    span = len(s["table_amplitudes_g"]) * len(s["positions_deg"]) * dwell_span(s)
    means = mean_families(design)
    structural = STRUCTURAL if design.nominal_terms is None else ()
    fams = list(families or (means + structural + OUT_OF_LIBRARY))
    unknown = [f for f in fams if f not in means + structural + OUT_OF_LIBRARY]
    if unknown:
        raise ValueError(f"families {unknown} are not case families of this design; use some of "
                         f"{', '.join(means + structural + OUT_OF_LIBRARY)}")
    key = jax.random.key(seed)
    for i in range(n_cases):
        family, lam = sealer.draw(i, fams, lambdas, null_fraction)
        nominal = {k: float(space[k].scale * rng.standard_normal())
                   for k in design.nominal_names()}
        p = space.make(nominal)
        truth = {"family": family, "lambda": lam if family not in ("null",) + STRUCTURAL
                 else 0.0}
        sched, out_term = s, None
        if family in means:
            rows = _TrainRows(design, s, p)
            names = ((family,) if family in COEFF_NAMES
                     else tuple(f"{_PARAMS[family]}_{ax}" for ax in "xyz"))
            if family == "warmup_transient":
                p["tau_w"] = jnp.asarray(float(np.exp(rng.uniform(np.log(span / 30),
                                                                  np.log(span / 3)))))
                truth["tau_w_min"] = float(p["tau_w"]) / 60.0
            sc = space.scales(names)
            d = rng.standard_normal(len(names)) * sc
            unit = p | {k: jnp.asarray(v) for k, v in zip(names, d, strict=True)}
            lam1 = float(np.sum(rows.whitened(_noise_free(unit, s) - rows.y0) ** 2))
            coef = d * np.sqrt(lam / lam1)
            # each coefficient's column (the model is linear in them), for the truth side of
            # the confounding recall / precision
            jb = np.stack([rows.whitened(_noise_free(p | {k: jnp.asarray(c)}, s) - rows.y0,
                                         projected=False) / c for k, c in zip(names, sc)], 1)
            truth |= truth_visibility(jb, rows.proj(jb))
            for k, c in zip(names, coef, strict=True):
                p[k] = jnp.asarray(c)
            truth["coefficients"] = {k: float(space[k].to_display(p[k])) for k in names}
        elif family in STRUCTURAL:
            sched = design.schedule(design.table_amplitudes_g[1:2])
            d = rng.standard_normal(3)
            for ax, v in zip("xyz", d):
                p[f"D_oo_{ax}"] = jnp.asarray(float(v * space[f"D_oo_{ax}"].scale))
            truth["coefficients"] = {f"D_oo_{ax}": float(space[f"D_oo_{ax}"].to_display(
                p[f"D_oo_{ax}"])) for ax in "xyz"}
        elif family in OUT_OF_LIBRARY:
            rows = _TrainRows(design, s, p)
            shape = _ool_shape(rng, family, s, rows.y0.shape)
            amp = np.sqrt(lam / float(np.sum(rows.whitened(shape) ** 2)))
            out_term = amp * shape
            truth["amplitude_arcsec"] = float(amp / units.ARCSEC)
        key, sub = jax.random.split(key)
        rec = simulate_schedule(p, sched, sub, noise_arcsec=design.noise_arcsec)
        if out_term is not None:
            y = np.asarray(rec.y).copy()
            y[:, :3] += out_term.reshape(-1, 3)
            rec = type(rec)(rec.t, jnp.asarray(y), rec.channels, rec.attrs)
        truth["nominal"] = {k: float(space[k].to_display(v)) for k, v in nominal.items()}
        sealer.add(rec, truth)
    return sealer.close(design)


def _ool_shape(rng, family, s, shape):
    """Unit (1 rad) out-of-library term on the angles, (A, P, n, 3)."""
    out = np.zeros(shape)
    n_a, n_p, n = shape[:3]
    ts = dwell_times(s)
    t_test = (np.arange(n_a * n_p)[:, None] * dwell_span(s) + ts[None, :]).reshape(n_a, n_p, n)
    if family == "readout_line":
        out[..., 2] = np.sin(2 * np.pi * t_test / 1200.0 + rng.uniform(0, 2 * np.pi))
    elif family == "readout_step":
        a, p = rng.integers(n_a), rng.integers(n_p)
        k = int(rng.uniform(0.2, 0.6) * n)
        out[a, p, k:, 0] = 1.0
    else:
        raise ValueError(f"unknown out-of-library family {family!r}")
    return out


def run(case_dir, *, design: PlatformDesign | None = None, progress=None,
        baselines: bool = False, refit_all: bool = True, prior: str | None = None) -> list:
    """Diagnose every record in ``case_dir`` (never reading ``sealed/``) with the design's
    split and nominal, refitting every catalogue effect as well (the scorer's oracle). Records
    on one amplitude (the structural cases) have no design shift and keep the same-design
    split. ``baselines``: B2 refit-all + BIC per record as well (goal G10's comparison);
    ``refit_all=False``: no refit of every effect inside the diagnosis (no G7 oracle);
    ``prior``: the diagnosis' Bayes-factor prior (and B2's)."""
    design = design or PlatformDesign()
    kw = {} if design.nominal_terms is None else {"nominal_terms": design.nominal_terms}
    return run_cases(case_dir, "platform", design.holdout, split=design.split, refit_all=refit_all,
                     progress=progress, split_for=_split_for, baselines=baselines,
                     diagnose_kw=kw, prior=prior)


def _split_for(record, split):
    amps = json.loads(record.conditions["schedule_json"])["table_amplitudes_g"]
    return split if len(amps) > 1 else "same-design"


def score(case_dir, results, separable=None, oracle_thresholds=None,
          design: PlatformDesign | None = None) -> dict:
    """Unseal and score (:func:`gyrojax.validation._harness.score_cases`)."""
    return score_cases(case_dir, results, mean_families(design), (), OUT_OF_LIBRARY,
                       structural=STRUCTURAL, separable=separable,
                       oracle_thresholds=oracle_thresholds)


# -- goal G6: design advice, closed loop ---------------------------------------------------
def advised_amplitudes(label: str, amplitudes) -> list:
    """Table amplitudes (g) of the test an advice row names, from the record's own
    ``amplitudes``: ``"second amplitude X g (table)"`` adds X, ``"an added 0 g (static) run"``
    adds 0 (the labels of :meth:`gyrojax.diagnose._platform.PlatformProblem.designs`)."""
    m = re.match(r"second amplitude ([0-9.eE+-]+) g", label)
    if m:
        return list(amplitudes) + [float(m.group(1))]
    if label.startswith("an added 0 g"):
        return list(amplitudes) + [0.0]
    raise ValueError(f"advice design {label!r} is not a platform design this harness knows")


def closed_loop(case_dir, *, design: PlatformDesign | None = None, seed: int = 0,
                progress=None) -> list:
    """Goal G6 on the source's structural cases of ``case_dir`` (hidden ``D_oo`` at its
    prior scale on a single-amplitude test): :func:`~gyrojax.validation._harness.closed_loop`,
    the same instrument (the sealed truth: the nominal coefficients and ``D_oo``) run again on
    the table amplitudes the advisor's first design for ``anisoelastic_oo`` names."""
    design = design or PlatformDesign()
    space = _RIG.param_space

    def rerun(rec, truth, label, key):
        amps = json.loads(rec.conditions["schedule_json"])["table_amplitudes_g"]
        p = space.make(truth["nominal"] | truth["coefficients"], display=True)
        return simulate_schedule(p, design.schedule(advised_amplitudes(label, amps)), key,
                                 noise_arcsec=design.noise_arcsec)

    return _harness.closed_loop(case_dir, "platform", "anisoelastic_oo", rerun,
                                lambda t: t["coefficients"], holdout=design.holdout, seed=seed,
                                progress=progress)
