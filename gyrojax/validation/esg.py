"""Blind validation harness for the gap diagnosis (docs/diagnosis.md), ESG rig.

:func:`generate` writes records (``case_<index>.nc``) and, separately, a sealed manifest
(``sealed/manifest.json``) keyed by each record file's SHA-256: the hidden effect, its
coefficients and its noncentrality. The diagnosis reads only the record files (the diagnosis
package never imports the validation package; a test enforces it). :func:`run` diagnoses every case, also
runs two baselines on the same records (B1: Ljung-Box whiteness of the nominal residual; B2:
refit every candidate and pick by BIC), and :func:`score` unseals and computes the metrics of
docs/goals.md with Monte Carlo standard errors.

Case families: ``null``; each library effect; ``two_effects``; and two effects the library omits
(``heater_cycle``: a 2 h square wave on the gimbal angles; ``hvac_line``: a 5 h line).
Magnitudes: the noncentrality ``lambda = b^T I_eff b`` of the hidden effect on the train split
with the nominal parameters projected out, computed here from the truth model.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..diagnose import (
    ESG_LIBRARY,
    ESG_TRANSIENT_TIMES_H,
    ljung_box,
    onset_grid,
)
from ..estimate import trajectory_jacobian
from ..io import load_record
from ..models.esg import ESGConditions, ESGRig
from ..record import BenchRecord
from ._scoring import (
    Sealer,
    calibration,
    confounding_scores,
    grid_localisation,
    heldout_reduction,
    localisation_fields,
    multiplicity_fields,
    onset_crb,
    ool_scores,
    oracle_choice,
    oracle_power,
    plain_bh_far,
    projector,
    ranking_scores,
    rate,
    ratio_rate,
    refit_all_baseline,
    remainder_after_library,
    sha256_file,
    tau_band_scores,
    top3_effects,
    top_effect,
    truth_visibility,
)

__all__ = ["generate", "run", "score", "LIBRARY_FAMILIES", "OUT_OF_LIBRARY"]


LIBRARY_FAMILIES = ("rotor_tilt", "base_misalignment", "drift_transient", "drift_ramp",
                    "drift_step", "diurnal_line")


OUT_OF_LIBRARY = ("heater_cycle", "hvac_line")


SIDEREAL_DAY = 2 * math.pi / units.EARTH_RATE


_TRUTH_RIG = ESGRig(base_param="rotvec")


_EFFECT_PARAMS = {
    "rotor_tilt": ("theta1", "theta2"),
    "base_misalignment": ("dchi1", "dchi2", "dchi3"),
    "drift_transient": ("dm11_0", "dm12_0", "dm21_0", "dm22_0", "dmc1_0", "dmc2_0"),
    "drift_ramp": ("rmc1", "rmc2"),
    "drift_step": ("smc1", "smc2"),
}


@dataclasses.dataclass(frozen=True)
class Design:
    """A test design of the blind suite (docs/goals.md, D3-like): scheme, latitude, length, noise."""

    scheme: str = "vertical"
    latitude_deg: float = 55.75
    hours: float = 24.0
    sample_s: float = 60.0
    noise_arcsec: float = 1.0
    holdout: float = 0.25
    # goal G1's robustness suite: flicker on each gimbal angle (the white nominal noise model
    # omits it, the white+flicker one models it), bias-instability coefficient B (Allan
    # deviation flat at ~0.664 B from ~2 samples to ~2000), arcsec; 0 = none
    flicker_arcsec: float = 0.0
    # "gm": the GM sum the diagnosis' white+flicker model assumes (models.imu._flicker);
    # "spectral": 1/f by spectral synthesis (models.imu.flicker_spectral), another shape
    flicker_kind: str = "gm"

    def __post_init__(self):
        if self.flicker_kind not in ("gm", "spectral"):
            raise ValueError(f"flicker_kind={self.flicker_kind!r}; use 'gm' or 'spectral'")

    @property
    def ts(self):
        return np.arange(int(round(self.hours * 3600 / self.sample_s)) + 1) * self.sample_s


@jax.jit
def _square_wave(t):
    return jnp.sign(jnp.sin(2 * jnp.pi * t / 7200.0))


def _truth_params(rng, design):
    sp = _TRUTH_RIG.param_space
    vals = {n: rng.uniform(-0.2, 0.2) for n in ("m11", "m12", "m21", "m22", "mc1", "mc2")}
    vals["alpha10"] = rng.uniform(-20, 20)
    vals["alpha20"] = rng.uniform(-20, 20)
    return sp.make(vals, display=True)


def _output_columns(family, t):
    """Output-side signatures (n, c, k) in rad per unit coefficient."""
    if family == "diurnal_line":
        w = 2 * math.pi / SIDEREAL_DAY
        cols = np.zeros((len(t), 2, 4))
        for ch in range(2):
            cols[:, ch, 2 * ch] = np.sin(w * t) * units.ARCSEC
            cols[:, ch, 2 * ch + 1] = np.cos(w * t) * units.ARCSEC
        return cols
    raise KeyError(family)


def _model_jac(params, cond, ts, names):
    return np.asarray(trajectory_jacobian(_TRUTH_RIG, params, cond, jnp.asarray(ts), names))


def _efficient(jn, jb):
    jt = projector(jn)(jb)
    return jt.T @ jt


def _hidden(rng, family, p, cond, design, lam):
    """Set the hidden effect into ``p`` (or return an output term) with noncentrality ``lam``."""
    ts = design.ts
    n_train = len(ts) - int(round(design.holdout * len(ts)))
    sigma = design.noise_arcsec * units.ARCSEC
    nominal = _TRUTH_RIG.param_space.nominal_names()
    truth = {"family": family}
    p = dict(p)
    out_term = np.zeros((len(ts), 2))
    if family in _EFFECT_PARAMS or family in OUT_OF_LIBRARY:
        if family == "drift_transient":
            tau_h = float(rng.uniform(0.25, 3.0))
            p["k_tr"] = jnp.asarray(1.0 / (tau_h * 3600 * units.EARTH_RATE))
            truth["decay_time_h"] = tau_h
        if family == "drift_step":
            onset_h = float(rng.uniform(0.1, 0.65) * design.hours)
            p["t_step"] = jnp.asarray(onset_h * 3600 * units.EARTH_RATE)
            truth["onset_h"] = onset_h
        if family in OUT_OF_LIBRARY:
            jn = _model_jac(p, cond, ts[:n_train], nominal) / sigma
            jb = _ool_columns(family, ts)[: n_train * 2] / sigma
            b = np.ones(1)
        else:
            names = _EFFECT_PARAMS[family]
            j = _model_jac(p, cond, ts[:n_train], nominal + names) / sigma
            jn, jb = j[:, : len(nominal)], j[:, len(nominal):]
            b = rng.standard_normal(len(names))
        info = _efficient(jn, jb)
        scale = math.sqrt(lam / float(b @ info @ b))
        b = b * scale
        if family in OUT_OF_LIBRARY:
            out_term = (_ool_columns(family, ts)[:, 0] * b[0]).reshape(len(ts), 2)
            truth["amplitude"] = float(b[0])
            truth |= remainder_after_library(jb[:, 0] * b[0], jn, _library_columns(
                p, cond, ts, n_train, sigma))
        else:
            for name, v in zip(_EFFECT_PARAMS[family], b):
                p[name] = jnp.asarray(v)
            truth["coefficients"] = {n: float(_TRUTH_RIG.param_space[n].to_display(v))
                                     for n, v in zip(_EFFECT_PARAMS[family], b)}
            truth |= truth_visibility(jb, projector(jn)(jb))
            if family == "drift_step":
                dj = [_model_jac(p | {"t_step": p["t_step"] + d}, cond, ts[:n_train], names)
                      for d in (-0.5 * design.sample_s * units.EARTH_RATE,
                                0.5 * design.sample_s * units.EARTH_RATE)]
                # d(response)/d(onset): the sizes' columns differenced over one sample
                jt = (dj[1] - dj[0]) @ b / (design.sample_s * units.EARTH_RATE * sigma)
                truth["onset_crb_h"] = onset_crb(np.c_[jn, jb], jt) / units.EARTH_RATE / 3600
            if family == "drift_transient":  # d/d(log tau) = -k d/dk, the sizes as nuisance
                jk = _model_jac(p, cond, ts[:n_train], ("k_tr",))[:, 0]
                truth["decay_crb_log"] = onset_crb(np.c_[jn, jb], -float(p["k_tr"]) * jk / sigma)
    elif family == "diurnal_line":
        jn = _model_jac(p, cond, ts[:n_train], nominal) / sigma
        cols = _output_columns(family, ts)
        jb = cols[:n_train].reshape(n_train * 2, 4) / sigma
        b = rng.standard_normal(4)
        b = b * math.sqrt(lam / float(b @ _efficient(jn, jb) @ b))
        out_term = cols @ b
        truth["coefficients_arcsec"] = [float(x) for x in b]
        truth |= truth_visibility(jb, projector(jn)(jb))
    elif family != "null":
        raise ValueError(f"unknown case family {family!r}")
    truth["lambda"] = float(lam) if family != "null" else 0.0
    return p, out_term, truth


def _library_columns(p, cond, ts, n_train, sigma) -> dict:
    """Truth-side whitened columns of every library effect on the train rows ``ts[:n_train]``
    (family -> one block per grid value: the diagnosis' decay-time grid and its onset grid,
    ``_signatures.onset_grid`` of the record)."""
    onsets = onset_grid(np.asarray(ts) / 3600, n_train)
    rows = ts[:n_train]
    grids = {"drift_transient": len(ESG_TRANSIENT_TIMES_H), "drift_step": len(onsets)}
    names = tuple(n for v in _EFFECT_PARAMS.values() for n in v)
    cols = {}
    for g in range(max(grids.values())):
        # the k-th pass sets each gridded effect to its k-th value (the last one past its end);
        # an effect's columns do not depend on another's grid value (every amplitude is 0 here)
        tau_h = ESG_TRANSIENT_TIMES_H[min(g, len(ESG_TRANSIENT_TIMES_H) - 1)]
        pg = dict(p) | {"k_tr": jnp.asarray(1.0 / (tau_h * 3600 * units.EARTH_RATE)),
                        "t_step": jnp.asarray(onsets[min(g, len(onsets) - 1)] * 3600
                                              * units.EARTH_RATE)}
        j = _model_jac(pg, cond, rows, names) / sigma
        k = 0
        for fam, fn in _EFFECT_PARAMS.items():
            if g < grids.get(fam, 1):
                cols.setdefault(fam, []).append(j[:, k:k + len(fn)])
            k += len(fn)
    cols["diurnal_line"] = [_output_columns("diurnal_line", rows).reshape(n_train * 2, 4) / sigma]
    return cols


def _ool_columns(family, ts):
    """Signature (n*c, 1) of an out-of-library output term at 1 arcsec amplitude: a 2 h
    square-wave heater cycle, or a 5 h HVAC line, on both gimbal angles (unit-norm mix)."""
    if family == "heater_cycle":
        prof = np.asarray(_square_wave(jnp.asarray(ts)))
    else:
        prof = np.sin(2 * math.pi * ts / (5 * 3600.0))
    return (np.stack([prof, 0.6 * prof], axis=1) * units.ARCSEC).reshape(-1, 1)


def generate(out_dir, n_cases: int, *, seed: int = 0, design: Design | None = None,
             lambdas=(8.0, 16.0, 32.0, 64.0), null_fraction: float = 0.25,
             families=None) -> list[Path]:
    """Write ``n_cases`` blind records into ``out_dir`` and the sealed manifest beside them."""
    design = design or Design()
    sealer = Sealer(out_dir, seed)
    rng = sealer.rng
    cond = ESGConditions.create(design.scheme, design.latitude_deg)
    fams = list(families or (LIBRARY_FAMILIES + OUT_OF_LIBRARY + ("two_effects",)))
    key = jax.random.key(seed)
    sp = _TRUTH_RIG.param_space
    for i in range(n_cases):
        family, lam = sealer.draw(i, fams, lambdas, null_fraction)
        p = _truth_params(rng, design)
        if family == "two_effects":
            a, b = rng.choice(len(LIBRARY_FAMILIES) - 1, 2, replace=False)
            pa = [LIBRARY_FAMILIES[a], LIBRARY_FAMILIES[b]]
            p, out1, t1 = _hidden(rng, pa[0], p, cond, design, lam)
            p, out2, t2 = _hidden(rng, pa[1], p, cond, design, lam)
            out_term, truth = out1 + out2, {"family": "two_effects", "effects": [t1, t2],
                                            "lambda": lam}
        elif family == "angle_random_walk":
            out_term, truth = _angle_random_walk(rng, design, lam)
        else:
            p, out_term, truth = _hidden(rng, family, p, cond, design, lam)
        truth["nominal"] = {k: float(sp[k].to_display(p[k])) for k in sp.nominal_names()}
        key, sub = jax.random.split(key)
        if design.flicker_arcsec > 0:
            from ..models.imu import _flicker, flicker_spectral

            sub, kf = jax.random.split(sub)
            b = np.full(2, design.flicker_arcsec)
            if design.flicker_kind == "spectral":
                fl = flicker_spectral(kf, len(design.ts), design.sample_s, b)
            else:
                fl = _flicker(kf, len(design.ts), design.sample_s, b, t0=design.sample_s)
            out_term = out_term + np.asarray(fl) * units.ARCSEC
        sealer.add(_simulate_case(p, design, sub, out_term), truth)
    return sealer.close(design)


def _simulate_case(p, design, key, out_term=0.0):
    """A record of the truth rig ``p`` on ``design`` (its scheme, latitude, length and noise)."""
    from ..simulate import simulate

    cond = ESGConditions.create(design.scheme, design.latitude_deg)
    rec = simulate(_TRUTH_RIG, p, cond, jnp.asarray(design.ts), key=key,
                   noise_std=design.noise_arcsec * units.ARCSEC,
                   attrs=dict(scheme=design.scheme, latitude_deg=design.latitude_deg))
    return BenchRecord(rec.t, rec.y + jnp.asarray(out_term), rec.channels, rec.attrs)


# -- goal G6: design advice, closed loop ---------------------------------------------------
# the hidden effects of the closed loops at the diagnosis' own prior scales (arcsec: 10 arcmin
# of rotor tilt, the source's figure; 5 arcsec per coefficient of the sidereal-day line)
G6_PRIOR = {k: ESG_LIBRARY[k][1] for k in ("rotor_tilt", "diurnal_line")}


_LINE_NAMES = ("alpha1_sin", "alpha1_cos", "alpha2_sin", "alpha2_cos")


def generate_closed_loop(out_dir, n_cases: int, family: str = "rotor_tilt", *, seed: int = 0,
                         design: Design | None = None, fractions=(1.0,),
                         schemes=None) -> list[Path]:
    """Sealed cases for the G6 closed loop: per case a scheme (``schemes``, default the four,
    in turn), the nominal drift and initial angles drawn as in :func:`generate`, and the hidden
    ``family`` in a random direction at ``fraction`` of its prior scale (``fractions`` in turn):
    ``rotor_tilt``, ``|theta| = fraction x 10 arcmin``; ``diurnal_line``, the four line
    coefficients (sin, cos on each gimbal angle) with RMS ``fraction x 5 arcsec``. The manifest
    keeps the whole instrument (display units) and the line so the case can be run again on
    another design."""
    from ..models.esg import SCHEMES

    if family not in G6_PRIOR:
        raise ValueError(f"closed-loop family {family!r}; known: {sorted(G6_PRIOR)}")
    design = design or Design()
    schemes = tuple(schemes or SCHEMES)
    sealer = Sealer(out_dir, seed)
    rng = sealer.rng
    key = jax.random.key(seed)
    sp = _TRUTH_RIG.param_space
    for i in range(n_cases):
        d = dataclasses.replace(design, scheme=schemes[i % len(schemes)])
        frac = float(fractions[(i // len(schemes)) % len(fractions)])
        p = dict(_truth_params(rng, d))
        line = np.zeros(4)
        if family == "rotor_tilt":
            phi = rng.uniform(0.0, 2 * math.pi)
            size = frac * G6_PRIOR[family] * units.ARCSEC
            p["theta1"], p["theta2"] = (jnp.asarray(size * math.cos(phi)),
                                        jnp.asarray(size * math.sin(phi)))
        else:
            line = rng.standard_normal(4)
            line *= frac * G6_PRIOR[family] / np.sqrt(np.mean(line ** 2))
        key, sub = jax.random.split(key)
        sealer.add(_simulate_case(p, d, sub, _output_columns("diurnal_line", d.ts) @ line),
                   {"family": family, "scheme": d.scheme, "hours": d.hours,
                    "fraction_of_prior": frac,
                    "instrument": {k: float(sp[k].to_display(p[k])) for k in sp.names},
                    "line_arcsec": dict(zip(_LINE_NAMES, map(float, line)))})
    return sealer.close(design)


def advised_design(label: str, design: Design) -> Design:
    """The test an ESG advice row names, from the record's ``design``: ``"<scheme> scheme"``
    remounts on that scheme, ``"<H> h record"`` records H hours, both comma-joined do both
    (the labels of :meth:`gyrojax.diagnose._esg.ESGProblem.designs`)."""
    from ..models.esg import SCHEMES

    out = design
    for part in label.split(", "):
        words = part.split()
        if len(words) == 2 and words[1] == "scheme" and words[0] in SCHEMES:
            out = dataclasses.replace(out, scheme=words[0])
        elif len(words) == 3 and words[1:] == ["h", "record"]:
            out = dataclasses.replace(out, hours=float(words[0]))
        else:
            raise ValueError(f"advice design {label!r} is not an ESG design this harness knows")
    return out


def closed_loop(case_dir, hidden: str = "rotor_tilt", *, design: Design | None = None,
                seed: int = 0, progress=None) -> list:
    """Goal G6 on the cases of :func:`generate_closed_loop` (``hidden``: their family):
    :func:`~gyrojax.validation._harness.closed_loop`, the same instrument (every sealed
    parameter and the line) run again on the design the advisor ranks first for ``hidden``.
    ``rotor_tilt`` is G6's "equatorial / arbitrary alpha_2 -> theta"; ``diurnal_line`` on a
    short record, its ">= 24 h -> diurnal vs ramp"."""
    from . import _harness

    design = design or Design()
    sp = _TRUTH_RIG.param_space

    def rerun(rec, truth, label, key):
        own = dataclasses.replace(design, scheme=truth["scheme"], hours=truth["hours"])
        d = advised_design(label, own)
        line = np.array([truth["line_arcsec"][k] for k in _LINE_NAMES])
        return _simulate_case(sp.make(truth["instrument"], display=True), d, key,
                              _output_columns("diurnal_line", d.ts) @ line)

    def coefficients(t):
        if hidden == "rotor_tilt":
            return {k: t["instrument"][k] for k in ("theta1", "theta2")}
        return t["line_arcsec"]

    return _harness.closed_loop(case_dir, "esg", hidden, rerun, coefficients,
                                holdout=design.holdout, seed=seed, progress=progress,
                                load=lambda path: load_record(path, channels=("alpha1", "alpha2")))


def _angle_random_walk(rng, design, z):
    """A noise-model effect outside the white-noise nominal model: a random walk on both gimbal
    angles (a gyro angle random walk), its step set so that the longest tau band of the gap map
    (cluster size ``m``, ``K`` clusters of the train rows) expects an Allan excess of ``z`` null
    standard deviations: ``(K - 1) q^2 (2 m^2 + 1) / 6 = z sd0`` with ``q`` the step over the
    white level and ``sd0^2 = 2 (K - 1) + (K - 2)`` (the projection ignored)."""
    n_train = len(design.ts) - int(round(design.holdout * len(design.ts)))
    m = 2
    while n_train // (2 * m) >= 9:
        m *= 2
    k = n_train // m
    q = math.sqrt(6 * z * math.sqrt(3 * k - 4) / ((k - 1) * (2 * m * m + 1)))
    sigma = design.noise_arcsec * units.ARCSEC
    walk = np.cumsum(rng.standard_normal((len(design.ts), 2)), axis=0) * q * sigma
    dt = float(design.ts[1] - design.ts[0])
    return walk, {"family": "angle_random_walk", "lambda": float(z),
                  "step_arcsec": q * design.noise_arcsec, "band_s": m * dt}


def run(case_dir, *, design: Design | None = None, baselines: bool = True,
        refit_all: bool = True, progress=None, noise: dict | None = None,
        prior: str | None = None) -> list:
    """Diagnose every record in ``case_dir`` (never reading ``sealed/``); returns one result dict
    per case with the verdict, ranking summary, held-out gaps, timings and baseline answers
    (``refit_all=False`` skips the costly B2 and keeps B1; ``noise``: the diagnosis' noise
    model arguments, e.g. ``{"noise_model": "white+flicker"}``; ``prior``: the diagnosis'
    Bayes-factor prior, and B2's)."""
    from ..diagnose import ESGProblem, diagnose

    design = design or Design()
    results = []
    paths = sorted(Path(case_dir).glob("case_*.nc"))
    for k, path in enumerate(paths):
        rec = load_record(path, channels=("alpha1", "alpha2"))
        t0 = time.perf_counter()
        rep = diagnose(rec, holdout=design.holdout, design_advice=False, prior=prior,
                       **(noise or {}))
        t_diag = time.perf_counter() - t0
        ranking = rep.ranking
        res = {
            "sha": sha256_file(path), "file": path.name, "verdict": rep.verdict["kind"],
            "prior": rep.prior, "effects": rep.verdict.get("effects") or [],
            "ranking": [r["name"] for r in ranking],
            "posterior": {r["name"]: r["posterior"] for r in ranking},
            "p": {r["name"]: r["p"] for r in ranking},
            "flags": {r["name"]: r["flag"] for r in ranking},
            "scores": ranking_scores(ranking),
            "log_bf": {r["name"]: r["log_bf"] for r in ranking},
            "log_bf_by_lambda": {r["name"]: r["log_bf_by_lambda"] for r in ranking},
            "visible_fraction": {r["name"]: r["visible_fraction"] for r in ranking},
            "ambiguity": rep.ambiguity["set"],
            "heldout_gap_before": rep.verdict.get("heldout_gap_before"),
            "heldout_gap_after": rep.verdict.get("heldout_gap_after"),
            "null_band": rep.gap.get("heldout_null_band"),
            "null_band_after": next((rf["heldout_null_band_after"] for rf in rep.refits
                                     if rf["effects"] == (rep.verdict.get("effects") or [])),
                                    None),
            "time_diagnose_s": t_diag,
            **multiplicity_fields(rep),
            "time_screen_s": rep.timings.get("screening_s", 0.0) + rep.timings.get("jacobians_s",
                                                                                   0.0),
            "time_calibration_s": rep.timings.get("calibration_s", 0.0),
            **localisation_fields(rep),
        }
        if baselines:
            e = np.asarray(rep.residual_all)[: rep.n_train]
            lb = [ljung_box(e[:, ch], 20)[1] for ch in range(e.shape[1])]
            res["b1_detect"] = bool(min(lb) * len(lb) < 0.05)
        if baselines and refit_all:
            prob = ESGProblem(rec, holdout=design.holdout, **(noise or {}))
            res |= refit_all_baseline(prob, ranking, np.asarray(rep.noise["std"]), prior=rep.prior)
        results.append(res)
        if progress is not None:
            progress(k + 1, len(paths))
    return results


def localisation_scores(lib, *, lam_min: float = 32.0) -> dict:
    """Goal G8 over in-library (truth, result) pairs at ``lambda >= lam_min``: a step's
    screened onset within 5 % of the record of the truth (one window of the gap map's finest
    level), a transient's screened decay time within one step of the geometric grid, and a
    diurnal line found on the sidereal-day line (the frequency cell of smallest p)."""
    strong = [(t, r) for t, r in lib if t.get("lambda", 0) >= lam_min and "grid_best" in r]
    return {
        **grid_localisation(strong, step=("drift_step", "onset_h"),
                            transient=("drift_transient", "decay_time_h"),
                            decay_grid=ESG_TRANSIENT_TIMES_H,
                            record_length=lambda r: r["record_hours"], crb_key="onset_crb_h",
                            decay_crb_key="decay_crb_log"),
        "g8_line": rate([(t, r) for t, r in strong if t["family"] == "diurnal_line"],
                         lambda t, r: (r["top_line"] or "").startswith("sidereal day")),
        # how specific that is: the other families' gaps on the same line
        "g8_line_other_families": rate(
            [(t, r) for t, r in strong if t["family"] != "diurnal_line"],
            lambda t, r: (r["top_line"] or "").startswith("sidereal day")),
    }



def score(case_dir, results, separable=None, oracle_thresholds=None) -> dict:
    """Unseal the manifest and compute the metrics of docs/goals.md (rate, its Monte Carlo standard error,
    and the count behind it). ``separable``: the families whose largest projected canonical
    correlation with another is <= 0.9 on the design (for the separable top-1 of goal G3;
    default: every family)."""
    manifest = json.loads((Path(case_dir) / "sealed" / "manifest.json").read_text())["cases"]
    rows = []
    for r in results:
        truth = manifest[r["sha"]]
        rows.append((truth, r))


    nulls = [(t, r) for t, r in rows if t["family"] == "null"]
    lib = [(t, r) for t, r in rows if t["family"] in LIBRARY_FAMILIES]
    ool = [(t, r) for t, r in rows if t["family"] in OUT_OF_LIBRARY]
    two = [(t, r) for t, r in rows if t["family"] == "two_effects"]
    sep = tuple(LIBRARY_FAMILIES if separable is None else separable)
    out = {"far": rate(nulls, lambda t, r: r["verdict"] != "no-gap"),
           **plain_bh_far(nulls),
           "b1_far": rate(nulls, lambda t, r: r.get("b1_detect")),
           "b2_false_selection": rate(nulls, lambda t, r: r.get("b2_choice", "none") != "none")}
    for lam in sorted({t["lambda"] for t, _ in lib}):
        sub = [(t, r) for t, r in lib if t["lambda"] == lam]
        out[f"lambda={lam:g}"] = {
            "power": rate(sub, lambda t, r: r["verdict"] != "no-gap"),
            "top1": rate(sub, lambda t, r: r["ranking"] and top_effect(r) == t["family"]),
            "top3": rate(sub, lambda t, r: t["family"] in top3_effects(r)),
            "top1_separable": rate([(t, r) for t, r in sub if t["family"] in sep],
                                   lambda t, r: top_effect(r) == t["family"]),
            "oracle_top1": rate(sub, lambda t, r: oracle_choice(r, lam) == t["family"]),
            "oracle_top1_separable": rate([(t, r) for t, r in sub if t["family"] in sep],
                                          lambda t, r: oracle_choice(r, lam) == t["family"]),
            "oracle_efficiency": ratio_rate(sub, lambda t, r: top_effect(r) == t["family"],
                                            lambda t, r: oracle_choice(r, lam) == t["family"]),
            "oracle_power": oracle_power(sub, lam, oracle_thresholds),
            "set_coverage": rate([(t, r) for t, r in sub if r["ambiguity"]],
                                 lambda t, r: t["family"] in r["ambiguity"]),
            "mean_set_size": (float(np.mean([len(r["ambiguity"]) for t, r in sub
                                             if r["ambiguity"]]))
                              if any(r["ambiguity"] for _, r in sub) else None),
            "confident_misattribution": rate(sub, lambda t, r: max(r["posterior"].values()) > 0.9
                                             and top_effect(r) != t["family"]),
            "calibration": calibration(sub),
            "b1_power": rate(sub, lambda t, r: r.get("b1_detect")),
            "b2_top1": rate(sub, lambda t, r: r.get("b2_choice") == t["family"]),
        }
    out["calibration"] = calibration(lib)
    red = [heldout_reduction(r) for t, r in lib if r["verdict"] in ("attributed", "ambiguous")]
    red = [x for x in red if x is not None]
    out["heldout_reduction_median"] = float(np.median(red)) if red else None
    out["heldout_closure"] = rate([(t, r) for t, r in lib if r["heldout_gap_after"] is not None
                                   and r["null_band_after"] is not None],
                                  lambda t, r: r["heldout_gap_after"] <= r["null_band_after"][1])
    out["out_of_library_honest"] = rate(ool, lambda t, r: r["verdict"] in
                                        ("unexplained", "ambiguous", "no-gap")
                                        or max(r["posterior"].values()) <= 0.9)
    out |= ool_scores(ool)  # goal G9
    out |= localisation_scores(lib)  # goal G8
    out |= confounding_scores(lib)  # goal G5, practical confounding
    out |= tau_band_scores(rows)
    out["two_effects_both_named"] = rate(two, lambda t, r: {e["family"] for e in t["effects"]}
                                         <= set(r["effects"]) | set(r["ambiguity"]))
    diag = [r["time_diagnose_s"] for _, r in rows]
    scr = [r["time_screen_s"] for _, r in rows]
    refit = [r["time_refit_all_s"] for _, r in rows if "time_refit_all_s" in r]
    nref = [r["n_refits"] for _, r in rows if "n_refits" in r]
    out["cost"] = {"median_diagnose_s": float(np.median(diag)),
                   "median_screen_s": float(np.median(scr)),
                   "median_calibration_s": float(np.median(
                       [r.get("time_calibration_s", 0.0) for _, r in rows])),
                   "median_refit_all_s": float(np.median(refit)) if refit else None,
                   "n_refits": int(np.median(nref)) if nref else None}
    strong = [(t, r) for t, r in lib if t.get("lambda", 0) >= 32 and "b2_lr_choice" in r]
    out["screen_refit_agreement"] = rate(strong, lambda t, r: top_effect(r) == r["b2_lr_choice"])
    out["screen_refit_agreement_separable"] = rate(
        [(t, r) for t, r in strong if t["family"] in sep],
        lambda t, r: top_effect(r) == r["b2_lr_choice"])
    return out

