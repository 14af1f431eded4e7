"""Blind validation harness for the gap diagnosis, strapdown IMU rig (docs/diagnosis.md).

Like :mod:`gyrojax.validation.esg` (ESG): :func:`generate` writes records and a sealed manifest
keyed by each file's SHA-256, :func:`run` diagnoses the records without reading the manifest, and
:func:`score` unseals it. Two designs:

- ``multi``: 12 poses (the six axis-up poses and six tilted ones) of 20 s joined by 2-s turns, for
  the mean effects (earth_rate, scale_factor, misalignment, g_sensitivity, time_drift,
  warmup_transient), the out-of-library ``pose_step`` (an accelerometer bias that jumps at one pose
  change) and ``thermal_cycle`` (a 300-s sinusoidal gyro and accelerometer bias); with
  ``temperature=True`` every record carries a ``temp`` channel (a thermal cycle) and the
  ``thermal_bias`` makes one channel's bias follow it (the catalogue's ``temperature`` effect
  with one coefficient: the aux axis' check and the effect's attribution);
- ``static``: one pose, 40 min at 50 Hz, for the noise-model effects (rate_random_walk,
  bias_instability, outliers, quantization) and time_drift / warmup_transient.

``IMUDesign(per_coefficient=True)`` (goal G10 at K >= 20): the diagnosis screens every
coefficient as an effect of its own (``diagnose(per_coefficient=True)``, K = 40 on the six
channels) and each case hides one coefficient (``g_sensitivity:gsxy``; :func:`mean_families`).

**Splits.** ``same-design``: the record's last quarter (time-ordered). ``design-shift`` (multi
only): the record continues with six *other* poses (tilted 45 deg between the axes) that form the
held-out part, so a confusable pick that only fits the training poses is caught.

**Magnitudes** come from the truth side: mean effects by the noncentrality
``lambda = b^T I_eff b`` of the hidden coefficients on the train samples (white noise, the nominal
biases and pose angles projected out), computed here with its own Jacobian of the measurement
model; noise effects by the Whittle noncentrality ``theta^2 sum (h_k - mean h)^2 / S_0^2`` of the
term over the fitted band (f <= rate/10).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..analysis.spectral import term_spectra
from ..diagnose import coefficient_effect, effect_family_name
from ..models.imu import (
    IMU_CHANNELS,
    IMUConditions,
    IMURig,
    Pose,
    cube_poses,
    imu_measure,
    pose_frame,
    simulate_imu,
)
from ..record import BenchRecord
from ._harness import run_cases, score_cases
from ._scoring import Sealer, orthonormal_basis, remainder_after_library, truth_visibility

__all__ = ["IMUDesign", "generate", "run", "score", "mean_families", "MEAN_FAMILIES", "NOISE_FAMILIES",
           "OUT_OF_LIBRARY"]

MEAN_FAMILIES = ("earth_rate", "scale_factor", "misalignment", "g_sensitivity", "time_drift",
                 "warmup_transient")
NOISE_FAMILIES = ("rate_random_walk", "bias_instability", "outliers", "quantization")
OUT_OF_LIBRARY = ("pose_step", "thermal_cycle")
STATIC_FAMILIES = ("time_drift", "warmup_transient") + NOISE_FAMILIES
_SPACE = IMURig().param_space
# the coefficients a hidden effect sets (accelerometer-visible subsets where gyro terms have no
# signature on a static stand)
_EFFECT_PARAMS = {
    "earth_rate": ("k_earth",),
    "scale_factor": ("sax", "say", "saz"),
    "misalignment": ("maxy", "mayx", "maxz", "mazx", "mayz", "mazy"),
    "g_sensitivity": tuple(f"gs{a}{b}" for a in "xyz" for b in "xyz"),
    "time_drift": ("dgx", "dgy", "dgz", "dax", "day", "daz"),
    "warmup_transient": ("wgx", "wgy", "wgz", "wax", "way", "waz"),
}
# on a rate table the gyro triad's scale factors and misalignments are driven too
_TABLE_PARAMS = _EFFECT_PARAMS | {
    "scale_factor": ("sgx", "sgy", "sgz") + _EFFECT_PARAMS["scale_factor"],
    "misalignment": ("mgxy", "mgxz", "mgyx", "mgyz", "mgzx", "mgzy")
    + _EFFECT_PARAMS["misalignment"],
}


def _effect_params(design):
    return _TABLE_PARAMS if design.kind == "table" else _EFFECT_PARAMS


@dataclasses.dataclass(frozen=True)
class IMUDesign:
    """One blind design: ``kind`` ``"multi"``, ``"static"`` or ``"table"`` (design D4: the
    12-pose stand, then the rate-table runs of the diagnosis' advice, ccw/cw at 10 deg/s with
    x, y and z up, twice, ``dwell_s`` each); white noise densities ``arw`` (deg/sqrt(h)) and
    ``vrw`` (m/s/sqrt(h)); ``split`` ``"same-design"`` or ``"design-shift"``."""

    kind: str = "multi"
    n_poses: int = 12
    dwell_s: float = 20.0
    turn_s: float = 2.0
    static_s: float = 2400.0
    rate_hz: float = 50.0
    arw: float = 0.3
    vrw: float = 0.05
    latitude_deg: float = 45.0
    split: str = "same-design"
    per_coefficient: bool = False  # each coefficient an effect of its own (diagnosis and cases)

    @property
    def poses(self):
        if self.kind == "static":
            return [Pose((0.0, 0.0, 1.0), self.static_s)]
        poses = cube_poses(self.n_poses, self.dwell_s, seed=3)
        return poses + table_poses(self.dwell_s) if self.kind == "table" else poses

    @property
    def span_s(self):
        """Total time on the poses (s)."""
        return sum(p.dwell_s for p in self.poses)

    @property
    def shift_poses(self):
        s = 1 / math.sqrt(2)
        ups = [(s, s, 0), (s, 0, s), (0, s, s), (-s, s, 0), (s, 0, -s), (0, -s, s)]
        return [Pose(u, self.dwell_s) for u in ups]

    @property
    def all_poses(self):
        return self.poses + (self.shift_poses if self.split == "design-shift" else [])

    @property
    def holdout(self):
        if self.split == "design-shift":
            return len(self.shift_poses) / len(self.all_poses)
        return 0.25

    @property
    def sigma(self):
        """White per-sample std: gyro (rad/s), accelerometer (m/s^2)."""
        return (self.arw * units.DEG / 60 * math.sqrt(self.rate_hz),
                self.vrw / 60 * math.sqrt(self.rate_hz))


def table_poses(dwell_s: float) -> list:
    """The advisor's rate-table runs (:func:`gyrojax.diagnose._imu.table_runs`) as poses of
    ``dwell_s`` each."""
    from ..diagnose import table_runs

    ups, rates = table_runs()
    return [Pose(tuple(map(float, u)), dwell_s, float(np.degrees(r))) for u, r in zip(ups, rates)]


def _truth_params(rng):
    vals = {f"bg{a}": rng.uniform(-0.02, 0.02) for a in "xyz"}
    vals |= {f"ba{a}": rng.uniform(-0.1, 0.1) for a in "xyz"}
    return _SPACE.make(vals)


def _static_samples(rec):
    spans = np.asarray(rec.conditions["static_s"]).reshape(-1, 2)
    t = np.asarray(rec.t)
    idx, seg = [], []
    for k, (t0, t1) in enumerate(spans):
        i = np.flatnonzero((t >= t0) & (t <= t1))
        idx.append(i)
        seg.append(np.full(i.size, k))
    return np.concatenate(idx), np.concatenate(seg)


def mean_families(design: IMUDesign | None = None) -> tuple:
    """The hidden mean effects of ``design``'s cases: the catalogue's families, or with
    ``per_coefficient`` each coefficient a case family may set (``g_sensitivity:gsxy``)."""
    design = design or IMUDesign()
    if not design.per_coefficient:
        return MEAN_FAMILIES
    return tuple(coefficient_effect(f, n) if len(names) > 1 else f
                 for f, names in _effect_params(design).items() for n in names)


def _lambda_scale(params, design, names, b, n_train_frac, heading_deg=None):
    """The factor that scales ``b`` to unit efficient noncentrality on the train samples, and
    the effect's visibility there (:func:`~gyrojax.validation.esg.truth_visibility`): truth
    side (``heading_deg``: the record's horizontal Earth rate, scaled by ``k_earth``)."""
    jn, jb, _ = _train_jacobian(params, design, names, n_train_frac, heading_deg)
    q = orthonormal_basis(jn)
    jt = jb - q @ (q.T @ jb)
    return 1.0 / math.sqrt(float(b @ (jt.T @ jt) @ b)), truth_visibility(jb, jt)


def _remainder_lambda(params, design, term):
    """Truth side of goal G9: the noncentrality of an additive term ``term`` (n, 6) on the
    train static samples (whitened) that is left after the nominal parameters (biases, pose
    angles) and the best catalogue fit of one mean effect or a pair are fitted (the diagnosis
    can name up to three: the truth side stops at pairs); the transient over a grid of decay
    times. Returns
    the nominal-projected lambda, the remainder after the best fit (one effect or a pair), after
    the best single effect, and that effect."""
    span = design.span_s
    sig = np.array([design.sigma[0]] * 3 + [design.sigma[1]] * 3)
    params_of = _effect_params(design)
    names = tuple(n for v in params_of.values() for n in v)
    cols, jn, d = {}, None, None
    for tau in np.geomspace(0.02, 0.5, 6) * span:
        jn, jb, idx = _train_jacobian(dict(params) | {"tau_w": float(tau)}, design, names,
                                      design.holdout)
        k = 0
        for fam, fn in params_of.items():
            if fam == "warmup_transient" or fam not in cols:
                cols.setdefault(fam, []).append(jb[:, k:k + len(fn)])
            k += len(fn)
        d = (np.asarray(term)[idx] / sig).reshape(-1)
    if "earth_rate" in cols:  # + the horizontal Earth rate of an unknown heading (one chain)
        size = units.EARTH_RATE * math.cos(math.radians(design.latitude_deg)) / sig[0]
        h = [np.pad(north_in_body(design, a)[idx] * size, ((0, 0), (0, 3))).reshape(-1, 1)
             for a in (0.0, 90.0)]
        cols["earth_rate"] = [np.concatenate([c] + h, axis=1) for c in cols["earth_rate"]]

    return remainder_after_library(d, jn, cols)


def north_in_body(design, heading_deg) -> np.ndarray:
    """``(samples, 3)``: the body-frame unit north of ``design``'s record whose north lies at
    ``heading_deg`` from the first pose's ``e1`` (:func:`~gyrojax.models.imu.simulate_imu`),
    read off the simulator's horizontal Earth rate."""
    p = _SPACE.make({"k_earth": 1.0})
    kw = dict(rate_hz=design.rate_hz, turn_s=design.turn_s, latitude_deg=design.latitude_deg)
    with_h = np.asarray(simulate_imu(p, design.all_poses, heading_deg=heading_deg, **kw).y)
    without = np.asarray(simulate_imu(p, design.all_poses, **kw).y)
    return (with_h - without)[:, :3] / (units.EARTH_RATE
                                         * math.cos(math.radians(design.latitude_deg)))


def _train_jacobian(params, design, names, n_train_frac, heading_deg=None):
    """Whitened Jacobians of the train static samples (truth side): the nominal parameters with
    each pose's two tilt angles, and ``names``; and the samples' indices in the record. With
    ``heading_deg`` the record carries the horizontal Earth rate too (``k_earth`` of it)."""
    rec = simulate_imu(params, design.all_poses, rate_hz=design.rate_hz, turn_s=design.turn_s,
                       latitude_deg=design.latitude_deg)
    idx, seg = _static_samples(rec)
    n_tr = int(round((1 - n_train_frac) * idx.size))
    idx, seg = idx[:n_tr], seg[:n_tr]
    north = np.zeros((len(idx), 3)) if heading_deg is None else \
        north_in_body(design, heading_deg)[idx] * units.EARTH_RATE * math.cos(
            math.radians(design.latitude_deg))
    t = np.asarray(rec.t)[idx]
    ups = np.array([np.asarray(p.up) / np.linalg.norm(p.up) for p in design.all_poses])
    omega = jnp.radians(jnp.array([p.rate_dps for p in design.all_poses]))[seg]
    cond = IMUConditions(design.latitude_deg, units.G0, design.rate_hz)
    nominal = tuple(_SPACE.nominal_names())

    def model(vec):
        p = dict(params)
        for i, n in enumerate(nominal + names):
            p[n] = params[n] + vec[i]
        da, db = vec[len(nominal) + len(names)::2], vec[len(nominal) + len(names) + 1::2]
        e1, e2 = pose_frame(ups)
        u = jnp.asarray(ups)[seg] + da[seg][:, None] * e1[seg] + db[seg][:, None] * e2[seg]
        u = u / jnp.linalg.norm(u, axis=1, keepdims=True)
        return imu_measure(p, u, jnp.asarray(t), cond,
                           omega[:, None] * u + p["k_earth"] * jnp.asarray(north))

    n_par = len(nominal) + len(names) + 2 * len(ups)
    j = np.asarray(jax.jacfwd(model)(jnp.zeros(n_par)))
    j = j / np.array([design.sigma[0]] * 3 + [design.sigma[1]] * 3)[None, :, None]
    j = j.reshape(-1, n_par)
    cols = list(range(len(nominal))) + list(range(len(nominal) + len(names), n_par))
    return j[:, cols], j[:, len(nominal): len(nominal) + len(names)], idx


def _noise_theta(family, design):
    """Strength of a noise term with unit Whittle noncentrality on the static train record,
    over the whole spectrum up to the Nyquist frequency: the information the record holds, not
    that of one test's band (quantization lives at the top of the band, where the slow terms'
    ``rate / 10`` fit never looks: counted over that band alone, its cases would be ~28x
    stronger in ``Q^2`` than their lambda says; bias instability and rate random walk would
    change by < 0.5 %). For quantization this is exactly the noncentrality ``N Q^4 / (tau0^4 sigma^4)``
    of its MA(1) score test."""
    n = int(design.static_s * design.rate_hz * 0.75)
    f = np.arange(2, n // 2) * design.rate_hz / n
    h = term_spectra(f, design.rate_hz)
    col = {"quantization": 0, "bias_instability": 2, "rate_random_walk": 3}[family]
    s0 = design.sigma[0] ** 2
    hk = h[:, col] / s0
    return 1.0 / math.sqrt(float(np.sum((hk - hk.mean()) ** 2)))


def _hidden(rng, family, p, design, lam):
    p = dict(p)
    truth = {"family": family, "lambda": float(lam) if family != "null" else 0.0,
             "nominal": {k: float(_SPACE[k].to_display(p[k])) for k in _SPACE.nominal_names()}}
    if effect_family_name(family) in _EFFECT_PARAMS:
        names = _effect_params(design)[family] if family in _EFFECT_PARAMS else (
            family.split(":", 1)[1],)
        if effect_family_name(family) == "warmup_transient":
            tau = float(rng.uniform(0.05, 0.4) * design.span_s)
            p["tau_w"] = tau
            truth["tau_s"] = tau
        heading = None
        if effect_family_name(family) == "earth_rate":  # the whole Earth rate: a heading
            heading = float(rng.uniform(0.0, 360.0))
            truth["heading_deg"] = heading
        b = rng.standard_normal(len(names))
        scale, visibility = _lambda_scale(p, design, names, b, design.holdout, heading)
        b = b * math.sqrt(lam) * scale
        for n, v in zip(names, b):
            p[n] = p[n] + v
        truth["coefficients"] = {n: float(_SPACE[n].to_display(v)) for n, v in zip(names, b)}
        truth |= visibility
    elif family in ("quantization", "bias_instability", "rate_random_walk"):
        theta = math.sqrt(lam) * _noise_theta(family, design)  # coefficient of the spectrum
        key = {"quantization": "q_g", "bias_instability": "b_g", "rate_random_walk": "k_g"}
        p[key[family]] = math.sqrt(theta)
        truth["term"] = {key[family]: math.sqrt(theta)}
    elif family == "outliers":
        p["eps_out"] = float(lam) * 1e-5
        truth["eps_out"] = p["eps_out"]
    elif family not in ("null", "thermal_bias") + OUT_OF_LIBRARY:
        raise ValueError(f"unknown case family {family!r}")
    return p, truth


def _ool_term(rng, family, rec, design, lam):
    """Out-of-library additive term (n, 6) and its truth entry. ``lam`` sets the term's size by
    a fixed rule, not its noncentrality: the truth side's ``nominal_lambda`` (and
    ``remainder_lambda``, after the best catalogue fit) says what the record holds, and the
    benchmark bins the cases by them."""
    t = np.asarray(rec.t)
    out = np.zeros((t.size, 6))
    amp = math.sqrt(lam) * 0.5
    if family == "pose_step":
        spans = np.asarray(rec.conditions["static_s"]).reshape(-1, 2)
        k = int(rng.integers(3, len(spans) - 2))
        t_jump = spans[k, 0]
        axis = int(rng.integers(3))
        out[t >= t_jump, 3 + axis] = amp * design.sigma[1] / 5
        return out, {"pose": k, "axis": "xyz"[axis], "step_mps2": amp * design.sigma[1] / 5}
    period = 300.0
    out[:, :3] = amp * design.sigma[0] / 10 * np.sin(2 * np.pi * t / period)[:, None]
    out[:, 3:] = amp * design.sigma[1] / 10 * np.sin(2 * np.pi * t / period)[:, None]
    return out, {"period_s": period, "gyro_amplitude_dph": amp * design.sigma[0] / 10 / units.DEG_PER_HOUR,
                 "accel_amplitude_mps2": amp * design.sigma[1] / 10}


def _temperature(rng, t):
    """A thermal cycle on the stand (deg C): 25 + A sin(2 pi t / P + phi), A in [1, 3], the
    period a third to a whole of the record, plus 0.01 deg C sensor noise."""
    span = float(t[-1] - t[0])
    a, per = rng.uniform(1.0, 3.0), rng.uniform(span / 3, span)
    return 25.0 + a * np.sin(2 * np.pi * t / per + rng.uniform(0, 2 * np.pi)) \
        + 0.01 * rng.standard_normal(t.size), {"temp_amplitude_c": a, "temp_period_s": per}


def _thermal_bias(rng, p, temp, design, lam):
    """A bias following the record's temperature on one random channel (the ``temperature``
    effect with one coefficient, on the measured temperature), scaled so that the nominal model
    leaves it noncentrality ``lam`` on the train samples."""
    ch = int(rng.integers(6))
    unit = np.zeros((temp.size, 6))
    unit[:, ch] = (temp - temp.mean()) * design.sigma[ch // 3]
    r = _remainder_lambda(p, design, unit)  # quadratic in the term: scaled below
    k2 = lam / r["nominal_lambda"]
    return math.sqrt(k2) * unit, {
        "channel": IMU_CHANNELS[ch], "k_per_c": float(math.sqrt(k2) * design.sigma[ch // 3]),
        "k_unit": "rad/s per deg C" if ch < 3 else "m/s^2 per deg C",
        **{a: (v * k2 if a.endswith("lambda") else v) for a, v in r.items()}}


def generate(out_dir, n_cases: int, *, seed: int = 0, design: IMUDesign | None = None,
             lambdas=(8.0, 16.0, 32.0, 64.0), null_fraction: float = 0.25,
             families=None, temperature: bool = False) -> list[Path]:
    """Write ``n_cases`` blind IMU records into ``out_dir`` and the sealed manifest beside them.
    ``temperature``: every record carries a ``temp`` channel (a thermal cycle,
    :func:`_temperature`), which the ``thermal_bias`` family (the ``temperature`` effect on one
    channel) makes one
    channel's bias follow."""
    design = design or IMUDesign()
    sealer = Sealer(out_dir, seed)
    rng = sealer.rng
    if families is None:
        families = STATIC_FAMILIES if design.kind == "static" else \
            mean_families(design) + OUT_OF_LIBRARY
    key = jax.random.key(seed)
    for i in range(n_cases):
        family, lam = sealer.draw(i, families, lambdas, null_fraction)
        p, truth = _hidden(rng, family, _truth_params(rng), design, lam)
        key, sub = jax.random.split(key)
        rec = simulate_imu(p, design.all_poses, rate_hz=design.rate_hz, turn_s=design.turn_s,
                           latitude_deg=design.latitude_deg, arw=design.arw * units.DEG / 60,
                           vrw=design.vrw / 60, key=sub, heading_deg=truth.get("heading_deg"))
        temp = None
        if temperature:
            temp, extra = _temperature(rng, np.asarray(rec.t))
            truth |= extra
        if family in OUT_OF_LIBRARY or family == "thermal_bias":
            term, extra = (_thermal_bias(rng, p, temp, design, lam)
                           if family == "thermal_bias" else _ool_term(rng, family, rec, design,
                                                                      lam))
            rec = BenchRecord(rec.t, rec.y + jnp.asarray(term), rec.channels, rec.attrs)
            truth |= extra if family == "thermal_bias" else \
                extra | _remainder_lambda(p, design, term)
        attrs = {k: v for k, v in rec.conditions.items() if k != "static_s"}
        y, chans = rec.y, rec.channels
        if temp is not None:
            y, chans = jnp.concatenate([y, jnp.asarray(temp)[:, None]], axis=1), chans + ("temp",)
        rec = BenchRecord(rec.t, y, chans, tuple(sorted(attrs.items())))
        sealer.add(rec, truth)
    return sealer.close(design)


def run(case_dir, *, design: IMUDesign | None = None, progress=None,
        baselines: bool = False, prior: str | None = None) -> list:
    """Diagnose every record in ``case_dir`` (never reading ``sealed/``); ``baselines``: B2
    refit-all + BIC per record as well; ``prior``: the diagnosis' Bayes-factor prior (and
    B2's)."""
    design = design or IMUDesign()
    return run_cases(case_dir, "imu", design.holdout, progress=progress, baselines=baselines,
                     diagnose_kw={"per_coefficient": True} if design.per_coefficient else None,
                     prior=prior)


def score(case_dir, results, separable=None, oracle_thresholds=None,
          design: IMUDesign | None = None) -> dict:
    """Unseal and score (:func:`gyrojax.validation._harness.score_cases`)."""
    return score_cases(case_dir, results, mean_families(design), NOISE_FAMILIES, OUT_OF_LIBRARY,
                       separable=separable,
                       oracle_thresholds=oracle_thresholds)


# -- goal G8 on the IMU: the position and tau axes of the gap map ------------------------
def expected_position_z(record, truth) -> dict:
    """Truth side of the per-position signature (G8) of a ``pose_step`` case: the expected Wald
    z of every position cell of the diagnosis's map (cell label, channel) -> E z, up to the
    step's (positive) amplitude, from the diagnosis's own design on this record (nominal fit,
    AR whitening, nominal span projected out): ``J~_p' (I - P) d / |J~_p|`` with ``d`` the
    whitened step (the stepped accelerometer channel, every pose from ``truth["pose"]`` on).
    Empty when the record's static segments are not the design's poses one to one."""
    from .. import rigs
    from ..diagnose import VISIBLE_MIN, nominal_basis, project_out

    prob = rigs.get("imu").problem_for(record, holdout=0.25)
    params0 = prob.fit_nominal()
    n, c = prob.n_train, len(prob.channels)
    sigma = prob.noise_level((prob.y - prob.predict(params0))[:n])[0]
    jn, _ = prob.jacobians(params0, sigma)
    u = nominal_basis(jn[: n * c])
    d = np.zeros((n, c))
    d[prob.seg[:n] >= truth["pose"], prob.channels.index("a" + truth["axis"])] = 1.0
    dt = project_out(u, (prob.whiten(d) / sigma).reshape(-1))
    out = {}
    for label, _, w in prob.position_signatures(sigma):
        for j, name in enumerate(prob.channels):
            col = np.zeros((n, c))
            col[:, j] = w[:, j]
            col = col.reshape(-1)
            jt = project_out(u, col[:, None])[:, 0]
            if jt @ jt >= VISIBLE_MIN * (col @ col):
                out[(label, name)] = float(jt @ dt / np.linalg.norm(jt))
    return out


def position_correlation(where, expected) -> float:
    """Cosine between the map's per-position Wald z (``where``: the report's cells) and their
    expectation (:func:`expected_position_z`), over the cells both have."""
    obs = {(x["cell"], x["channel"]): x["z"] for x in where
           if x["axis"] == "position" and "z" in x}
    keys = [k for k in expected if k in obs]
    if not keys:
        return float("nan")
    a = np.array([obs[k] for k in keys])
    b = np.array([expected[k] for k in keys])
    return float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))


# the tau band a noise term lifts most over white noise on the rows' Allan variance: its
# AVAR over the white one grows as tau^2 (rate random walk), tau (bias instability) or falls
# as 1/tau (quantization)
NOISE_BAND = {"rate_random_walk": "longest", "bias_instability": "longest",
              "quantization": "shortest"}
BAND_OCTAVES = 3  # the full-rate tau band's tolerance at the end a noise term lifts (x8 in tau)


def tau_band_hit(where, family, level) -> dict:
    """G8's tau band for a noise-model case, on both tau axes of the report:

    - the decided one (the map's rows: block means after the AR prewhitening): whether a gyro
      tau cell is significant (``significant``), and whether the smallest-p one sits at the
      band the term lifts most (``hit``, :data:`NOISE_BAND`: the shortest or the longest);
    - the full-rate one (reported, not decided on): whether the smallest-p gyro cell lies within
      :data:`BAND_OCTAVES` octaves of that end of its axis (``full_hit``; its p ``full_p``). An
      octave band, not one cell: a bias instability's excess over white grows with tau while the
      longest cells have the fewest clusters, so the smallest p can fall an octave or two short
      of the end."""
    cells = [x for x in where if x["axis"] == "tau" and x["channel"].startswith("w")]
    out = {"significant": False, "hit": False, "full_hit": False, "full_p": 1.0}
    if family not in NOISE_BAND:
        return out
    longest = NOISE_BAND[family] == "longest"
    decided = [x for x in cells if x.get("rate") != "full"]
    if decided:
        taus = sorted({x["tau_s"] for x in decided})
        best = min(decided, key=lambda x: x["p"])
        out |= {"significant": bool(best.get("q", 1.0) < level),
                "hit": best["tau_s"] == (taus[-1] if longest else taus[0]),
                "tau_s": best["tau_s"]}
    full = [x for x in cells if x.get("rate") == "full"]
    if full:
        taus = sorted({x["tau_s"] for x in full})
        best = min(full, key=lambda x: x["p"])
        k = 2.0 ** BAND_OCTAVES
        out |= {"full_hit": bool(best["tau_s"] >= taus[-1] / k if longest
                                 else best["tau_s"] <= taus[0] * k),
                "full_p": float(best["p"]), "full_tau_s": best["tau_s"]}
    return out


# -- goal G6: design advice, closed loop (cw/ccw rotation; a temperature cycle) -------------
# the hidden coefficients: the gyro scale factors and misalignments (no signature on a still
# stand whose nominal model carries no Earth rate; a rate table drives them) and the gyro
# temperature coefficients (on a warm-up ramp a time drift; a temperature cycle tells them)
G6_PARAMS = {"scale_factor": ("sgx", "sgy", "sgz"),
             "misalignment": ("mgxy", "mgxz", "mgyx", "mgyz", "mgzx", "mgzy"),
             "temperature": ("tgx", "tgy", "tgz")}
G6_TEMP_NOISE_C = 0.01  # deg C, the temperature sensor's noise


def generate_closed_loop(out_dir, n_cases: int, *, seed: int = 0,
                         design: IMUDesign | None = None, families=tuple(G6_PARAMS),
                         fraction: float = 1.0) -> list[Path]:
    """Sealed multi-position records for the G6 closed loop: per case a family of
    :data:`G6_PARAMS` in turn, the nominal biases drawn as in :func:`generate`, and the hidden
    effect's gyro coefficients in a random direction with RMS ``fraction`` x the catalogue's
    prior scale (3000 ppm, 3 mrad, 10 deg/h/deg C). ``temperature`` records carry a ``temp``
    channel on a ramp of 2-4 deg C over the record (warming up), where Delta T is a linear
    function of time like the ``time_drift`` effect. The manifest keeps the whole instrument
    (display units) and the ramp."""
    from ..diagnose import IMU_LIBRARY
    from ..diagnose import IMU_PRIOR_BY_UNIT as PRIOR_BY_UNIT

    design = design or IMUDesign()
    sealer = Sealer(out_dir, seed)
    rng = sealer.rng
    key = jax.random.key(seed)
    for i in range(n_cases):
        family = families[i % len(families)]
        names = G6_PARAMS[family]
        prior = IMU_LIBRARY[family][1] or PRIOR_BY_UNIT[_SPACE[names[0]].display_unit]
        b = rng.standard_normal(len(names))
        b *= fraction * prior / np.sqrt(np.mean(b ** 2))
        instrument = {k: float(_SPACE[k].to_display(v)) for k, v in _truth_params(rng).items()
                      if k.startswith(("bg", "ba"))} | dict(zip(names, map(float, b)))
        truth = {"family": family, "fraction_of_prior": fraction, "instrument": instrument}
        if family == "temperature":
            truth["ramp_c"] = float(rng.uniform(2.0, 4.0))
        key, sub = jax.random.split(key)
        sealer.add(_simulate_g6(truth, design.all_poses, design, sub), truth)
    return sealer.close(design)


def _g6_temperature(truth, design, label=None):
    """The temperature (deg C, a function of time) of a ``temperature`` case on the record's
    own test (``label`` None: the ramp over the record's poses, then held) or on the advised
    one: :data:`~gyrojax.diagnose._imu.CYCLE_DESIGN` replaces the ramp by a cycle of period
    half the record and amplitude half the ramp (the advisor's own assumption); other designs
    keep the ramp, held at its end beyond it."""
    from ..diagnose import IMU_CYCLE_DESIGN as CYCLE_DESIGN
    from ..diagnose import IMU_CYCLE_MIN_C as CYCLE_MIN_C

    if "ramp_c" not in truth:
        return None
    span = design.span_s + design.turn_s * (len(design.all_poses) - 1)
    r = truth["ramp_c"]
    if label == CYCLE_DESIGN:
        amp = max(r / 2, CYCLE_MIN_C)
        return lambda t: 25.0 + r / 2 + amp * np.sin(4 * np.pi * np.asarray(t) / span)
    return lambda t: 25.0 + r * np.clip(np.asarray(t) / span, 0.0, 1.0)


def _simulate_g6(truth, poses, design, key, label=None):
    temp_c = _g6_temperature(truth, design, label)
    k1, k2 = jax.random.split(key)
    rec = simulate_imu(_SPACE.make(truth["instrument"], display=True), poses,
                       rate_hz=design.rate_hz, turn_s=design.turn_s,
                       latitude_deg=design.latitude_deg, arw=design.arw * units.DEG / 60,
                       vrw=design.vrw / 60, key=k1, temperature_c=temp_c)
    attrs = {k: v for k, v in rec.conditions.items() if k != "static_s"}  # the detector's truth
    y, chans = rec.y, rec.channels
    if temp_c is not None:  # the temperature as its sensor reads it
        temp = temp_c(np.asarray(rec.t)) + G6_TEMP_NOISE_C * np.asarray(
            jax.random.normal(k2, (len(rec.t),)))
        y, chans = jnp.concatenate([y, jnp.asarray(temp)[:, None]], axis=1), chans + ("temp",)
    return BenchRecord(rec.t, y, chans, tuple(sorted(attrs.items())))


def advised_poses(label: str, design: IMUDesign) -> list:
    """The poses of the test an IMU advice row names, from the record's ``design`` (the labels
    of :meth:`gyrojax.diagnose._imu.IMUProblem.designs`)."""
    from ..diagnose import IMU_CYCLE_DESIGN as CYCLE_DESIGN
    from ..diagnose import IMU_TABLE_DESIGN as TABLE_DESIGN

    if label == TABLE_DESIGN:
        return design.all_poses + table_poses(design.dwell_s)
    if label == "record twice as long":
        return design.all_poses * 2
    if label.startswith("12 poses"):
        return cube_poses(12, design.dwell_s * len(design.all_poses) / 12, seed=1)
    if label == CYCLE_DESIGN:
        return design.all_poses
    raise ValueError(f"advice design {label!r} is not an IMU design this harness knows")


def closed_loop(case_dir, hidden: str, *, design: IMUDesign | None = None, seed: int = 0,
                progress=None) -> list:
    """Goal G6's "cw/ccw rotation -> sf vs misalignment" on the cases of
    :func:`generate_closed_loop` (``hidden``: their family):
    :func:`~gyrojax.validation._harness.closed_loop`, the same instrument run again, new noise,
    on the poses the advisor's first design for ``hidden`` names."""
    from . import _harness

    design = design or IMUDesign()

    def rerun(rec, truth, label, key):
        return _simulate_g6(truth, advised_poses(label, design), design, key, label)

    # the sealed instrument holds the hidden gyro terms; the family's other coefficients (a
    # misalignment's accelerometer terms, which its determined combinations involve) are zero
    return _harness.closed_loop(case_dir, "imu", hidden, rerun,
                                lambda t: {k: t["instrument"].get(k, 0.0)
                                           for k in _SPACE.effect_names(hidden)},
                                holdout=design.holdout, seed=seed, progress=progress)
