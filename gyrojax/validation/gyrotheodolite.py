"""Blind validation harness for the gyrotheodolite diagnosis (docs/diagnosis.md).

:func:`generate` writes north-seeking runs (``case_<index>.nc``: channel ``alpha`` with the
latitude as an attribute) and the sealed manifest beside them (see :mod:`.bench`). Each case
draws the test parameters - index offset ~ U(-60, 60) arcsec, release angle ~ N(0, 10 arcmin),
stiffness error kappa ~ N(0, 0.05), damping F_KC within 10 % - adds a hidden effect, integrates
the rig (1) with diffrax and adds white pick-off noise.

Case families: ``null``; the visible catalogue effects (``torque_ramp``, ``drift_transient`` with
a log-uniform decay time in [3, 30] min, ``torque_step`` with a uniform onset), at noncentrality
8/16/32/64; the structurally confounded ``tape_torque`` at a physical 0.5-2 nN m (the right
answer is silence: its whole effect is an index offset); and two effects the library omits:
``pickoff_line`` (a 4-min line on the pick-off, e.g. a building or HVAC oscillation) and
``pickoff_step`` (a jump of the pick-off zero). Magnitudes: ``lambda = b^T I_eff b`` on the train
split with the five test parameters projected out, computed here from the truth model through
:func:`gyrojax.estimate.least_squares.trajectory_jacobian`, not the diagnosis code.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..estimate.least_squares import trajectory_jacobian
from ..models.gyrotheodolite import (
    ODE_OPTIONS,
    TEST_PARAMS,
    GyrotheodoliteConditions,
    GyrotheodoliteRig,
)
from ..record import BenchRecord
from ..simulate import integrate
from ._harness import projector, run_cases, score_cases, sealed_localisation
from ._scoring import Sealer, onset_crb, truth_visibility

__all__ = ["GyrotheodoliteDesign", "generate", "run", "score", "MEAN_FAMILIES",
           "OUT_OF_LIBRARY", "STRUCTURAL"]

MEAN_FAMILIES = ("torque_ramp", "drift_transient", "torque_step")
STRUCTURAL = ("tape_torque",)
OUT_OF_LIBRARY = ("pickoff_line", "pickoff_step")
_RIG = GyrotheodoliteRig()
_GRID = {"drift_transient": "tau_tr", "torque_step": "t_step"}


@dataclasses.dataclass(frozen=True)
class GyrotheodoliteDesign:
    """A north-seeking run of ``minutes`` at ``sample_s`` with ``noise_arcsec`` pick-off noise."""

    minutes: float = 40.0
    sample_s: float = 1.0
    noise_arcsec: float = 1.0
    latitude_deg: float = 50.45
    holdout: float = 0.25

    @property
    def conditions(self) -> GyrotheodoliteConditions:
        return GyrotheodoliteConditions.create(self.latitude_deg)

    @property
    def ts(self) -> np.ndarray:
        return np.arange(0.0, self.minutes * 60 + 0.5 * self.sample_s, self.sample_s)

    @property
    def n_train(self) -> int:
        """Samples in the train part (the diagnosis holds out the last ``holdout``)."""
        n = len(self.ts)
        return n - int(round(self.holdout * n))


def generate(out_dir, n_cases: int, *, seed: int = 0,
             design: GyrotheodoliteDesign | None = None, lambdas=(8.0, 16.0, 32.0, 64.0),
             null_fraction: float = 0.3, families=None) -> list[Path]:
    """Write ``n_cases`` blind north-seeking runs into ``out_dir`` and the sealed manifest."""
    design = design or GyrotheodoliteDesign()
    sealer = Sealer(out_dir, seed)
    rng = sealer.rng
    cond = design.conditions
    space = _RIG.param_space
    ts = design.ts
    n_train = design.n_train
    sigma = design.noise_arcsec * units.ARCSEC
    fams = list(families or (MEAN_FAMILIES + STRUCTURAL + OUT_OF_LIBRARY))
    key = jax.random.key(seed)
    attrs = (("latitude_deg", design.latitude_deg), ("rig", "gyrotheodolite"))
    for i in range(n_cases):
        family, lam = sealer.draw(i, fams, lambdas, null_fraction)
        nominal = {"index_offset": rng.uniform(-60, 60) * units.ARCSEC,
                   "alpha0": 10 * units.ARCMIN * rng.standard_normal(),
                   "kappa": 0.05 * rng.standard_normal(),
                   "F_KC": 3e-4 * (1 + 0.1 * rng.standard_normal())}
        p = _RIG.default_params(**nominal)
        truth = {"family": family, "lambda": lam if family not in ("null",) + STRUCTURAL
                 else 0.0}
        out_term = np.zeros((len(ts), 1))
        if family in MEAN_FAMILIES + OUT_OF_LIBRARY:
            jn = np.asarray(trajectory_jacobian(_RIG, p, cond, jnp.asarray(ts), TEST_PARAMS, **ODE_OPTIONS))
            proj = projector(jn[:n_train] * space.scales(TEST_PARAMS) / sigma)
        if family in MEAN_FAMILIES:
            gpar = _GRID.get(family)
            if gpar == "tau_tr":
                p[gpar] = jnp.asarray(60 * float(np.exp(rng.uniform(np.log(3.0), np.log(30.0)))))
            elif gpar == "t_step":
                p[gpar] = jnp.asarray(float(ts[0] + rng.uniform(0.15, 0.7)
                                            * (ts[n_train - 1] - ts[0])))
            names = tuple(k for k in space.effect_names(family) if k != gpar)
            jb = np.asarray(trajectory_jacobian(_RIG, p, cond, jnp.asarray(ts), names, **ODE_OPTIONS))
            jt = proj(jb[:n_train] / sigma)
            d = rng.choice([-1.0, 1.0], size=len(names))
            coef = np.sqrt(lam / float(d @ (jt.T @ jt) @ d)) * d
            for k, c in zip(names, coef, strict=True):
                p[k] = jnp.asarray(c)
            truth["coefficients"] = {k: float(space[k].to_display(p[k])) for k in names}
            truth |= truth_visibility(jb[:n_train] / sigma, jt)
            if gpar:
                truth[gpar] = float(space[gpar].to_display(p[gpar]))
            if gpar:  # the grid value's Cramér-Rao deviation, the sizes as nuisance: the
                # onset in minutes, the decay time in log time (d/d log tau = tau d/dtau)
                crb_name, unit = {"t_step": ("onset_crb_min", 60.0),
                             "tau_tr": ("decay_crb_log", float(p[gpar]))}[gpar]
                jo = np.asarray(trajectory_jacobian(_RIG, p, cond, jnp.asarray(ts), (gpar,),
                                                    **ODE_OPTIONS))
                truth[crb_name] = onset_crb(
                    np.c_[jn[:n_train] * space.scales(TEST_PARAMS), jb[:n_train]] / sigma,
                    jo[:n_train, 0] * unit / sigma)
        elif family in STRUCTURAL:
            p["M_tape"] = jnp.asarray(rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 2.0) * 1e-9)
            truth["coefficients"] = {"M_tape": float(space["M_tape"].to_display(p["M_tape"]))}
        elif family in OUT_OF_LIBRARY:
            shape = _ool_shape(rng, family, ts, n_train)
            amp = np.sqrt(lam / float(np.sum(proj(shape[:n_train] / sigma) ** 2)))
            out_term = amp * shape
            truth["amplitude_arcsec"] = float(amp / units.ARCSEC)
        key, sub = jax.random.split(key)
        y = np.asarray(integrate(_RIG, p, cond, jnp.asarray(ts), **ODE_OPTIONS))
        y = y + out_term + sigma * np.asarray(jax.random.normal(sub, y.shape))
        truth["nominal"] = {k: float(space[k].to_display(v)) for k, v in nominal.items()}
        sealer.add(BenchRecord(ts, y, ("alpha",), attrs), truth)
    return sealer.close(design)


def _ool_shape(rng, family, ts, n_train):
    """Unit-amplitude (1 rad) shape of an out-of-library pick-off term, ``(n, 1)``."""
    if family == "pickoff_line":
        return np.sin(2 * np.pi * ts / 240.0 + rng.uniform(0, 2 * np.pi))[:, None]
    if family == "pickoff_step":
        t0 = ts[0] + rng.uniform(0.2, 0.7) * (ts[n_train - 1] - ts[0])
        return (ts >= t0).astype(float)[:, None]
    raise ValueError(f"unknown out-of-library family {family!r}")


def run(case_dir, *, design: GyrotheodoliteDesign | None = None, progress=None,
        prior: str | None = None) -> list:
    """Diagnose every record in ``case_dir`` (never reading ``sealed/``); ``prior``: the
    diagnosis' Bayes-factor prior."""
    design = design or GyrotheodoliteDesign()
    return run_cases(case_dir, "gyrotheodolite", design.holdout, progress=progress, prior=prior)


def score(case_dir, results, separable=None, oracle_thresholds=None) -> dict:
    """Unseal and score (:func:`gyrojax.validation._harness.score_cases`); a hidden tape torque
    must stay unattributed (``structural_silent``)."""
    return score_cases(case_dir, results, MEAN_FAMILIES, (), OUT_OF_LIBRARY,
                       structural=STRUCTURAL, separable=separable,
                       oracle_thresholds=oracle_thresholds)


def localisation_scores(case_dir, results, *, lam_min: float = 32.0) -> dict:
    """Goal G8 over the in-library cases at ``lambda >= lam_min``: a torque step's onset at
    its largest score within 5 % of the record of the truth, and a drift transient's decay time
    within one step of its geometric grid (``_gyrotheodolite.TRANSIENT_TIMES_MIN``)."""
    from ..diagnose import GYROTHEODOLITE_TRANSIENT_TIMES_MIN as TRANSIENT_TIMES_MIN

    return sealed_localisation(case_dir, results, lam_min=lam_min,
                               step=("torque_step", "t_step"),
                               transient=("drift_transient", "tau_tr"),
                               decay_grid=TRANSIENT_TIMES_MIN, crb_key="onset_crb_min",
                               decay_crb_key="decay_crb_log",
                               record_length=lambda r: r["record_s"] / 60)
