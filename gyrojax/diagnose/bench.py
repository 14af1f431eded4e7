"""Blind validation harness for the gap diagnosis (spec gap-diagnosis §5), ESG rig.

:func:`generate` writes records (``case_<index>.nc``) and, separately, a sealed manifest
(``sealed/manifest.json``) keyed by each record file's SHA-256: the hidden effect, its
coefficients and its noncentrality. The diagnosis reads only the record files (the diagnosis
package never imports this module; a test enforces it). :func:`run` diagnoses every case, also
runs two baselines on the same records (B1: Ljung-Box whiteness of the nominal residual; B2:
refit every candidate and pick by BIC), and :func:`score` unseals and computes the metrics of
§5.6 with Monte Carlo standard errors.

Case families: ``null``; each library effect; ``two_effects``; and two effects the library omits
(``heater_cycle``: a 2 h square wave on the gimbal angles; ``hvac_line``: a 5 h line).
Magnitudes: the noncentrality ``lambda = b^T I_eff b`` of the hidden effect on the train split
with the nominal parameters projected out, computed here from the truth model.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .. import units
from ..estimate.least_squares import trajectory_jacobian
from ..io import load_record, save_record, write_json
from ..models.esg import ESGConditions, ESGRig
from ..record import BenchRecord
from ._esg import ESG_LIBRARY, TRANSIENT_TIMES_H
from ._stats import (
    SHELL_DESIGN_LAMBDAS,
    _directions,
    _project,
    ljung_box,
    mix_log_bf,
    nominal_basis,
    onset_grid,
    shape_log_bf_scores,
    shell_design_log_bf,
    shell_log_bf,
    visibility_flag,
    zellner_log_bf,
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
    """A test design of the blind suite (spec §5.2, D3-like): scheme, latitude, length, noise."""

    scheme: str = "vertical"
    latitude_deg: float = 55.75
    hours: float = 24.0
    sample_s: float = 60.0
    noise_arcsec: float = 1.0
    holdout: float = 0.25
    # spec §6 G1's robustness suite: flicker on each gimbal angle (the white nominal noise model
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


# the flags of spec §4.2 stage 3 that say the nominal fit absorbs (part of) an effect: visible
# fraction < 0.05 in some direction (practically or structurally confounded, or no signature)
CONFOUNDED_FLAGS = ("practically confounded", "structurally confounded",
                    "partly structurally confounded", "no signature")


def truth_visibility(jb, jt) -> dict:
    """Truth side of spec §5.6's confounding recall and precision: the hidden effect's visible
    fraction on the train rows (the smallest ``1 - rho^2`` over its coefficient directions,
    spec §4.2 stage 3) from the whitened Jacobian ``jb`` of its coefficients at the generating
    parameters and sealed grid value, and ``jt``, the same with the nominal span projected out;
    and the flag that fraction earns. The diagnosis computes its own at its fitted nominal and
    chosen grid value, from the record."""
    jb, jt = np.asarray(jb, float), np.asarray(jt, float)
    _, _, v, null, conf = _directions(jb, jt)
    return {"visible_fraction": float(v),
            "visibility": visibility_flag(v, bool(null), jb.shape[1] - len(null), len(conf))}


def projector(jn):
    """``a -> (I - P) a`` with ``P`` the orthogonal projector on the columns of ``jn``: the
    generators' truth-side noncentrality has the nominal parameters projected out."""
    q, _ = np.linalg.qr(jn)
    return lambda a: a - q @ (q.T @ a)


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
    ``_stats.onset_grid`` of the record)."""
    onsets = onset_grid(np.asarray(ts) / 3600, n_train)
    rows = ts[:n_train]
    grids = {"drift_transient": len(TRANSIENT_TIMES_H), "drift_step": len(onsets)}
    names = tuple(n for v in _EFFECT_PARAMS.values() for n in v)
    cols = {}
    for g in range(max(grids.values())):
        # the k-th pass sets each gridded effect to its k-th value (the last one past its end);
        # an effect's columns do not depend on another's grid value (every amplitude is 0 here)
        tau_h = TRANSIENT_TIMES_H[min(g, len(TRANSIENT_TIMES_H) - 1)]
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
    sealer = _Sealer(out_dir, seed)
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


# -- spec §6 G6: design advice, closed loop ---------------------------------------------------
# the hidden effects of the closed loops at the diagnosis' own prior scales (arcsec: 10 arcmin
# of rotor tilt, seed 000; 5 arcsec per coefficient of the sidereal-day line)
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
    sealer = _Sealer(out_dir, seed)
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
    """Spec §6 G6 on the cases of :func:`generate_closed_loop` (``hidden``: their family):
    :func:`~gyrojax.diagnose._harness.closed_loop`, the same instrument (every sealed
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


def _sha(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


class _Sealer:
    """Writes the case records ``case_<index>.nc`` and, on :meth:`close`, the sealed manifest
    keyed by each file's SHA-256 (so the truth travels with the exact bytes diagnosed)."""

    def __init__(self, out_dir, seed: int):
        self.out = Path(out_dir)
        (self.out / "sealed").mkdir(parents=True, exist_ok=True)
        self.manifest, self.paths = {}, []
        self.seed = seed
        self.rng = np.random.default_rng(seed)

    def draw(self, i: int, families, lambdas, null_fraction: float):
        """Case ``i``'s family (a null with probability ``null_fraction``, else the families in
        turn) and its noncentrality."""
        family = "null" if self.rng.uniform() < null_fraction else families[i % len(families)]
        return family, float(self.rng.choice(lambdas))

    def add(self, rec, truth: dict):
        path = self.out / f"case_{len(self.paths):04d}.nc"
        save_record(rec, path)
        self.manifest[_sha(path)] = truth | {"file": path.name}
        self.paths.append(path)

    def close(self, design) -> list[Path]:
        write_json({"design": dataclasses.asdict(design), "seed": self.seed,
                    "cases": self.manifest},
                   self.out / "sealed" / "manifest.json")
        return self.paths


def run(case_dir, *, design: Design | None = None, baselines: bool = True,
        refit_all: bool = True, progress=None, noise: dict | None = None,
        prior: str | None = None) -> list:
    """Diagnose every record in ``case_dir`` (never reading ``sealed/``); returns one result dict
    per case with the verdict, ranking summary, held-out gaps, timings and baseline answers
    (``refit_all=False`` skips the costly B2 and keeps B1; ``noise``: the diagnosis' noise
    model arguments, e.g. ``{"noise_model": "white+flicker"}``; ``prior``: the diagnosis'
    Bayes-factor prior, and B2's)."""
    from ._diagnose import diagnose
    from ._esg import ESGProblem

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
            "sha": _sha(path), "file": path.name, "verdict": rep.verdict["kind"],
            "prior": rep.prior, "effects": rep.verdict.get("effects") or [],
            "ranking": [r["name"] for r in ranking],
            "posterior": {r["name"]: r["posterior"] for r in ranking},
            "p": {r["name"]: r["p"] for r in ranking},
            "flags": {r["name"]: r["flag"] for r in ranking},
            "scores": _scores(ranking),
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


def refit_all_baseline(prob, ranking, sigma, prior: str = "design") -> dict:
    """Spec §5.7 B2 on one record: refit every catalogued effect alone (a grid effect at every
    grid value, keeping the best: refit-all has no score to pick a decay time or onset, and the
    grid value counts as one more parameter) from the same nominal fit as the diagnosis, on its
    whitened train rows. Returns the BIC choice (``b2_choice``, ``"none"`` when the nominal wins),
    the choice by the screening's own Bayes factor with each refit's estimate in place of the
    one-step one (``b2_lr_choice``: the answer screening approximates, spec §6 G10), their log
    Bayes factors, the refits' wall time and count. ``ranking``: the report's rows (the dof each
    effect was screened on); ``sigma``: the report's noise level; ``prior``: the screening's
    (``"design"`` or ``"shell"``, :func:`~gyrojax.diagnose._stats.screen`)."""
    if prior not in ("design", "shell"):
        raise ValueError(f"prior={prior!r}: B2's Bayes factors follow 'design' or 'shell'")
    params0 = prob.fit_nominal()
    n = prob.n_train

    def standardize(resid):
        return prob.standardize(resid, sigma)

    def chi2(pred):  # on the diagnosis' whitened rows
        return float(np.sum(standardize(prob.y[:n] - pred[:n]) ** 2))

    rss0 = chi2(prob.predict(params0))
    m = n * len(prob.channels)
    jn, sigs = prob.jacobians(params0, sigma)
    rows = slice(0, m)  # the train rows the refits fit
    u = nominal_basis(jn[rows])
    screened_dof = {r["name"]: int(r["dof"]) for r in ranking}
    t0 = time.perf_counter()  # both answers start from the same nominal fit
    n_refits = 0
    bic = {"none": m * math.log(rss0 / m)}
    lr_bf = {}
    for sig in sigs:
        rss, blocks = [], []
        for g in range(max(len(sig.grid), 1)):
            pred, coeffs, _ = prob.refit(params0, [(sig, g)], sigma)
            n_refits += 1
            rss.append(chi2(pred))
            # the screening's Bayes factor with the refit in place of the one-step estimate
            # (shape part: score = I b^; g-prior part: the likelihood-ratio drop for the score
            # statistic, on the dof the screening tested)
            jt = _project(u, sig.jac[g][rows])
            b_hat = np.array([coeffs[nm] for nm in sig.names]) / sig.prior_scale
            blocks.append((jt.T @ jt, jt.T @ jt @ b_hat))
        k = len(sig.names) + (1 if sig.grid else 0)
        bic[sig.name] = m * math.log(min(rss) / m) + k * math.log(m)
        drops = [max(rss0 - r, 0.0) for r in rss]
        dof = screened_dof[sig.name]
        if prior == "shell" and len(sig.names) == 1:  # one coefficient: the exact shell factor
            v = shell_log_bf(drops) if dof > 0 else np.zeros(len(drops))
            lr_bf[sig.name] = float(np.logaddexp.reduce(v) - math.log(len(v)))
            continue
        lams = SHELL_DESIGN_LAMBDAS if prior == "shell" else np.array([32.0])
        shape = shape_log_bf_scores(blocks, lams)
        zell = zellner_log_bf(drops, [dof] * len(rss), lams)
        lr_bf[sig.name] = float(shell_design_log_bf(shape, zell) if prior == "shell"
                                else mix_log_bf(shape, zell)[0])
    return {"b2_choice": min(bic, key=bic.get),
            "b2_lr_choice": max(lr_bf, key=lr_bf.get) if lr_bf else None,
            "b2_lr_log_bf": lr_bf, "time_refit_all_s": time.perf_counter() - t0,
            "n_refits": n_refits}


def grid_best(rep) -> dict:
    """Each grid effect's grid value at its largest score (onset, decay time) in a report."""
    return {r["name"]: r["grid"]["best"] for r in rep.ranking if r.get("grid")}


def grid_locations(rep) -> dict:
    """Each grid effect's located value in a report: the centre of the one-step window of most
    posterior mass (:func:`gyrojax.diagnose._report.grid_located`)."""
    return {r["name"]: r["grid"]["located"] for r in rep.ranking if r.get("grid")}


def grid_localisation(strong, *, step, transient, decay_grid, record_length,
                      truth_scale: float = 1.0, crb_key: str | None = None,
                      decay_crb_key: str | None = None) -> dict:
    """Spec §6 G8's onset and decay-time rules over (truth, result) pairs with ``grid_best``:
    ``step`` and ``transient`` are ``(family, truth key)``; an onset counts within 5 % of the
    record (``record_length(result)``, in the grid's unit) of the truth, a decay time within one
    step of the geometric ``decay_grid``. ``truth_scale`` converts the truth's display unit to the
    grid's (e.g. 1/60 for minutes against a grid in hours). ``crb_key``: the truth's Cramér-Rao
    standard deviation of the onset (same unit), for an efficient estimator's rate on the same
    cases (``g8_step_onset_crb``, :func:`crb_rate`); ``decay_crb_key``: the decay time's
    deviation in log time, summarised against the one-step tolerance (``g8_transient_decay_crb``,
    :func:`crb_spread`). The rates are scored twice where the
    results carry ``grid_located`` (the reports' located values, :func:`grid_locations`):
    ``g8_step_onset`` and ``g8_transient_decay`` at the largest score, the ``_located`` ones
    at the located value."""
    (fs, ks), (ft, kt) = step, transient
    ratio = math.log(decay_grid[1] / decay_grid[0])
    steps = [(t, r) for t, r in strong if t["family"] == fs]
    transients = [(t, r) for t, r in strong if t["family"] == ft]

    def rates(key):
        if not all(key in r for _, r in steps + transients):
            return None, None
        return (_rate(steps, lambda t, r: abs(r[key][fs] - truth_scale * t[ks])
                      <= 0.05 * record_length(r)),
                _rate(transients, lambda t, r: abs(math.log(r[key][ft] / (truth_scale * t[kt])))
                      <= ratio))

    best, located = rates("grid_best"), rates("grid_located")
    return {
        "g8_step_onset": best[0], "g8_transient_decay": best[1],
        "g8_step_onset_located": located[0], "g8_transient_decay_located": located[1],
        # a local reference on the same cases: the truth side's Cramér-Rao deviations
        "g8_step_onset_crb": crb_rate(steps, crb_key, lambda r: 0.05 * record_length(r),
                                      truth_scale) if crb_key else None,
        "g8_transient_decay_crb": crb_spread(transients, decay_crb_key, ratio)
        if decay_crb_key else None,
    }


def onset_crb(j_nuisance, j_onset) -> float:
    """Cramér-Rao standard deviation of an onset (in its Jacobian's unit) from whitened columns:
    ``1 / |(I - P) j_onset|`` with ``P`` the projector on the span of the nuisance columns (the
    nominal parameters and the effect's sizes, estimated jointly with the onset; rank-revealing,
    so a structurally unidentifiable nominal direction costs nothing). Any other grid value
    the same way, e.g. a decay time with ``j_onset`` its column in log time."""
    q = nominal_basis(np.asarray(j_nuisance))
    r = np.asarray(j_onset) - q @ (q.T @ np.asarray(j_onset))
    return float(1.0 / np.sqrt(r @ r))


def crb_rate(pairs, key: str, tol, truth_scale: float = 1.0):
    """An efficient estimator's expected share within ``tol(result)`` of the truth, the mean of
    ``erf(tol / (sqrt 2 sigma))`` over the pairs whose truth has the Cramér-Rao standard
    deviation ``key`` (times ``truth_scale``, to ``tol``'s unit); ``None`` when none has. A local
    reference: it counts only errors near the truth, not the far ones of the threshold regime
    (another onset fitting the absorbed remainder better), so it is no bound at low lambda."""
    vals = [math.erf(tol(r) / (math.sqrt(2) * truth_scale * t[key])) for t, r in pairs
            if key in t]
    return {"rate": float(np.mean(vals)), "n": len(vals)} if vals else None


def crb_spread(pairs, key: str, tol: float):
    """How well the record can place a grid parameter at all: over the pairs whose truth has
    the Cramér-Rao deviation ``key``, the median of deviation / ``tol`` and the share with a
    deviation <= ``tol`` (``None`` when none has). For a decay time (deviation in log time,
    ``tol`` the grid's log ratio) :func:`crb_rate` would mislead: where the deviation exceeds the
    grid's whole span, a Gaussian efficient estimator does worse than any guess inside the
    grid, so the rate a diagnosis reaches there comes from the grid's range, not the record."""
    r = np.array([t[key] / tol for t, _ in pairs if key in t])
    return ({"median_ratio": float(np.median(r)), "resolved": float(np.mean(r <= 1.0)),
             "n": int(r.size)} if r.size else None)


def localisation_fields(rep) -> dict:
    """What spec §6 G8 scores from a report: each grid effect's screened grid value (onset,
    decay time; ``grid_best``) and located value (``grid_located``), the frequency cell of
    smallest p (``top_line``, its p) and the record's length in hours."""
    lines = [x for x in rep.where if x["axis"] == "frequency"]
    top = min(lines, key=lambda x: x["p"]) if lines else None
    taus = [x for x in rep.where if x["axis"] == "tau" and x.get("rate") != "full"]  # decided
    top_tau = min(taus, key=lambda x: x["p"]) if taus else None
    t = np.asarray(rep.t)
    return {"grid_best": grid_best(rep), "grid_located": grid_locations(rep),
            "top_line": top["cell"] if top else None, "top_line_p": top["p"] if top else None,
            "top_tau_s": top_tau["tau_s"] if top_tau else None,
            "top_tau_significant": bool(top_tau and top_tau["significant"]),
            "longest_tau_s": max(x["tau_s"] for x in taus) if taus else None,
            "record_hours": float((t[-1] - t[0]) / 3600)}


def tau_band_scores(pairs) -> dict:
    """Spec §6 G8 for noise-model effects over (truth, result) pairs of ``angle_random_walk``
    cases: the share whose tau axis has a significant cell, and of those the share whose
    smallest-p tau cell is the longest band (where a random walk's Allan excess over white
    noise, growing as tau^2, is largest)."""
    rw = [(t, r) for t, r in pairs if t["family"] == "angle_random_walk"]
    sig = [(t, r) for t, r in rw if r.get("top_tau_significant")]
    return {"g8_tau_detected": _rate(rw, lambda t, r: r.get("top_tau_significant")),
            "g8_tau_band": _rate(sig, lambda t, r: r["top_tau_s"] == r["longest_tau_s"]),
            "g8_tau_not_attributed": _rate(rw, lambda t, r: r["verdict"] != "attributed")}


def localisation_scores(lib, *, lam_min: float = 32.0) -> dict:
    """Spec §6 G8 over in-library (truth, result) pairs at ``lambda >= lam_min``: a step's
    screened onset within 5 % of the record of the truth (one window of the gap map's finest
    level), a transient's screened decay time within one step of the geometric grid, and a
    diurnal line found on the sidereal-day line (the frequency cell of smallest p)."""
    strong = [(t, r) for t, r in lib if t.get("lambda", 0) >= lam_min and "grid_best" in r]
    return {
        **grid_localisation(strong, step=("drift_step", "onset_h"),
                            transient=("drift_transient", "decay_time_h"),
                            decay_grid=TRANSIENT_TIMES_H,
                            record_length=lambda r: r["record_hours"], crb_key="onset_crb_h",
                            decay_crb_key="decay_crb_log"),
        "g8_line": _rate([(t, r) for t, r in strong if t["family"] == "diurnal_line"],
                         lambda t, r: (r["top_line"] or "").startswith("sidereal day")),
        # how specific that is: the other families' gaps on the same line
        "g8_line_other_families": _rate(
            [(t, r) for t, r in strong if t["family"] != "diurnal_line"],
            lambda t, r: (r["top_line"] or "").startswith("sidereal day")),
    }


def multiplicity_fields(rep) -> dict:
    """What a blind result keeps of the multiplicity decision: the smallest weighted-BH q over
    the map and the library, and the level it was held to (calibrated or ``alpha``)."""
    qs = [x["q"] for x in rep.where if x.get("q") is not None] + [r["q"] for r in rep.ranking]
    return {"min_q": min(qs, default=1.0),
            "level": rep.multiplicity.get("level", rep.alpha)}


def plain_bh_far(nulls) -> dict:
    """On the null cases ``(truth, result)``: the false-alarm rate weighted BH would have at the
    uncalibrated level 0.05 (smallest q < 0.05), and the median calibrated level."""
    nulls = [(t, r) for t, r in nulls if "min_q" in r]
    if not nulls:
        return {}
    levels = sorted(r["level"] for _, r in nulls)
    return {"far_plain_bh": _rate(nulls, lambda t, r: r["min_q"] < 0.05),
            "level_median": levels[len(levels) // 2]}


def _se(p, n):
    return math.sqrt(max(p * (1 - p), 1e-12) / max(n, 1))


def _rate(pairs, fn):
    """Share of (truth, result) pairs where ``fn`` holds, its Monte Carlo standard error and n."""
    pairs = list(pairs)
    if not pairs:
        return None
    k = sum(bool(fn(t, r)) for t, r in pairs)
    p = k / len(pairs)
    return {"rate": p, "se": _se(p, len(pairs)), "n": len(pairs)}


def _basis(j):
    """Orthonormal basis of the column span of ``j`` (rank-revealing QR: column pivoting, so a
    dependent or zero column does not turn a later column's direction)."""
    q, r, _ = scipy.linalg.qr(j, mode="economic", pivoting=True)
    d = np.abs(np.diag(r))
    return q[:, : int(np.sum(d > 1e-10 * d[0]))] if d.size and d[0] > 0 else q[:, :0]


def remainder_after_library(d, jn, cols) -> dict:
    """Truth side of spec §6 G9: the noncentrality of a whitened out-of-library term ``d``
    (train rows) left after the nominal parameters (columns ``jn``) and the best catalogue fit
    the diagnosis can make (one effect, or a pair: its greedy second step) are fitted.
    ``cols``: family -> list of column blocks (one per grid value). Returns the
    nominal-projected lambda, the remainder after the best fit (one effect or a pair), after
    the best single effect, and that effect.

    Every fit below projects ``d`` on ``jn`` and a few blocks: all are taken in the coordinates
    of one QR of ``[jn, every block, d]`` (an isometry of their span), so each fit is a small
    dense problem instead of a QR over every train row (the same numbers to rounding)."""
    blocks = [b for fam in cols for b in cols[fam]]
    m = np.concatenate([jn] + blocks + [np.asarray(d)[:, None]], axis=1)
    if m.shape[0] > m.shape[1]:
        r = np.linalg.qr(m, mode="r")
        edges = np.cumsum([jn.shape[1]] + [b.shape[1] for b in blocks])
        jn, d, in_r, at = r[:, :edges[0]], r[:, -1], {}, 0
        for fam, fam_blocks in cols.items():
            in_r[fam] = [r[:, edges[at + i]:edges[at + i + 1]] for i in range(len(fam_blocks))]
            at += len(fam_blocks)
        cols = in_r

    def left(extra):
        q = _basis(np.concatenate([jn] + list(extra), axis=1))
        r = d - q @ (q.T @ d)
        return float(r @ r)

    fams = list(cols)
    single = min(((a, left([ca])) for a in fams for ca in cols[a]), key=lambda x: x[1])
    pair = min(left([ca, cb]) for i, a in enumerate(fams) for b in fams[i + 1:]
               for ca in cols[a] for cb in cols[b])
    return {"nominal_lambda": left([]), "remainder_lambda": min(single[1], pair),
            "remainder_single_lambda": single[1], "closest_effect": single[0]}


def confident(r) -> bool:
    """Attributed with posterior > 0.9 (an effect without a posterior, e.g. a noise-model term,
    counts as confident)."""
    return r["verdict"] == "attributed" and bool(r["effects"]) and max(
        r["posterior"].get(e, 1.0) for e in r["effects"]) > 0.9


def ool_scores(ool) -> dict:
    """Spec §6 G9 over out-of-library (truth, result) pairs: over the cases whose remainder
    noncentrality after the best library fit (truth side, ``remainder_lambda``; else the
    case's lambda) is >= 32, the share not confidently attributed and the share unexplained or
    ambiguous; over every case, the confident misattributions."""
    strong = [(t, r) for t, r in ool if t.get("remainder_lambda", t["lambda"]) >= 32]
    return {
        "ool_strong_not_confident": _rate(strong, lambda t, r: not confident(r)),
        "ool_strong_unexplained_or_ambiguous": _rate(
            strong, lambda t, r: r["verdict"] in ("unexplained", "ambiguous")),
        "ool_confident_misattribution": _rate(ool, lambda t, r: confident(r)),
        # how far outside the catalogue's span the confidently misattributed cases reached: a
        # remainder near zero means the library mimics the effect on this record (no test on it
        # can tell them apart; only a design shift can)
        "ool_confident_remainder_max": max(
            (t["remainder_lambda"] for t, r in ool if confident(r) and "remainder_lambda" in t),
            default=None),
        "ool_remainder_from_truth": bool(ool) and all("remainder_lambda" in t for t, _ in ool),
    }


def _scores(ranking) -> dict:
    """What the oracle needs from a blind run: each effect's score statistic and dof at every
    grid value (``{name: [scores, dofs]}``)."""
    return {r["name"]: [r["score_grid"], r["dof_grid"]] for r in ranking}


def oracle_choice(r, lam: float):
    """The Bayes-oracle answer (spec §5.6) for a case of noncentrality ``lam``: the effect of
    largest posterior under the linearised model with equal prior odds between the catalogue
    effects and the diagnosis' design prior sized to expect exactly ``lam``
    (:func:`~gyrojax.diagnose._stats.design_log_bf`), averaged over each effect's grid. It
    reads the blind run's design-prior factors at every prior size (``r["log_bf_by_lambda"]``)
    at the sealed ``lam``, which the diagnosis does not know (it assumes ``lambda0 = 32``)."""
    lbf = _oracle_log_bfs(r, lam)
    return max(lbf, key=lbf.get) if lbf else None


def _oracle_log_bfs(r, lam: float) -> dict:
    """Each effect's design-prior log Bayes factor at prior size ``lam`` (the effects with a
    signature) from the run's recorded curve (``log_bf_by_lambda``, powers of 2 from 1 to
    1024: every suite's lambda is one); a ``lam`` between two recorded sizes is interpolated
    linearly in ``log lambda``."""
    curves = r.get("log_bf_by_lambda") or {}
    scores = r.get("scores") or {}
    out = {}
    for k, c in curves.items():
        if k in scores and not any(scores[k][1]):
            continue  # no signature: no posterior (as the diagnosis', _stats._posteriors)
        sizes = sorted(c, key=float)
        x = np.log([float(v) for v in sizes])
        if not x[0] - 1e-12 <= math.log(lam) <= x[-1] + 1e-12:
            raise KeyError(f"the run's design-prior factors cover lambda {sizes[0]}-{sizes[-1]}, "
                           f"not {lam:g}")
        out[k] = float(np.interp(math.log(lam), x, [c[v] for v in sizes]))
    return out


def oracle_detect_statistic(r, lam: float) -> float:
    """The Bayes oracle's detection statistic for a case of noncentrality ``lam``: the log of
    the mean over the catalogue of the design-prior Bayes factors expecting exactly ``lam``
    (:func:`oracle_choice`'s prior), i.e. the likelihood ratio of the generator's alternative
    against the null in the linearised model (Neyman-Pearson: the most powerful detector)."""
    lbf = list(_oracle_log_bfs(r, lam).values())
    return float(np.logaddexp.reduce(lbf) - math.log(len(lbf)))


def oracle_power(pairs, lam: float, thresholds):
    """Detection power of the Bayes oracle on ``pairs`` of noncentrality ``lam``: its statistic
    above the level-alpha threshold ``thresholds[lam]`` (from
    :func:`gyrojax.diagnose._harness.oracle_detection_thresholds`); ``None`` without one."""
    if not thresholds or float(lam) not in thresholds:
        return None
    return _rate([(t, r) for t, r in pairs if r.get("log_bf_by_lambda")],
                 lambda t, r: oracle_detect_statistic(r, lam) > thresholds[float(lam)])


def calibration(pairs, n_bins: int = 10):
    """Spec §5.6 set calibration of the posteriors over in-library (truth, result) pairs, with
    each result's posteriors renormalised over the catalogue (an effect is present): expected
    calibration error of the top posterior (``n_bins`` equal-width bins; ``|accuracy -
    confidence|`` weighted by the bin's share) and the multi-class Brier score. ``None``
    without posteriors."""
    conf, hit, brier = [], [], []
    for t, r in pairs:
        post = r.get("posterior") or {}
        total = sum(post.values())
        if total <= 0:
            continue
        p = {k: v / total for k, v in post.items()}
        top = max(p, key=p.get)
        conf.append(p[top])
        hit.append(float(top == t["family"]))
        brier.append(sum((v - (k == t["family"])) ** 2 for k, v in p.items())
                     + (0.0 if t["family"] in p else 1.0))
    if not conf:
        return None
    conf, hit = np.asarray(conf), np.asarray(hit)
    bins = np.minimum((conf * n_bins).astype(int), n_bins - 1)

    def ece(h):
        return sum(abs(h[bins == b].mean() - conf[bins == b].mean()) * np.mean(bins == b)
                   for b in range(n_bins) if np.any(bins == b))

    # the ECE a perfectly calibrated forecaster shows with these confidences and this n (the
    # binned ECE is biased upwards at small n): outcomes drawn as Bernoulli(confidence)
    rng = np.random.default_rng(0)
    null = [ece((rng.uniform(size=conf.size) < conf).astype(float)) for _ in range(1000)]
    return {"ece": float(ece(hit)), "ece_calibrated_median": float(np.median(null)),
            "ece_calibrated_95": float(np.quantile(null, 0.95)), "brier": float(np.mean(brier)),
            "n": len(conf), "mean_confidence": float(conf.mean()), "accuracy": float(hit.mean())}


def ratio_rate(pairs, num, den):
    """Ratio of two rates on the same cases (e.g. top-1 / oracle top-1) with its delta-method
    standard error for paired indicators: ``se = sd(x - R y) / (sqrt(n) mean(y))``."""
    pairs = list(pairs)
    if not pairs:
        return None
    x = np.array([bool(num(t, r)) for t, r in pairs], float)
    y = np.array([bool(den(t, r)) for t, r in pairs], float)
    if y.sum() == 0:
        return None
    ratio = x.mean() / y.mean()
    se = float(np.std(x - ratio * y) / (math.sqrt(len(x)) * y.mean()))
    return {"rate": float(ratio), "se": se, "n": len(x)}


def score(case_dir, results, separable=None, oracle_thresholds=None) -> dict:
    """Unseal the manifest and compute the §5.6 metrics (rate, its Monte Carlo standard error,
    and the count behind it). ``separable``: the families whose largest projected canonical
    correlation with another is <= 0.9 on the design (for the separable top-1 of spec §6 G3;
    default: every family)."""
    manifest = json.loads((Path(case_dir) / "sealed" / "manifest.json").read_text())["cases"]
    rows = []
    for r in results:
        truth = manifest[r["sha"]]
        rows.append((truth, r))

    rate = _rate
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
            "top1": rate(sub, lambda t, r: r["ranking"] and _top(r) == t["family"]),
            "top3": rate(sub, lambda t, r: t["family"] in _top3(r)),
            "top1_separable": rate([(t, r) for t, r in sub if t["family"] in sep],
                                   lambda t, r: _top(r) == t["family"]),
            "oracle_top1": rate(sub, lambda t, r: oracle_choice(r, lam) == t["family"]),
            "oracle_top1_separable": rate([(t, r) for t, r in sub if t["family"] in sep],
                                          lambda t, r: oracle_choice(r, lam) == t["family"]),
            "oracle_efficiency": ratio_rate(sub, lambda t, r: _top(r) == t["family"],
                                            lambda t, r: oracle_choice(r, lam) == t["family"]),
            "oracle_power": oracle_power(sub, lam, oracle_thresholds),
            "set_coverage": rate([(t, r) for t, r in sub if r["ambiguity"]],
                                 lambda t, r: t["family"] in r["ambiguity"]),
            "mean_set_size": (float(np.mean([len(r["ambiguity"]) for t, r in sub
                                             if r["ambiguity"]]))
                              if any(r["ambiguity"] for _, r in sub) else None),
            "confident_misattribution": rate(sub, lambda t, r: max(r["posterior"].values()) > 0.9
                                             and _top(r) != t["family"]),
            "calibration": calibration(sub),
            "b1_power": rate(sub, lambda t, r: r.get("b1_detect")),
            "b2_top1": rate(sub, lambda t, r: r.get("b2_choice") == t["family"]),
        }
    out["calibration"] = calibration(lib)
    red = [_reduction(r) for t, r in lib if r["verdict"] in ("attributed", "ambiguous")]
    red = [x for x in red if x is not None]
    out["heldout_reduction_median"] = float(np.median(red)) if red else None
    out["heldout_closure"] = rate([(t, r) for t, r in lib if r["heldout_gap_after"] is not None
                                   and r["null_band_after"] is not None],
                                  lambda t, r: r["heldout_gap_after"] <= r["null_band_after"][1])
    out["out_of_library_honest"] = rate(ool, lambda t, r: r["verdict"] in
                                        ("unexplained", "ambiguous", "no-gap")
                                        or max(r["posterior"].values()) <= 0.9)
    out |= ool_scores(ool)  # spec §6 G9
    out |= localisation_scores(lib)  # spec §6 G8
    out |= confounding_scores(lib)  # spec §6 G5, practical confounding
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
    out["screen_refit_agreement"] = rate(strong, lambda t, r: _top(r) == r["b2_lr_choice"])
    out["screen_refit_agreement_separable"] = rate(
        [(t, r) for t, r in strong if t["family"] in sep],
        lambda t, r: _top(r) == r["b2_lr_choice"])
    return out


def confounding_scores(lib) -> dict:
    """Spec §5.6 / §6 G5 over the in-library cases ``lib`` ((truth, result) pairs): confounding
    recall (hidden effects whose truth-side visible fraction is < 0.05, or which have no
    signature, that the diagnosis flags so: :data:`CONFOUNDED_FLAGS` on that effect's row) and
    precision (flagged hidden effects that are so on the truth side), the agreement of the two
    flags over every case, and the confident misattribution over all in-library cases
    (posterior > 0.9 on another effect)."""
    known = [(t, r) for t, r in lib if "visibility" in t and "flags" in r]

    def flagged(t, r):
        return r["flags"].get(t["family"]) in CONFOUNDED_FLAGS

    def truth(t, r):
        return t["visibility"] in CONFOUNDED_FLAGS

    return {"confounding_recall": _rate([x for x in known if truth(*x)], flagged),
            "confounding_precision": _rate([x for x in known if flagged(*x)], truth),
            "confounding_agreement": _rate(known, lambda t, r: flagged(t, r) == truth(t, r)),
            "confident_misattribution_all": _rate(
                lib, lambda t, r: bool(r["posterior"]) and max(r["posterior"].values()) > 0.9
                and _top(r) != t["family"])}


def _top(r):
    return max(r["posterior"], key=r["posterior"].get) if r["posterior"] else None


def _top3(r):
    return sorted(r["posterior"], key=lambda k: -r["posterior"][k])[:3]


def _reduction(r):
    g0, g1 = r["heldout_gap_before"], r["heldout_gap_after"]
    if g0 is None or g1 is None or g0 <= r["null_band"][1]:
        return None
    return 1 - g1 / g0
