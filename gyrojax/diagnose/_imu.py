"""The strapdown IMU rig as the diagnosis sees it (``--rig imu``).

Rows are block means of the static samples (static intervals from
:func:`gyrojax.estimate.multiposition.detect_static`; masked spans excluded), so long records stay
small; the turns between poses are not rows (the poses' up vectors are nuisance parameters,
two small-angle terms per pose about the accelerometer's first guess), but they carry north:
:func:`~gyrojax.estimate.multiposition.turn_chains` joins still poses by the turns the record
holds into chains, and the ``earth_rate`` effect is the whole Earth rate, ``k_earth`` (the
vertical part) and two terms per chain (``earth<j>_c``, ``earth<j>_s``: the horizontal part
``Omega cos(lat)`` at the chain's unknown heading; :meth:`IMUProblem.earth_reading` reads them).

Rate-table runs (design D4: the record's conditions ``table_rate_s``, flat ``(t0, t1,
rate_dps)`` triples, or the CLI's ``--table-run``) are segments too: the IMU turns about the
vertical at the commanded rate, and each run adds two nominal terms, the horizontal Earth rate,
which turns at minus the table rate in the body frame from a heading the stand does not record
(a run is no chain member). Mean effects are screened
on these rows exactly as for the other rigs, after **prewhitening**: an AR(p) noise model per
channel (order by BIC, p <= 5), fitted to the residual of the nominal model plus *every* catalogued
mean effect (so a catalogued drift is not taken for coloured noise), filters the residual and every
Jacobian column — the nominal model's colour would otherwise make every slow effect "significant".
Its innovation variance is divided by the dof that fit leaves (:func:`ar_noise_model`).

Noise-model effects are tested at the full sampling rate on the static residual of the same full
model: ``bias_instability`` and ``rate_random_walk`` by the likelihood-ratio tests of the Whittle
fit (:func:`gyrojax.analysis.spectral.fit_noise_likelihood`, band-limited to ``rate / 10`` for real
sensors' anti-alias roll-off) on static pieces of at least ``MIN_NOISE_PIECE_S``;
``quantization``, which lives up to the Nyquist frequency, by the MA(1) score test (the lag-one
autocorrelation, :func:`~._noise_tests.quantization_score`) on every static piece; ``outliers`` by the
excess kurtosis of non-overlapping first differences (one-sided). Each effect's p-value is the
smallest over channels, Bonferroni-corrected.

Auxiliary channels (``temp*``, ``tilt*``, ``supply*``, ``aux*``) ride along block by block and are
never fitted: the gap map's aux axis bins them (:meth:`IMUProblem.aux_signatures`) and the lag
axis reports their cross-correlation with the residual.

Held-out split: time-ordered (the last ``holdout`` of the static rows). Poses that lie wholly in
the held-out part get their two pose terms fitted there with everything else fixed (the
calibration is what is being checked; the held-out gap is corrected for those dofs).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..analysis.spectral import fit_noise_likelihood
from ..datasets import masked
from ..estimate import ScaledLevenbergMarquardt, convergence_note, solve_least_squares
from ..estimate.multiposition import (
    Segment,
    accel_units_problem,
    design_chain,
    detect_static,
    turn_chains,
)
from ..models.imu import (
    IMU_CHANNELS,
    MEAN_EFFECTS,
    NOISE_EFFECTS,
    THERMAL_EFFECTS,
    IMUConditions,
    IMURig,
    imu_measure,
    pose_frame,
)
from ..record import BenchRecord
from ._noise_tests import full_rate_tau_cells, outlier_score, quantization_score
from ._problem import AbstractGapProblem
from ._signatures import Signature, check_effects, coefficient_effect, effect_family_name
from ._turns import (
    build_turns,
    rescale_block,
    turn_jacobian,
    turn_level,
    turn_misclosure,
    turn_parts,
)

__all__ = ["IMUProblem", "IMU_LIBRARY"]

# effect -> (family, prior scale per coefficient, in each coefficient's display unit)
IMU_LIBRARY = {
    "earth_rate": ("earth", 1.0),
    "scale_factor": ("scale", 3000.0),  # ppm
    "misalignment": ("mounting", 3.0),  # mrad
    "g_sensitivity": ("g", 100.0),  # deg/h/g
    "time_drift": ("trend", None),  # per channel type, below
    "warmup_transient": ("transient", None),
    "temperature": ("thermal", None),
    "temperature_rate": ("thermal", None),
    "quantization": ("noise", None),
    "bias_instability": ("noise", None),
    "rate_random_walk": ("noise", None),
    "outliers": ("noise", None),
}
PRIOR_BY_UNIT = {"deg/h/h": 10.0, "mg/h": 1.0, "deg/h": 100.0, "mg": 5.0,
                  "deg/h/degC": 10.0, "mg/degC": 1.0, "deg/h/(degC/min)": 10.0,
                  "mg/(degC/min)": 1.0}
AUX_PREFIXES = ("temp", "tilt", "supply", "aux")  # auxiliary channels: not modelled, mapped
AUX_BINS = 5
POSE_SCALE = 1e-2  # rad, scale of the pose terms (conditioning only)
HRATE_SCALE = 1e-4  # rad/s, scale of a table run's horizontal Earth rate terms (conditioning)
CHAIN_SCALE = 1.0  # a chain's horizontal Earth rate terms, in units of Omega cos(lat)
MIN_NOISE_PIECE_S = 100.0  # s, shortest static piece that tests bias instability / RRW
NOISE_NULL_DRAWS = 200  # bootstrap periodograms per noise term's boundary law (spectral.py)
LONG_TAU_TERMS = ("bias_instability", "rate_random_walk")  # tested on those pieces only
TABLE_RATE_DPS = 10.0  # deg/s, the rate of the advisor's rate-table design (cw and ccw)
TABLE_TRIM_S = 0.2  # s cut from both ends of a table run (as the static detector trims)


def is_aux(channel: str) -> bool:
    """Whether a record channel is auxiliary (temperature, tilt, supply, ``aux*``): carried
    along block by block for the gap map's aux axis, never fitted."""
    return channel.lower().startswith(AUX_PREFIXES)


class IMUProblem(AbstractGapProblem):
    """One IMU record reduced to static block means, split by time into train / held-out.

    **Options:** `per_coefficient`: every coefficient of a many-coefficient catalogue effect an
    effect of its own (``g_sensitivity:gsxy``); `block_s`, `max_rows`: the block-mean length
    (default: the record's statics in at most ``max_rows`` rows)."""

    OPTIONS = {"per_coefficient": "screen every coefficient of the catalogue as an effect of "
                                  "its own (family:parameter)",
               "block_s": "block-mean length in s (default: at most max_rows rows)",
               "max_rows": "the most block-mean rows (default 1500)",
               "turns": "use the turns between still poses as a second residual block "
                        "(default: where the record holds them)"}
    NOISE_UNITS = {"wx": (1.0, "rad/s"), "wy": (1.0, "rad/s"), "wz": (1.0, "rad/s"),
                   "ax": (1.0, "m/s^2"), "ay": (1.0, "m/s^2"), "az": (1.0, "m/s^2")}
    CATALOGUE_NOTE = ("earth_rate is the whole Earth rate: k_earth (its vertical part) and, per "
                      "chain of still poses joined by turns the record holds, earth<j>_c and "
                      "earth<j>_s (the horizontal part at the chain's unknown heading, in units "
                      "of Omega cos(lat)); with --per-coefficient every parameter of another "
                      "mean effect above is an effect of its own, named effect:parameter (e.g. "
                      "g_sensitivity:gsxy)")

    @classmethod
    def catalogue(cls, **options) -> dict:
        """The catalogue: effect name -> family."""
        return {k: v[0] for k, v in IMU_LIBRARY.items()}

    @classmethod
    def single_coefficients(cls, *, per_coefficient: bool = False, **options) -> bool:
        return bool(per_coefficient)

    def __init__(self, record: BenchRecord, *, holdout: float = 0.25, noise_std=None,
                 effects=None, block_s: float | None = None, max_rows: int = 1500,
                 per_coefficient: bool = False, turns: bool = True):
        # single coefficients (family:parameter) are checked below
        check_effects([effect_family_name(e) for e in effects or ()], IMU_LIBRARY, "imu")
        bad = [c for c in record.channels if c not in IMU_CHANNELS and not is_aux(c)]
        if bad:
            raise ValueError(f"channels {bad} are neither IMU channels {IMU_CHANNELS} nor "
                             f"auxiliary channels (names starting with {', '.join(AUX_PREFIXES)})")
        sensors = [c for c in record.channels if c in IMU_CHANNELS]
        if not sensors:
            raise ValueError(f"the record has no IMU channel; give one or more of {IMU_CHANNELS}")
        y_rec = np.asarray(record.y, float)
        self.aux_names = tuple(c for c in record.channels if is_aux(c))
        self._aux_raw = y_rec[:, [record.channels.index(c) for c in self.aux_names]]
        if self.aux_names:
            record = BenchRecord(record.t, jnp.asarray(
                y_rec[:, [record.channels.index(c) for c in sensors]]), tuple(sensors),
                record.attrs)
        self.record = record
        self.cond = IMUConditions.from_record(record)
        self.rig = IMURig()
        self.space = self.rig.param_space
        self.channels = tuple(record.channels)
        self.ch_idx = np.array([IMU_CHANNELS.index(c) for c in self.channels])
        self.has_accel = any(c.startswith("a") for c in self.channels)
        table = table_segments(record)
        static = [s for s in detect_static(record)
                  if not any(s.t0 <= tb.t1 and tb.t0 <= s.t1 for tb, _ in table)]
        steady = sorted([(s, 0.0) for s in static] + table, key=lambda x: x[0].i0)
        if not steady:
            raise ValueError("no static interval found (>= 1 s still) and no rate-table run "
                             "(conditions table_rate_s): the IMU diagnosis needs a static, "
                             "multi-position or rate-table record")
        self.segments = [s for s, _ in steady]
        if all(c in record.channels for c in ("ax", "ay", "az")):  # in m/s^2 (SI)?
            f = np.stack([np.asarray(record.channel(c), float) for c in ("ax", "ay", "az")], 1)
            problem = accel_units_problem([f[s.i0:s.i1].mean(0) for s in self.segments],
                                          self.cond.gravity)
            if problem:
                raise ValueError(problem)
        self.omega = np.array([w for _, w in steady])  # table rate per segment, rad/s
        self.noise_std = noise_std
        self.rate_hz = self.cond.rate_hz
        lib = list(effects) if effects is not None else list(IMU_LIBRARY)
        # per coefficient, single coefficients may be asked for by name (family:parameter)
        picked = [e for e in lib if ":" in e]
        if picked and not per_coefficient:
            raise ValueError(f"effects {picked} name single coefficients; add --per-coefficient "
                             "(per_coefficient=True), or give their families")
        coefs = {e: [n for n in self.space.effect_names(e) if n != "tau_w"] for e in MEAN_EFFECTS}
        known = {coefficient_effect(e, n) for e, ns in coefs.items() if len(ns) > 1 for n in ns}
        bad = [e for e in picked if e not in known]
        if bad:
            raise ValueError(f"unknown coefficient effect(s) {bad} for --rig imu: give "
                             "family:parameter of a mean effect with several coefficients, "
                             "e.g. g_sensitivity:gsxy (gyrojax effects --rig imu lists them)")
        lib = list(dict.fromkeys(effect_family_name(e) for e in lib))
        self.notes = []
        # the temperature effects act on the record's temperature channel (the first aux
        # channel named temp*): Delta T from its train mean and dT/dt of its block means
        self.temp_name = next((a for a in self.aux_names if a.lower().startswith("temp")), None)
        dropped = [e for e in THERMAL_EFFECTS if e in lib] if self.temp_name is None else []
        if dropped:
            lib = [e for e in lib if e not in dropped]
            self.notes.append(f"{' and '.join(dropped)} not screened: the record has no "
                              "temperature channel (an aux channel named temp*)")
        if "earth_rate" in lib and np.isnan(self.cond.latitude_deg):
            lib.remove("earth_rate")
            self.notes.append("earth_rate not screened: the record gives no latitude "
                              "(--latitude DEG)")
        self.effects = tuple(e for e in lib if e in MEAN_EFFECTS)
        self.noise_effects = tuple(e for e in lib if e in NOISE_EFFECTS)
        self._build_rows(block_s, max_rows)
        n = len(self.t)
        self.n_train = n - int(round(holdout * n)) if holdout > 0 else n
        self.thermal = (np.zeros(n), np.zeros(n))
        if self.temp_name is not None:
            temp = self.aux[:, self.aux_names.index(self.temp_name)]
            # dT/dt: the least-squares slope of the raw temperature samples (turns included)
            # within +-W of each row, W = max(block, 1 % of the record): a temperature moves
            # over minutes, and its sensor's noise would swamp a two-row difference
            t_raw = np.asarray(self.record.t, float)
            half = max(self.block / self.rate_hz, 0.01 * (t_raw[-1] - t_raw[0]))
            raw = self._aux_raw[:, self.aux_names.index(self.temp_name)]
            self.thermal = (temp - temp[: self.n_train].mean(),
                            _local_slope(t_raw, raw, self.t, half))
        # the turns between still poses: a second residual block (its level: fit_nominal)
        # each entry's level (rad; set by fit_nominal), its scale over the gyro-noise prior,
        # the dof of that scale and the basis the null draws re-estimate it through
        self.turn_std, self.turn_scale, self.turn_dof, self._turn_q = None, 1.0, np.inf, None
        self.turn_start = {}  # the gyro scale and misalignment terms that fit the turns
        self.turns = build_turns(
            self.record, self.segments, self.omega == 0, self.u0,
            self.t[self.n_train] if self.n_train < n else np.inf,
            self._thermal_at) if turns and self.has_accel else None
        if self.turns is not None and self.turns.n_train < 2:
            self.notes.append(f"the {self.turns.m} turn(s) between poses not used: "
                              f"{self.turns.n_train} end before the held-out rows")
            self.turns = None
        # poses with no train row are fitted on the held-out rows (profiled)
        self.heldout_poses = sorted(set(self.seg[self.n_train:]) - set(self.seg[: self.n_train]))
        self.heldout_dof = len(self._pose_terms(self.heldout_poses))
        self.nominal_names = tuple(n for n in self.space.nominal_names()
                                   if n[1] in "ga" and _channel_of(n) in self.channels)
        self.pose_names = self._pose_terms(range(self.n_pose))
        self.nominal_scales = np.concatenate([self.space.scales(self.nominal_names),
                                              [_pose_scale(n) for n in self.pose_names]])
        self.nominal_units = tuple(self.space[k].display_unit for k in self.nominal_names) + \
            tuple("rad/s" if n[-1] in "cs" else "rad" for n in self.pose_names)
        self.nominal_display_scales = self.nominal_scales / np.concatenate([
            [self.space[k].display_factor for k in self.nominal_names],
            np.ones(len(self.pose_names))])
        self.effect_names = {e: tuple(n for n in self.space.effect_names(e) if n != "tau_w"
                                      and _relevant(n, self.channels)) for e in self.effects}
        if "earth_rate" in self.effect_names:  # + each chain's horizontal Earth rate
            heads = sorted(set(self.chains[0][self.seg[: self.n_train]]) - {-1})
            self.effect_names["earth_rate"] += tuple(
                _term_name(int(k), x) for k in heads for x in "CS")
        if per_coefficient:  # every coefficient of a many-coefficient effect an effect of its own
            # (the Earth rate stays whole: its chains' terms are the heading's nuisance)
            self.effect_names = {k: v for e, names in self.effect_names.items() for k, v in (
                [(coefficient_effect(e, n), (n,)) for n in names]
                if len(names) > 1 and e != "earth_rate" else [(e, names)])}
            if picked:  # the families asked for whole, and the coefficients asked for by name
                whole = set(effects) - set(picked)
                self.effect_names = {k: v for k, v in self.effect_names.items()
                                     if k in picked or effect_family_name(k) in whole}
                missing = [e for e in picked if e not in self.effect_names]
                if missing:
                    raise ValueError(
                        f"effects {missing} are not screened on this record: a coefficient "
                        f"needs its sensor among the channels {self.channels}, and an effect "
                        "with one coefficient keeps its family's name (e.g. earth_rate); see "
                        "gyrojax effects --rig imu")
            self.effects = tuple(self.effect_names)
        span = self.t[self.n_train - 1] - self.t[0]
        self.tau_grid_s = tuple(float(x) for x in np.geomspace(span / 30, span / 2, 6))
        self.lines = {}
        self._ar = None
        self.earth_readings = {}

    # -- data reduction --------------------------------------------------------------------
    def _build_rows(self, block_s, max_rows):
        t = np.asarray(self.record.t, float)
        y = np.asarray(self.record.y, float)
        bad = masked(self.record)
        total = sum(s.n for s in self.segments)
        dt = 1.0 / self.rate_hz
        m = max(1, int(np.ceil(total / max_rows))) if block_s is None else \
            max(1, int(round(block_s / dt)))
        self.block = m
        ts, ys, seg, aux = [], [], [], []
        for k, s in enumerate(self.segments):
            keep = ~bad[s.i0:s.i1]
            tk, yk = t[s.i0:s.i1][keep], y[s.i0:s.i1][keep]
            nb = len(tk) // m
            if nb == 0:
                continue
            ts.append(tk[: nb * m].reshape(nb, m).mean(1))
            ys.append(yk[: nb * m].reshape(nb, m, -1).mean(1))
            ak = self._aux_raw[s.i0:s.i1][keep]
            aux.append(ak[: nb * m].reshape(nb, m, -1).mean(1))
            seg.append(np.full(nb, k))
        self.t = np.concatenate(ts)
        self.y = np.concatenate(ys)
        self.seg = np.concatenate(seg)
        self.aux = np.concatenate(aux)  # (rows, auxiliary channels), block means
        self.n_pose = len(self.segments)
        # first guess of each pose's up vector: the accelerometer mean (or z up)
        u0 = np.tile([0.0, 0.0, 1.0], (self.n_pose, 1))
        acc = [i for i, c in enumerate(self.channels) if c.startswith("a")]
        if len(acc) == 3:
            for k in range(self.n_pose):
                rows = self.seg == k
                if rows.any():
                    v = self.y[rows][:, acc].mean(0)
                    u0[k] = v / np.linalg.norm(v)
        self.u0 = u0
        # the still poses' chains (joined by recorded turns): the horizontal Earth rate's frame
        n = self.n_pose
        self.chains = (np.full(n, -1), np.zeros((n, 3)), np.zeros((n, 3)))
        self.chain_miss = []
        if "earth_rate" in self.effects and any(c.startswith("w") for c in self.channels):
            *chains, self.chain_miss = turn_chains(self.record, self.segments, u0,
                                                   members=self.omega == 0)
            self.chains = tuple(chains)

    def _pose_terms(self, poses, omega=None):
        """Nuisance terms of the poses ``poses``: each pose's two tilts (``pose<k>_a``, ``_b``:
        the up vector, given accelerometers) and, on a table run seen by a gyro, the
        horizontal Earth rate's two components at the run's start (``pose<k>_c``, ``_s``: it
        turns at minus the table rate in the body frame; a heading the stand does not
        record)."""
        omega = self.omega if omega is None else omega
        gyro = any(c.startswith("w") for c in self.channels)
        return tuple(f"pose{k}_{x}" for k in poses for x in
                     ("ab" if self.has_accel else "") + ("cs" if gyro and omega[k] else ""))

    def _geo(self, u0, omega, chains=None):
        """The compiled model's pose geometry: up vectors, tilt frames, table rates, the
        block-mean gain of a sinusoid at the table rate (``sinc``, exact for full blocks) and
        the chains (``(head, a, b)`` of :func:`~gyrojax.estimate.multiposition.turn_chains`;
        default the record's)."""
        e1, e2 = pose_frame(u0)
        head, a, b = self.chains if chains is None else chains
        return (u0, e1, e2, omega, np.sinc(omega * self.block / self.rate_hz / (2 * np.pi)),
                np.maximum(head, 0), a, b)

    # -- model -----------------------------------------------------------------------------
    def _compiled(self, n_pose):
        """The compiled model, its directional Jacobian and its fit for ``n_pose`` poses on
        this record's conditions and channels (cached across problems; a candidate design's
        poses count compiles the first two only)."""
        ch = tuple(int(i) for i in self.ch_idx)
        # the conditions by value: an unknown latitude is NaN, and NaN != NaN
        key = (n_pose, repr((self.cond.latitude_deg, self.cond.gravity, self.cond.rate_hz)), ch)
        if key not in _COMPILED:
            _COMPILED[key] = _build(n_pose, self.cond, ch)
        return _COMPILED[key]

    def _full(self, base, names, t, seg, vec=None, design=None, thermal=None):
        """The whole mean-model vector (per-scale units) at ``base`` with ``names`` set from
        ``vec`` (default zeros), the indices of ``names`` in it, and the compiled model's other
        arguments."""
        geo = tuple(jnp.asarray(g) for g in (design or self._geo(self.u0, self.omega)))
        n_pose = len(geo[0])
        allp = _all_params(n_pose)
        pose = {} if design is not None else base.get("_pose", {})
        full = np.array([pose.get(n, 0.0) / _pose_scale(n) if _is_pose(n)
                         else float(base[n]) / _SPACE[n].scale for n in allp])
        idx = [allp.index(n) for n in names]
        full[idx] = 0.0 if vec is None else np.asarray(vec, float)
        args = (float(base["tau_w"]), jnp.asarray(t), jnp.asarray(seg), geo,
                self._thermal_at(t) if thermal is None else thermal)
        return full, idx, args

    def _call(self, which, names, base, t, seg, vec=None, design=None, thermal=None,
              turns=False):
        """Model (``which=0``) or its Jacobian in the free parameters ``names`` (``which=1``) at
        ``base`` with ``names`` set from ``vec`` (per-scale units; default zeros). One compiled
        model per poses count, conditions and channels serves every name set: it takes the
        whole mean-model vector, and the Jacobian is the tangents along ``names`` alone.
        ``turns``: the turns' misclosures ``(2 m,)`` (rad; :mod:`._turns`) instead of the
        rows."""
        names = tuple(names)
        full, idx, args = self._full(base, names, t, seg, vec, design, thermal)
        model, jvps, _, turn, turn_jvps = self._compiled(len(args[3][0]))
        if turns:  # the turns' misclosures instead of the rows: (2 m, ...)
            m2 = 2 * self.turns.m
            args = (args[0], args[3], self.turns.arrays)
            model, jvps = (lambda *a: turn(*a)[:m2]), (lambda *a: turn_jvps(*a)[:m2])
        if which == 0:
            return np.asarray(model(jnp.asarray(full), *args))
        # one tangent per name, JVP_WIDTH at a time (the last chunk padded): one compilation
        # per shape whatever the names, and no columns computed to be thrown away
        cols = []
        for a in range(0, max(len(idx), 1), JVP_WIDTH):
            chunk = idx[a: a + JVP_WIDTH]
            dirs = np.zeros((JVP_WIDTH, len(full)))
            dirs[np.arange(len(chunk)), chunk] = 1.0
            cols.append(np.asarray(jvps(jnp.asarray(full), jnp.asarray(dirs), *args))
                        [..., : len(chunk)])
        return np.concatenate(cols, axis=-1)

    def _thermal_at(self, t):
        """``(Delta T, dT/dt)`` at times ``t``: the record's rows where ``t`` are its rows'
        times, else interpolated (held at the record's ends beyond it: a candidate design
        assumes no temperature change of its own)."""
        t = np.asarray(t, float)
        if t.shape == self.t.shape and np.array_equal(t, self.t):
            return tuple(jnp.asarray(x) for x in self.thermal)
        return tuple(jnp.asarray(np.interp(t, self.t, x)) for x in self.thermal)

    def _vector(self, params, names):
        return jnp.asarray([params["_pose"].get(n, 0.0) / _pose_scale(n) if _is_pose(n)
                            else params[n] / self.space[n].scale for n in names])

    def predict(self, params, extra=None):
        """Model rows (block means) over train + held-out for a params dict (effects included)."""
        names = self.nominal_names + self.pose_names
        out = self._call(0, names, params, self.t, self.seg, self._vector(params, names))
        return out if extra is None else out + extra

    # -- fits ------------------------------------------------------------------------------
    def _gn(self, params, free, rows, turns: bool = False):
        """Levenberg-Marquardt (optimistix, :func:`~gyrojax.estimate.solve_least_squares`) on
        ``free`` over ``rows``: one compiled fit per poses count over the whole mean-model
        vector, the other terms masked (held) and the other rows weighted 0. ``turns``: the
        train turns' misclosures join the fit, weighted by their level (once it is known). The
        model is nearly linear, so a few steps do; a fit that does not converge says so in
        :attr:`notes`."""
        names = tuple(free)
        full, idx, model_args = self._full(params, names, self.t, self.seg,
                                           self._vector(params, names))
        where, valid = _padded(idx, len(self.nominal_names) + len(self.pose_names))
        rw = np.zeros(len(self.t))
        rw[rows] = 1.0
        fit = self._compiled(len(self.segments))[2]
        block = None
        if self.turns is not None:  # weight 0 until the turns join: one compiled fit for both
            on = turns and self.turn_std is not None
            w = self.turns.weights(self.turn_std) if on else np.zeros(2 * self.turns.arrays[0].shape[0])
            block = (self.turns.arrays, jnp.asarray(w), jnp.asarray(_TURN_RIDGE if on else 0.0))
        value, sol = fit(jnp.asarray(full), jnp.asarray(where), jnp.asarray(valid),
                         jnp.asarray(rw), jnp.asarray(self.y),
                         jnp.asarray(1.0 / self._scale_rows()), block, *model_args)
        note = convergence_note(sol, "the IMU fit of " + (
            "the nominal model" if set(names) <= set(self.nominal_names + self.pose_names)
            else ", ".join(n for n in names if not _is_pose(n)
                           and n not in self.nominal_names)))
        if note is not None:
            self.notes.append(note)
        return self._unpack(params, names, np.asarray(value)[: len(idx)])

    def _unpack(self, params, names, vec):
        out = dict(params)
        out["_pose"] = dict(params["_pose"])
        for i, n in enumerate(names):
            if _is_pose(n):
                out["_pose"][n] = float(vec[i]) * _pose_scale(n)
            else:
                out[n] = float(vec[i]) * self.space[n].scale
        return out

    def _scale_rows(self):
        """Per-channel scale for the fit weights (robust noise of the block means)."""
        d = np.diff(self.y[: self.n_train], axis=0)
        s = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2)
        return np.maximum(s, 1e-12)

    def _base(self):
        p = {k: float(v) for k, v in self.space.make().items()}
        p["_pose"] = dict.fromkeys(self.pose_names, 0.0)
        return p

    def fit_nominal(self):
        """The nominal model on the train rows, then its AR noise model; with turns, their
        levels (:meth:`_fit_turn_level`), and the nominal model again on rows and turns
        together (and its AR noise model)."""
        p = self._base()
        tr = np.arange(self.n_train)
        train_poses = self.pose_names if not self.heldout_poses else tuple(
            n for n in self.pose_names if int(n[4:].split("_")[0]) not in self.heldout_poses)
        p = self._gn(p, self.nominal_names + train_poses, tr)
        p = self._fit_heldout_poses(p)
        self._fit_ar(p)
        if self.turns is not None:
            self._fit_turn_level(p)
            p = self._gn(p, self.nominal_names + train_poses, tr, turns=True)
            p = self._fit_heldout_poses(p)
            self._fit_ar(p)
        return p

    # -- the turns: a second residual block ------------------------------------------------
    def _fit_turn_level(self, p):
        """The turns' levels: the gyros' white noise over each turn
        (:attr:`~._turns.TurnBlock.prior_std`), scaled to the full model's residual
        (:func:`~._turns.turn_level`, the nominal model and every catalogued mean effect, the
        warm-up at its middle decay time, linearised); where the turns leave too few dof for
        that, they are dropped with a note. A large gyro scale or misalignment error (20 %)
        turns a 100-deg turn's misclosure far from linear, so the full model is linearised
        where those nine terms fit the turns (the gyro calibration's fit, every other term
        held): :attr:`turn_start`, which the refits start from too."""
        n, c, m2 = self.n_train, len(self.channels), 2 * self.turns.n_train
        prior = np.repeat(self.turns.prior_std, 2)
        self.turn_std = prior
        gyro = tuple(x for x in self.space.names if x[:2] in ("sg", "mg"))
        full = self._gn(dict(p, tau_w=self.tau_grid_s[len(self.tau_grid_s) // 2]), gyro,
                        np.arange(0), turns=True)
        names = self.nominal_names + self.pose_names
        gcols = self.whiten(self.full_model_columns(full)[:n]) / self._ar_sigma[None, :, None]
        gres = self.whiten((self.y - self.predict(full))[:n]) / self._ar_sigma
        bcols = np.concatenate([self._call(1, names, full, self.t, self.seg,
                                           self._vector(full, names), turns=True),
                                self._full_effect_columns(full, turns=True)], axis=1)[:m2]
        bres = -self._call(0, names, full, self.t, self.seg, self._vector(full, names),
                           turns=True)[:m2]
        scale, dof, q = turn_level(gcols.reshape(n * c, -1), gres.reshape(-1),
                                   bcols / prior[:m2, None], bres / prior[:m2])
        if not np.isfinite(scale):
            self.notes.append(
                f"the {self.turns.m} turns between poses not used: the full model leaves "
                f"{dof:.1f} dof on the {self.turns.n_train} train turns' misclosures, too few "
                "to estimate their noise level (a hand turn's misclosure holds more than the "
                "gyros' white noise)")
            self.turns, self.turn_std = None, None
            return
        self.turn_scale, self.turn_dof, self._turn_q = scale, dof, q
        self.turn_std = scale * prior
        self.turn_start = {x: full[x] for x in gyro}

    @property
    def block_train(self) -> int:
        """Train entries of the turns' block (two per train turn; 0 without turns)."""
        return 0 if self.turns is None else 2 * self.turns.n_train

    def block_residual(self, params):
        """The turns' whitened misclosure entries ``(2 m,)``, train turns first (``None``
        without turns): minus the misclosure over its level, as the rows' data minus model."""
        if self.turns is None:
            return None
        names = self.nominal_names + self.pose_names
        return -self._call(0, names, params, self.t, self.seg, self._vector(params, names),
                           turns=True) / self.turn_std

    def block_rescale(self, z):
        """Null draws ``(b, n c + 2 m_train)`` with the turns' level re-estimated as on the
        data (:func:`~._turns.rescale_block`)."""
        return rescale_block(z, self._turn_q, self.block_train, self.turn_dof)

    def block_cells(self):
        """The gap map's turn cells: each train turn (2 dof), the turns mostly about each body
        axis, and all train turns, as ``(axis, label, channel, columns (2 m_train, k))``."""
        if self.turns is None:
            return []
        tb, m2 = self.turns, self.block_train
        eye = np.eye(m2)
        labels = tb.labels()
        out = [("turn", labels[j], "turns", eye[:, 2 * j: 2 * j + 2])
               for j in range(tb.n_train)]
        for ax in "xyz":
            js = [j for j in range(tb.n_train) if tb.axis[j] == ax]
            if js:
                cols = eye[:, [2 * j + i for j in js for i in (0, 1)]]
                out.append(("turn", f"turns about {ax} ({len(js)})", "turns", cols))
        out.append(("turn", f"all train turns ({tb.n_train})", "turns", eye))
        return out

    @property
    def noise_fit(self) -> dict:
        """The turns' level (deg) and its dof, where the turns are used."""
        if self.turns is None:
            return {}
        return {"turns": {"count": self.turns.m, "train": self.turns.n_train,
                          "std_deg": float(np.degrees(np.median(self.turn_std))),
                          "scale": float(self.turn_scale), "dof": float(self.turn_dof),
                          "source": "the gyros' white noise over each turn, scaled to the full "
                                    "model's residual"}}

    def _fit_heldout_poses(self, p):
        names = self._pose_terms(self.heldout_poses)
        if not names:
            return p
        return self._gn(p, names, np.arange(self.n_train, len(self.t)))

    # -- prewhitening ----------------------------------------------------------------------
    def _full_effect_columns(self, params, t=None, seg=None, turns=False):
        """Raw (unwhitened) Jacobian columns of every catalogued mean effect at the null, all
        warm-up grid values included: ``(rows, channels, k)`` (``turns``: the turns'
        misclosures', ``(2 m, k)``)."""
        t = self.t if t is None else t
        seg = self.seg if seg is None else seg
        cols = self._effect_columns(params, t, seg, turns=turns)
        cols = [c for e in self.effects for n in self.effect_names[e] for c in cols[n]]
        if turns:
            return np.stack(cols, axis=1) if cols else np.zeros((2 * self.turns.m, 0))
        return np.stack(cols, axis=2) if cols else np.zeros((len(t), len(self.channels), 0))

    def _effect_columns(self, params, t, seg, design=None, thermal=None, whiten=None,
                        turns=False):
        """Jacobian columns ``(rows, channels)`` of every catalogued mean-effect coefficient at
        the null (raw, or through ``whiten``; ``turns``: of the turns' misclosures, ``(2 m,)``):
        name -> one column per warm-up decay time (one for the others). One batched JVP (and
        whitening) per decay time and one for the rest, whatever the catalogue's
        granularity."""
        effects = [e for e in self.effects if self.effect_names[e]]
        warm = [n for e in effects if _grid_effect(e) for n in self.effect_names[e]]
        plain = [n for e in effects if not _grid_effect(e) for n in self.effect_names[e]]
        out = {}
        for names, taus in ((plain, (None,)), (warm, self.tau_grid_s)):
            for tau in taus if names else ():
                base = dict(params) | ({"tau_w": tau} if tau else {})
                j = self._call(1, names, base, t, seg, design=design, thermal=thermal,
                               turns=turns)
                j = j if whiten is None else whiten(j)
                for i, n in enumerate(names):
                    out.setdefault(n, []).append(j[..., i])
        return out

    def _fit_ar(self, params, max_order: int = 5):
        """AR(p) per channel on the full-model train residual, p by BIC; stores the filters."""
        n = self.n_train
        self._ar, self._ar_sigma, dof = ar_noise_model(
            (self.y - self.predict(params))[:n], self.full_model_columns(params)[:n],
            self.seg[:n], max_order)
        self._ar_dof = float(min(dof))
        self._mean_part = None

    def full_model_columns(self, params):
        """Raw Jacobian columns of the nominal model (biases, poses) and every catalogued mean
        effect at ``params``: ``(rows, channels, k)``, the noise model's regressors."""
        names = self.nominal_names + self.pose_names
        jn = self._call(1, names, params, self.t, self.seg, self._vector(params, names))
        return np.concatenate([jn, self._full_effect_columns(params)], axis=2)

    def whiten(self, x):
        """Apply the per-channel AR prewhitening filters (within each pose) to ``x`` of shape
        ``(rows, channels, ...)``."""
        out = np.array(x, float, copy=True)
        for c, phi in enumerate(self._ar):
            if len(phi) == 0:
                continue
            for k in np.unique(self.seg[: len(x)]):
                idx = np.flatnonzero(self.seg[: len(x)] == k)
                xs = np.asarray(x)[idx, c]
                ys = xs.copy()
                for i, ph in enumerate(phi, start=1):
                    ys[i:] -= ph * xs[:-i]
                out[idx, c] = ys
        return out

    def position_signatures(self, sigma):
        """Per pose with train rows, the whitened (AR-filtered, scaled) signature of an offset
        on that pose alone: the gap map's position axis (one condition: no condition axis)."""
        n = self.n_train
        out = []
        for k in np.unique(self.seg[:n]):
            rows = self.seg[:n] == k
            if rows.sum() < 2:
                continue
            ind = np.repeat(rows.astype(float)[:, None], len(self.channels), axis=1)
            t = self.t[:n][rows]
            out.append((f"pose {int(k)} ({t[0]:.0f}-{t[-1]:.0f} s)", "static",
                        self.whiten(ind) / np.asarray(sigma)[None, :]))
        return out

    @property
    def aux_rows(self) -> dict:
        """The auxiliary channels' block means on the train rows (name -> values)."""
        return {a: self.aux[: self.n_train, i] for i, a in enumerate(self.aux_names)}

    def aux_signatures(self, sigma, bins: int = AUX_BINS):
        """Per auxiliary channel, ``bins`` ranges of equal train-row count (quantiles), each
        with the whitened signature of an offset on its rows: the gap map's aux axis (a bias
        that follows the temperature lights the hot and cold bins). A channel that is constant
        on the train rows has no bins."""
        out = []
        for name, a in self.aux_rows.items():
            edges = np.quantile(a, np.linspace(0, 1, bins + 1))
            if not edges[-1] > edges[0]:
                continue
            k = np.clip(np.searchsorted(edges, a, side="right") - 1, 0, bins - 1)
            for b in np.unique(k):
                rows = k == b
                ind = np.repeat(rows.astype(float)[:, None], len(self.channels), axis=1)
                out.append((f"{name} {edges[b]:.4g}-{edges[b + 1]:.4g}", name,
                            self.whiten(ind) / np.asarray(sigma)[None, :]))
        return out

    def noise_level(self, resid):
        if self.noise_std is not None:
            s = np.broadcast_to(np.asarray(self.noise_std, float), (len(self.channels),)).copy()
            return s, np.inf, "given"
        order = [len(p) for p in self._ar]
        return self._ar_sigma, self._ar_dof, \
            f"AR prewhitening per channel, orders {order} (BIC), on the full-model residual"

    def standardize(self, resid, sigma):
        return self.whiten(resid) / sigma

    # -- Jacobians -------------------------------------------------------------------------
    def jacobians(self, params, sigma, *, conditions=None, t=None):
        """Whitened (AR-filtered, per-channel scaled) Jacobians: nominal (biases, poses) and one
        Signature per mean effect (warm-up: one slice per decay time)."""
        if conditions is not None:
            return self._design_jacobians(params, sigma, conditions)
        t, seg = self.t, self.seg
        names = self.nominal_names + self.pose_names
        jn = self._call(1, names, params, t, seg, self._vector(params, names))
        jn = (self.whiten(jn) / sigma[None, :, None]).reshape(-1, len(names))
        if self.turns is not None:  # the turns' block: rows after the still rows'
            jn = np.concatenate([jn, self._call(1, names, params, t, seg, self._vector(
                params, names), turns=True) / self.turn_std[:, None]])
        return jn, self._signatures(params, sigma, t, seg, self.whiten,
                                    turns=self.turns is not None)

    def _signatures(self, params, sigma, t, seg, whiten, design=None, thermal=None,
                    turns=False):
        """One :class:`Signature` per catalogued mean effect with coefficients (whitened by
        ``whiten``, scaled by ``sigma`` and the prior scales; warm-up: one slice per decay
        time; ``turns``: the turns' block appended to the rows). A pair of per-coefficient
        warm-ups refits at one decay time (the model has one ``tau_w``)."""
        cols = self._effect_columns(params, t, seg, design, thermal, whiten)
        block = self._effect_columns(params, t, seg, turns=True) if turns else None
        out = []
        for e in self.effects:
            names = self.effect_names[e]
            if not names:
                continue
            fam, prior = IMU_LIBRARY[effect_family_name(e)]
            pri = np.array([prior if prior is not None else
                            PRIOR_BY_UNIT[self._unit(n)] for n in names])
            factor = np.array([1.0 / CHAIN_SCALE if _is_pose(n) else
                               self.space[n].display_factor / self.space[n].scale
                               for n in names])
            slices = [(np.stack([cols[n][g] for n in names], axis=2)
                       / sigma[None, :, None]).reshape(-1, len(names))
                      for g in range(len(cols[names[0]]))]
            if block is not None:  # the turns' rows after the still rows'
                slices = [np.concatenate([j, np.stack([block[n][g] for n in names], axis=1)
                                          / self.turn_std[:, None]])
                          for g, j in enumerate(slices)]
            slices = [j * factor * pri for j in slices]
            grid = tuple(x / 3600 for x in self.tau_grid_s) if _grid_effect(e) else ()
            out.append(Signature(e, fam, names, tuple(self._unit(n) for n in names),
                                 pri, np.stack(slices), grid, "decay time" if grid else "",
                                 "h" if grid else ""))
        return out

    def _unit(self, name):
        """Display unit of an effect coefficient (a chain's Earth-rate terms: Omega cos(lat))."""
        return "1" if _is_pose(name) else self.space[name].display_unit

    def _display(self, params, name):
        """An effect coefficient of ``params`` in its display unit."""
        if _is_pose(name):
            return float(params["_pose"].get(name, 0.0))
        return float(self.space[name].to_display(params[name]))

    # -- refits ----------------------------------------------------------------------------
    def refit(self, params0, sig_choices, sigma):
        p = dict(params0)
        p["_pose"] = dict(params0["_pose"])
        free = list(self.nominal_names) + [n for n in self.pose_names if int(
            n[4:].split("_")[0]) not in self.heldout_poses]
        for sig, g in sig_choices:
            free += list(sig.names)
            if _grid_effect(sig.name):
                p["tau_w"] = self.tau_grid_s[g]
            # a gyro scale or misalignment term starts where it fits the turns (the optimum
            # does not move; the Levenberg-Marquardt steps from 0 to 20 % do)
            p |= {x: v for x, v in self.turn_start.items() if x in sig.names}
        p = self._gn(p, tuple(free), np.arange(self.n_train), turns=True)
        p = self._fit_heldout_poses(p)
        coeffs = {n: self._display(p, n) for sig, _ in sig_choices for n in sig.names}
        if any(effect_family_name(sig.name) == "earth_rate" for sig, _ in sig_choices):
            self.earth_readings[tuple(sig.name for sig, _ in sig_choices)] = \
                self.earth_reading(p)
        return self.predict(p), coeffs, p

    def earth_reading(self, params) -> dict | None:
        """The refitted Earth rate read as a size and a heading per chain (``None`` when the
        refit has no chain term).

        Each chain's two terms give its horizontal Earth rate in units of ``Omega cos(lat)``:
        size ``k_h`` (the check of ``k_earth``) and north at ``heading_deg`` from the chain's
        first pose's ``e1`` about up. Where the record leaves directions open (a rate common to
        every chain is a gyro bias: two antipodal poses without a recorded turn between them),
        the reading puts every chain's size at ``k_earth`` (optimistix, from several starts)
        and lists the readings that fit, mirror images included.

        **Returns:** ``{"k_earth", "chains": [{"poses", "k_h", "heading_deg", "axes_deg"}],
        "open": gyro biases traded with the chains, "readings": [chains per reading],
        "text"}``; ``axes_deg``: each body axis within 60 deg of horizontal in the chain's
        first pose, its angle from north (deg)."""
        head = self.chains[0]
        terms = sorted({_pose_term(n)[0] for n in params["_pose"] if n.startswith("earth")})
        if not terms or not np.isfinite(self.cond.latitude_deg):
            return None
        gyro = [i for i, c in enumerate(self.channels) if c.startswith("w")]
        biases = tuple(n for n in self.nominal_names if n.startswith("bg"))
        chain = tuple(_term_name(k, x) for k in terms for x in "CS")
        free = biases + chain
        x0 = np.asarray(self._vector(params, free))
        jac = self._call(1, free, params, self.t, self.seg, x0)[:, gyro]
        jac = jac.reshape(-1, len(free))
        scale = np.maximum(np.linalg.norm(jac, axis=0), 1e-300)
        _, sv, vt = np.linalg.svd(jac / scale, full_matrices=False)
        null = vt[sv < OPEN_TOL * sv[0]]
        k_e = float(params["k_earth"])
        n_b = len(biases)
        readings = [x0]
        if len(null):
            basis = (null / scale).T  # the open directions in per-scale units, each moving
            basis = basis / np.linalg.norm(basis[n_b:], axis=0)  # the chains' terms by 1
            readings = _size_readings(x0, basis, n_b, k_e)
        out = []
        for x in readings:
            cs = np.asarray(x[n_b:]).reshape(-1, 2) * CHAIN_SCALE
            out.append([self._chain_reading(k, c, s) for k, (c, s) in zip(terms, cs)])
        opened = sorted({biases[i] for v in null for i in range(n_b) if abs(v[i]) > 0.05})
        rec = {"k_earth": k_e, "chains": out[0] if out else [], "open": opened,
               "readings": out}
        rec["text"] = _earth_text(rec, [int(np.sum(head == k)) for k in terms])
        return rec

    def _chain_reading(self, k, c, s):
        head, a, b = self.chains
        psi = float(np.arctan2(s, c))
        north = np.cos(psi) * a[k] + np.sin(psi) * b[k]
        u = self.u0[k]
        axes = {}
        for i, ax in enumerate("xyz"):
            proj = np.eye(3)[i] - u[i] * u
            if np.linalg.norm(proj) > 0.5:
                axes[ax] = float(np.degrees(np.arccos(np.clip(
                    north @ proj / np.linalg.norm(proj), -1, 1))))
        return {"poses": [int(j) for j in np.flatnonzero(head == k)], "k_h": float(np.hypot(c, s)),
                "heading_deg": float(np.degrees(psi)), "axes_deg": axes}

    def refit_reading(self, effects: tuple) -> dict | None:
        """The Earth-rate reading of the refit of ``effects`` (:meth:`earth_reading`)."""
        return self.earth_readings.get(tuple(effects))

    def verdict_notes(self, verdict: dict) -> list:
        """The Earth-rate reading of the verdict's refit, when it names earth_rate."""
        r = self.earth_readings.get(tuple(verdict.get("effects") or ()))
        return [r["text"]] if r else []

    # -- designs ---------------------------------------------------------------------------
    def designs(self):
        """Candidate designs: the record twice as long (same poses); 12 poses (the six axis-up
        poses and six tilted ones) of the same total static time; and the record followed by a
        rate-table test (:data:`TABLE_DESIGN`, :func:`table_runs`: counter-clockwise and
        clockwise at ``TABLE_RATE_DPS`` with x, y and z up in turn, twice, each run as long as
        the record's mean pose; CIGTF's STB, design D4), where the gyro scale factors and
        misalignments, which a still stand sees only through the Earth rate (no signature
        under the nominal model, which carries none), are driven by the table rate, and cw/ccw
        tells them (odd in the rate) from biases and g-sensitivity (even)."""
        from ..models.imu import cube_poses

        out = [("record twice as long", ("long", None), None)]
        if self.has_accel and len(self.channels) == 6:
            ups = np.array([p.up for p in cube_poses(12, seed=1)])
            out.append(("12 poses (axes up/down + 6 tilted)", ("poses", ups), None))
        if self.has_accel and any(c.startswith("w") for c in self.channels) \
                and not np.any(self.omega):
            out.append((TABLE_DESIGN, ("table", None), None))
        if self.temp_name is not None:
            out.append((CYCLE_DESIGN, ("cycle", None), None))
        return out

    def thermal_cycle(self, t):
        """The temperature cycle of :data:`CYCLE_DESIGN` at times ``t``: ``(Delta T, dT/dt)``
        of a sinusoid of period half the record and amplitude half the record's temperature
        range (at least ``CYCLE_MIN_C``)."""
        t = np.asarray(t, float)
        span = self.t[-1] - self.t[0]
        amp = max(0.5 * float(np.ptp(self.thermal[0])), CYCLE_MIN_C)
        w = 4 * np.pi / max(span, 1e-9)
        return amp * np.sin(w * (t - self.t[0])), amp * w * np.cos(w * (t - self.t[0]))

    def _design_jacobians(self, params, sigma, design):
        kind, ups = design
        nom = self._vector(params, self.nominal_names)
        if kind == "cycle":  # the same poses and times under a temperature cycle
            names = self.nominal_names + self.pose_names
            thermal = tuple(jnp.asarray(x) for x in self.thermal_cycle(self.t))
            jn = self._call(1, names, params, self.t, self.seg, self._vector(params, names),
                            thermal=thermal) / sigma[None, :, None]
            sigs = self._signatures(params, sigma, self.t, self.seg, lambda x: x,
                                    thermal=thermal)
            return jn.reshape(-1, len(names)), sigs
        if kind == "long":
            t = np.concatenate([self.t, self.t + (self.t[-1] - self.t[0]) + 1.0])
            seg = np.concatenate([self.seg, self.seg])
            geo, names = None, self.nominal_names + self.pose_names
            vec = self._vector(params, names)
        else:
            if kind == "poses":
                per = max(1, len(self.t) // len(ups))
                seg = np.repeat(np.arange(len(ups)), per)
                t = np.linspace(self.t[0], self.t[-1], len(seg))
                u0 = ups / np.linalg.norm(ups, axis=1, keepdims=True)
                omega = np.zeros(len(u0))
                chains = design_chain(u0)
            else:  # the record, then the table's runs
                table_up, table_rate = table_runs()
                step = self.block / self.rate_hz
                per = max(1, int(np.mean([x.t1 - x.t0 for x in self.segments]) // step))
                n_run = len(table_rate)
                t = np.concatenate([self.t, self.t[-1] + step * (1 + np.arange(n_run * per))])
                seg = np.concatenate([self.seg, self.n_pose + np.repeat(np.arange(n_run), per)])
                u0 = np.concatenate([self.u0, table_up])
                omega = np.concatenate([self.omega, table_rate])
                chains = tuple(np.concatenate([x, np.zeros((n_run,) + x.shape[1:], x.dtype)
                                               - (x.ndim == 1)]) for x in self.chains)
            geo = self._geo(u0, omega, chains)
            names = self.nominal_names + self._pose_terms(range(len(u0)), omega)
            # every pose at its first guess, as the effects' columns are (``_call`` with a
            # design): one linearisation point, so the poses absorb what they structurally can
            vec = jnp.zeros(len(names)).at[: len(nom)].set(nom)
        jn = self._call(1, names, params, t, seg, vec, geo) / sigma[None, :, None]
        sigs = self._signatures(params, sigma, t, seg, lambda x: x, geo)
        return jn.reshape(-1, len(names)), sigs

    def display_nominal(self, params):
        out = {k: float(self.space[k].to_display(params[k])) for k in self.nominal_names}
        return out

    def _static_residuals(self, params):
        """Two residuals at the full rate on the train part of every static interval (>= 64
        samples), per channel index: of the full mean model (the nominal plus every catalogued
        mean effect, fitted to the rows: noise beyond them) and of the nominal model (where a
        slow drift and a random walk compete)."""
        t_all = np.asarray(self.record.t, float)
        y_all = np.asarray(self.record.y, float)
        bad = masked(self.record)
        t_split = self.t[self.n_train - 1]
        # full-model mean part at the block rows -> interpolated to the samples
        names = self.nominal_names + self.pose_names
        jn = self._call(1, names, params, self.t, self.seg, self._vector(params, names))
        je = self._full_effect_columns(params)
        pred = self.predict(params)
        resid_rows = self.y - pred
        n = self.n_train
        pieces = {c: [] for c in range(len(self.channels))}
        nominal = {c: [] for c in range(len(self.channels))}
        where = []  # (sample indices, block rows) of each piece, the same for every channel
        for k, s in enumerate(self.segments):
            rows = np.flatnonzero(self.seg == k)
            idx = np.arange(s.i0, s.i1)
            idx = idx[(~bad[idx]) & (t_all[idx] <= t_split)]
            if rows.size >= 2 and idx.size >= 64:
                where.append((idx, rows))
        columns = {}
        for c in range(len(self.channels)):
            x = np.concatenate([jn[:, c], je[:, c]], axis=1)
            beta, *_ = np.linalg.lstsq(x[:n], resid_rows[:n, c], rcond=None)
            fitted_rows = pred[:, c] + x @ beta
            for idx, rows in where:
                pieces[c].append(y_all[idx, c] - np.interp(t_all[idx], self.t[rows],
                                                           fitted_rows[rows]))
                nominal[c].append(y_all[idx, c] - np.interp(t_all[idx], self.t[rows],
                                                            pred[rows, c]))
            # the columns those fits removed, for the noise tests' bootstrap (noise_screen):
            # the full model's (nominal + effects) and the nominal model's, non-zero ones only
            used = np.any(x[:n] != 0, axis=0)
            columns[c] = (x[:, used], np.flatnonzero(used) < jn.shape[2])
        self._residuals = (params, pieces, nominal)
        self._removed = (where, columns)
        return pieces, nominal

    def _removed_at(self, c):
        """The columns the full and the nominal fit removed from channel ``c``'s static pieces
        (:meth:`_static_residuals`), at the samples of the pieces :meth:`_long` keeps: two lists
        of ``(n_i, m)`` arrays."""
        where, columns = self._removed
        x, is_nominal = columns[c]
        t_all = np.asarray(self.record.t, float)
        full, nom = [], []
        for idx, rows in where:
            if not self._is_long(idx.size):
                continue
            # np.interp of every column at once: the same brackets and weights for all
            tr, ts = self.t[rows], np.clip(t_all[idx], self.t[rows][0], self.t[rows][-1])
            j = np.clip(np.searchsorted(tr, ts, side="right") - 1, 0, rows.size - 2)
            w = ((ts - tr[j]) / (tr[j + 1] - tr[j]))[:, None]
            at = x[rows[j]] * (1 - w) + x[rows[j + 1]] * w
            full.append(at)
            nom.append(at[:, is_nominal])
        return full, nom

    def _is_long(self, n_samples):
        return n_samples >= MIN_NOISE_PIECE_S * self.rate_hz

    def _long(self, pcs):
        return [x for x in pcs if self._is_long(x.size)]

    def full_rate_tau_cells(self, params):
        """The gap map's full-rate tau band (:func:`~._noise_tests.full_rate_tau_cells`) of the
        full-model residual on the static pieces that test the slow noise terms (>=
        ``MIN_NOISE_PIECE_S``): where in tau the noise departs from white, down to one sample
        (reported, not decided on). Its white reference has the full mean fit's columns removed,
        as the residual has (their slow columns lower the longest cells' white mean by up to
        ~20 %)."""
        done = self._residuals
        pieces = done[1] if done is not None and done[0] is params else \
            self._static_residuals(params)[0]
        return full_rate_tau_cells({c: self._long(p) for c, p in pieces.items()}, self.channels,
                                   1.0 / self.rate_hz,
                                   removed={c: self._removed_at(c)[0] for c in pieces})

    # -- noise-model effects ---------------------------------------------------------------
    def noise_screen(self, params, alpha: float = 0.05):
        """Noise-model effects on the full-rate static residual (train part) of the full mean
        model. Returns one row per noise effect: p (min over channels, Bonferroni), the channel,
        the statistic and the fitted term per channel in display units."""
        if not self.noise_effects:
            return []
        pieces, nominal = self._static_residuals(params)
        rows_out = []
        # bias instability and rate random walk live at long tau: only static pieces of at
        # least MIN_NOISE_PIECE_S test them (short hand-held poses carry settling motion)
        fits, fits_nom = {}, {}
        for c in pieces:
            long_full = self._long(pieces[c])
            long_nom = self._long(nominal[c])
            if long_full:
                at = functools.cache(lambda c=c: self._removed_at(c))
                fits[c], fits_nom[c] = (fit_noise_likelihood(
                    x, self.rate_hz, null_draws=NOISE_NULL_DRAWS, seed=c,
                    bootstrap_terms=LONG_TAU_TERMS, removed=lambda k=k: at()[k])
                    for k, x in enumerate((long_full, long_nom)))
        longest = max((x.size for pcs in pieces.values() for x in pcs), default=0) / self.rate_hz
        for e in self.noise_effects:
            per = {}
            if e in LONG_TAU_TERMS and not fits:
                rows_out.append({"name": e, "family": "noise", "kind": "noise", "p": 1.0,
                                 "p_nominal": 1.0, "channel": None, "statistic": 0.0,
                                 "fitted": {}, "unit": {}, "testable": False,
                                 "statistic_kind": f"not testable: the longest static piece is "
                                 f"{longest:.0f} s < {MIN_NOISE_PIECE_S:.0f} s"})
                continue
            for c, pcs in pieces.items():
                if not pcs or (e in LONG_TAU_TERMS and c not in fits):
                    continue
                if e == "quantization":
                    p_q, z, q = quantization_score(pcs, 1.0 / self.rate_hz)
                    per[self.channels[c]] = (p_q, z * abs(z), q,
                                             quantization_score(nominal[c], 1.0 / self.rate_hz)[0])
                elif e == "outliers":
                    p_z, z, k = outlier_score(pcs)
                    per[self.channels[c]] = (p_z, z * abs(z), k, p_z)
                else:
                    fit = fits[c]
                    per[self.channels[c]] = (fit.p[e], fit.lr[e], getattr(fit.terms, e),
                                             fits_nom[c].p[e])
            if not per:
                continue
            best = max(per, key=lambda ch: per[ch][1])
            rows_out.append({
                "name": e, "family": "noise", "kind": "noise",
                "p": min(1.0, per[best][0] * len(per)), "channel": best,
                "p_nominal": min(1.0, min(v[3] for v in per.values()) * len(per)),
                "statistic": float(per[best][1]),
                "statistic_kind": _NOISE_STATISTIC.get(
                    e, "likelihood ratio (Whittle), p from its bootstrap boundary law"),
                "fitted": {ch: _noise_display(e, ch, v[2]) for ch, v in per.items()},
                "testable": True,
                "unit": {ch: _noise_unit(e, ch) for ch in per},
            })
        self.noise_fits = {self.channels[c]: f for c, f in fits.items()}
        return rows_out


_NOISE_STATISTIC = {"outliers": "excess kurtosis z * |z|",
                    "quantization": "lag-one autocorrelation score z * |z| (MA(1) Rao test, "
                                    "full rate)"}
_COMPILED: dict = {}
_SPACE = IMURig().param_space


def horizontal_earth_rate(cond) -> float:
    """``Omega cos(lat)`` in rad/s at the conditions' latitude (0 where it is unknown)."""
    lat = cond.latitude_deg
    return 0.0 if np.isnan(lat) else float(units.EARTH_RATE * np.cos(np.radians(lat)))


def _params(vec, base, n_pose):
    """Parameter dict and pose terms from the compiled model's vector ``vec`` (per-scale units,
    ordered as :func:`_all_params`) over ``base``: slices of the vector, no per-entry writes."""
    ns = len(_ALL_SCALAR)
    p = dict(base) | dict(zip(_ALL_SCALAR, vec[:ns] * _SCALAR_SCALES))
    grid = vec[ns:].reshape(n_pose, 6)
    return p, {x: grid[:, j] * _pose_scale(_term_name(0, x)) for j, x in enumerate("abcsCS")}


@functools.partial(jax.jit, static_argnums=3)
def _size_fit(x0, basis, z0, n_b, k_e):
    """Move ``x0`` along ``basis`` (the directions the record leaves open) from ``z0`` until
    every chain's horizontal rate has size ``k_e`` (Levenberg-Marquardt, optimistix)."""
    def resid(z, _):
        cs = (x0 + basis @ z)[n_b:].reshape(-1, 2) * CHAIN_SCALE
        return jnp.sqrt(jnp.sum(cs ** 2, axis=1) + 1e-30) - k_e

    sol = solve_least_squares(resid, z0, None, max_steps=100)
    return sol.value, resid(sol.value, None)


SIZE_STARTS = 12  # starts of the size-constrained Earth-rate reading
OPEN_TOL = 1e-2  # singular value (of the largest) below which a direction is left open


def _size_readings(x0, basis, n_b, k_e):
    """The distinct points ``x0 + basis z`` whose chains all have size ``k_e``, from
    ``SIZE_STARTS`` seeded starts (none when no start reaches it)."""
    rng = np.random.default_rng(0)
    found = []
    for _ in range(SIZE_STARTS):
        z, r = _size_fit(jnp.asarray(x0), jnp.asarray(basis),
                         jnp.asarray(rng.normal(size=basis.shape[1]) * max(k_e, 0.1)),
                         n_b, k_e)
        x = np.asarray(x0 + basis @ np.asarray(z))
        if np.max(np.abs(np.asarray(r))) < 1e-6 * max(k_e, 1e-3) and not any(
                np.allclose(x, y, atol=1e-5) for y in found):
            found.append(x)
    return found


def _earth_text(rec, n_poses) -> str:
    """One line of :meth:`IMUProblem.earth_reading`."""
    def chain(c, n):
        axes = ", ".join(f"{ax} {v:.0f} deg" for ax, v in c["axes_deg"].items())
        return (f"chain of pose {c['poses'][0]} ({n} pose{'s' if n != 1 else ''}): "
                f"{c['k_h']:.3f} x Omega cos(lat), axes from north: {axes}")

    text = (f"Earth rate: k_earth {rec['k_earth']:.4f} of the vertical part; horizontal part: "
            + "; ".join(chain(c, n) for c, n in zip(rec["chains"], n_poses)))
    if rec["open"]:
        many = len(rec["readings"])
        text += (f". The record leaves open a rate common to its chains (it is the bias of "
                 f"{', '.join(rec['open'])}): the size k_earth Omega cos(lat) fixes it up to "
                 f"{many} reading{'s' if many != 1 else ''}")
        if many > 1:
            first = rec["readings"][0]
            differ = sorted({ax for r in rec["readings"][1:] for c0, c in zip(first, r)
                             for ax in c["axes_deg"]
                             if abs(c["axes_deg"][ax] - c0["axes_deg"].get(ax, np.nan)) > 45})
            alt = "; ".join(", ".join(f"{ax} {v:.0f}" for ax, v in c["axes_deg"].items())
                            for r in rec["readings"][1:] for c in r)
            text += (f" (the other: {alt} deg from north); they differ in the north of "
                     f"{', '.join(differ) or 'no axis'}, which its bias absorbs")
    return text


def _local_slope(t, x, at, half):
    """Least-squares slope of ``x(t)`` over the samples within ``+-half`` of each time in ``at``
    (prefix sums: linear time). NaN samples are left out."""
    ok = np.isfinite(x)
    t, x = t[ok], x[ok]
    t0 = t - t.mean()
    c = [np.concatenate([[0.0], np.cumsum(v)]) for v in (np.ones_like(t0), t0, x, t0 * t0,
                                                          t0 * x)]
    i0 = np.searchsorted(t, np.asarray(at) - half, side="left")
    i1 = np.searchsorted(t, np.asarray(at) + half, side="right")
    n, st, sx, stt, stx = (v[i1] - v[i0] for v in c)
    den = n * stt - st * st
    return np.where(den > 0, (n * stx - st * sx) / np.where(den > 0, den, 1.0), 0.0)


def _grid_effect(name: str) -> bool:
    return effect_family_name(name) == "warmup_transient"


def _is_pose(name: str) -> bool:
    """A term of the compiled model's pose part: ``pose<k>_<a|b|c|s>`` (a pose's tilts and a
    table run's horizontal Earth rate) or ``earth<k>_<c|s>`` (a chain's horizontal Earth rate,
    ``k`` its first pose)."""
    return name.startswith(("pose", "earth"))


def _pose_term(name: str):
    """``(pose index, term letter)`` of a pose-part name; a chain's terms are ``C`` and ``S``."""
    if name.startswith("earth"):
        k, x = name[5:].split("_")
        return int(k), x.upper()
    k, x = name[4:].split("_")
    return int(k), x


def _term_name(k: int, x: str) -> str:
    return f"earth{k}_{x.lower()}" if x in "CS" else f"pose{k}_{x}"


def _pose_scale(name):
    if name.startswith("earth"):
        return CHAIN_SCALE
    return HRATE_SCALE if name[-1] in "cs" else POSE_SCALE


# every mean-model parameter (the nominal biases and the mean effects' terms, not tau_w)
_ALL_SCALAR = tuple(n for n in _SPACE.names if _SPACE[n].effect in (None,) + MEAN_EFFECTS
                    and n != "tau_w")


_SCALAR_SCALES = np.array([_SPACE[n].scale for n in _ALL_SCALAR])


@functools.cache
def _all_params(n_pose):
    """The compiled model's vector: every mean-model parameter, then each pose's four terms and
    the two horizontal-Earth-rate terms of a chain starting there."""
    return _ALL_SCALAR + tuple(_term_name(k, x) for k in range(n_pose) for x in "abcsCS")


_FIT_STEPS = 30  # optimistix steps of an IMU fit
# a fit with the turns adds (_TURN_RIDGE v)^2 per fitted entry v (per-scale units) to its sum
# of squares in noise units: it pins the valley of a common rotation of the gyro and
# accelerometer frames (without it the Xsens refits crept along it for 60 steps), and pulls a
# term with standard error se (per-scale units) by 1e-4 se^2 of its value
_TURN_RIDGE = 1e-2


def _build(n_pose, cond, ch_idx):
    ch = np.asarray(ch_idx)
    base = {n: 0.0 for n in _SPACE.names}
    horizontal = horizontal_earth_rate(cond)

    def f(vec, tau_w, t, seg, geo, thermal):
        p, x = _params(vec, base | {"tau_w": tau_w}, n_pose)
        u0, e1, e2, omega, gain, head, ca, cb = geo
        u = u0[seg] + x["a"][seg][:, None] * e1[seg] + x["b"][seg][:, None] * e2[seg]
        u = u / jnp.linalg.norm(u, axis=1, keepdims=True)
        # a table run turns the IMU about the vertical: body rate omega * up, plus the
        # horizontal Earth rate turning at -omega in the body frame (its block mean: gain)
        c, s = x["c"][seg] * gain[seg], x["s"][seg] * gain[seg]
        cw, sw = jnp.cos(omega[seg] * t), jnp.sin(omega[seg] * t)
        h = (c * cw + s * sw)[:, None] * e1[seg] + (s * cw - c * sw)[:, None] * e2[seg]
        # a still pose's horizontal Earth rate: its chain's two terms along the chain's
        # horizontal frame carried to the pose (zero off the chains)
        hd = head[seg]
        h = h + horizontal * (x["C"][hd][:, None] * ca[seg] + x["S"][hd][:, None] * cb[seg])
        return imu_measure(p, u, t, cond, omega[seg][:, None] * u + h, thermal)[:, ch]

    def jvps(vec, dirs, *args):
        """The Jacobian along the rows of ``dirs`` (one-hot: selected columns), last axis."""
        return jax.vmap(lambda d: jax.jvp(lambda v: f(v, *args), (vec,), (d,))[1],
                        out_axes=-1)(dirs)

    def parts(vec, tau_w, geo, arrays):
        p, x = _params(vec, base | {"tau_w": tau_w}, n_pose)
        return turn_parts(p, x["a"], x["b"], geo[0], geo[1], geo[2], arrays)

    @jax.custom_jvp
    def turn(vec, tau_w, geo, arrays):
        """The turns' misclosures (:func:`~._turns.turn_misclosure`) at ``vec``; its derivative
        in ``vec`` alone (the rest is data), through :func:`~._turns.turn_jacobian`."""
        p, x = _params(vec, base | {"tau_w": tau_w}, n_pose)
        return turn_misclosure(p, x["a"], x["b"], geo[0], geo[1], geo[2], arrays)

    @turn.defjvp
    def _turn_jvp(primals, tangents):
        vec, tau_w, geo, arrays = primals
        value, jac = turn_jacobian(lambda v, a: parts(v, tau_w, geo, a), vec, geo[1], geo[2],
                                   arrays)
        return value, jac @ tangents[0]

    def turn_jvps(vec, dirs, *args):
        """The misclosures' Jacobian along the rows of ``dirs``, last axis."""
        return jax.vmap(lambda d: jax.jvp(lambda v: turn(v, *args), (vec,), (d,))[1],
                        out_axes=-1)(dirs)

    def fit(full, where, valid, rw, y, w, turns, *args):
        """The entries ``where`` of ``full`` (those ``valid`` marks; the rest padding) fitted to
        the rows ``rw`` marks of ``y`` (per-channel weights ``w``) and, where ``turns`` is
        ``(arrays, weights, ridge)`` (not ``None``), to the turns' misclosures weighted by
        ``weights``, with the ridge ``ridge`` (all 0: the rows alone, the same compiled fit):
        (the fitted entries, the solution)."""
        def resid(v, data):
            full, where, valid, rw, y, w, turns, *rest = data
            x = full.at[where].add(v * valid)
            out = ((y - f(x, *rest)) * w[None, :] * rw[:, None]).reshape(-1)
            if turns is not None:
                # with the turns, a common rotation of the gyro and accelerometer frames (their
                # misalignments' antisymmetric parts, with the poses) changes nothing: a small
                # ridge on the fitted entries pins that valley (_TURN_RIDGE)
                out = jnp.concatenate([out, turn(x, rest[0], rest[3], turns[0]) * turns[1],
                                       turns[2] * v * valid])
            return out

        start = full[where] * valid
        data = (full.at[where].multiply(1.0 - valid), where, valid, rw, y, w, turns, *args)
        sol = solve_least_squares(resid, start, data, max_steps=_FIT_STEPS,
                                  solver=ScaledLevenbergMarquardt(gram=True))
        return sol.value * valid, sol

    return jax.jit(f), jax.jit(jvps), jax.jit(fit), jax.jit(turn), jax.jit(turn_jvps)


def _padded(idx, at_least: int = 0):
    """``(where, valid)``: the indices ``idx`` padded to a multiple of ``JVP_WIDTH``, at least
    ``at_least`` wide (the padding points at entry 0, weight 0): one compiled fit per width.
    The record's nominal terms and poses set the least width, so the nominal fit, the held-out
    poses' and the refits with an effect or two share one compilation; a width for every
    effect's columns besides (96 on 12 poses) made the nominal fits 2x slower."""
    n = max(len(idx), at_least)
    width = JVP_WIDTH * max(1, -(-n // JVP_WIDTH))
    where = np.zeros(width, int)
    where[: len(idx)] = idx
    return where, (np.arange(width) < len(idx)).astype(float)


JVP_WIDTH = 32  # tangents per directional Jacobian call, and a fit's width a multiple of it


CYCLE_MIN_C = 1.0  # deg C, the smallest amplitude of the advisor's temperature cycle
CYCLE_DESIGN = ("the record under a temperature cycle (period half the record, amplitude half "
                "its temperature range, >= 1 deg C)")
TABLE_DESIGN = (f"the record + a rate table: ccw/cw at {TABLE_RATE_DPS:g} deg/s with x, y, z up, "
                "twice (12 runs)")


def table_runs():
    """The advisor's rate-table test (design D4): up vectors ``(12, 3)`` and table rates
    ``(12,)`` in rad/s: x, y and z up in turn, each counter-clockwise then clockwise (seen from
    above), the sequence twice (so that a time-ordered held-out quarter holds a whole pass)."""
    up = np.tile(np.repeat(np.eye(3), 2, axis=0), (2, 1))
    return up, np.radians(TABLE_RATE_DPS) * np.tile([1.0, -1.0], 6)


def table_segments(record: BenchRecord) -> list:
    """The record's rate-table runs from its conditions ``table_rate_s`` (flat (t0, t1,
    rate_dps) triples, the table's commanded constant rates about the vertical): ``(Segment,
    rate in rad/s)`` pairs, ``TABLE_TRIM_S`` cut from both ends."""
    raw = record.conditions.get("table_rate_s")
    if raw is None:
        return []
    a = np.asarray(raw, float).reshape(-1)
    if a.size == 0 or a.size % 3:
        raise ValueError(f"conditions table_rate_s has {a.size} numbers; give flat (t0_s, "
                         "t1_s, rate_dps) triples, one per constant-rate table run")
    t = np.asarray(record.t, float)
    runs = a.reshape(-1, 3)
    order = np.argsort(runs[:, 0])
    if np.any(runs[order][1:, 0] < runs[order][:-1, 1]):
        raise ValueError("conditions table_rate_s: two table runs overlap in time; give each "
                         "constant-rate run once, (t0, t1, rate_dps) with t1 before the next t0")
    out = []
    for t0, t1, r in runs:
        if not (np.isfinite([t0, t1, r]).all() and t1 > t0 and r != 0):
            raise ValueError(f"table_rate_s run ({t0:g}, {t1:g}, {r:g}): need t1 > t0 and a "
                             "finite non-zero rate in deg/s (a still pose needs no entry)")
        idx = np.flatnonzero((t >= t0 + TABLE_TRIM_S) & (t <= t1 - TABLE_TRIM_S))
        if idx.size < 2:
            raise ValueError(f"table_rate_s run {t0:g}-{t1:g} s holds fewer than 2 samples of "
                             f"the record ({t[0]:g}-{t[-1]:g} s); check its times (s from the "
                             "record start)")
        out.append((Segment(int(idx[0]), int(idx[-1]) + 1, float(t[idx[0]]), float(t[idx[-1]])),
                    float(np.radians(r))))
    return out


def _noise_unit(e, ch):
    gyro = ch.startswith("w")
    return {"quantization": "arcsec" if gyro else "m/s",
            "bias_instability": "deg/h" if gyro else "mg",
            "rate_random_walk": "deg/h/sqrt(h)" if gyro else "mg/sqrt(h)",
            "outliers": "excess kurtosis"}[e]


def _noise_display(e, ch, v):
    return float(v) if e == "outliers" else float(units.to_unit(v, _noise_unit(e, ch)))


def _channel_of(name):
    """Channel a nominal bias belongs to: bgx -> wx, bay -> ay."""
    return ("w" if name[1] == "g" else "a") + name[2]


def _relevant(name, channels):
    """Does effect parameter ``name`` touch a channel the record has?"""
    gyro = any(c.startswith("w") for c in channels)
    accel = any(c.startswith("a") for c in channels)
    if name[:2] in ("tg", "rg"):
        return gyro
    if name == "k_earth" or name[:2] in ("sg", "mg", "gs", "dg", "wg"):
        return gyro and (accel or name[:2] in ("dg", "wg"))
    return accel


def ar_noise_model(resid, cols, seg, max_order: int = 5):
    """Per channel: the residual of ``resid`` (``(n, c)``) after least squares on that channel's
    columns ``cols[:, ch]`` (``(n, c, k)``), an AR(p) fit to it within the poses ``seg``, ``p <=
    max_order`` by BIC. Returns ``(phis, sigma, dof)``: the filters, the innovation standard
    deviations and their dof. The residual lost ``rank`` dof to the columns and ``p`` to the AR
    fit, and the innovations' mean square is divided by what is left: the plain mean square puts
    sigma^2 low by ``(rank + p) / n`` (3 % on the rate-table design D4), and every score test
    on the whitened residual reads that as signal."""
    phis, sig, dof = [], [], []
    for ch in range(resid.shape[1]):
        beta, _, rank, _ = np.linalg.lstsq(cols[:, ch], resid[:, ch], rcond=None)
        r = resid[:, ch] - cols[:, ch] @ beta
        best = None
        for p in range(max_order + 1):
            phi, s2, m = _ar_fit(r, seg, p)
            bic = m * np.log(s2) + p * np.log(max(m, 2))
            if best is None or bic < best[0]:
                best = (bic, phi, s2, m)
        _, phi, s2, m = best
        free = max(m - len(phi) - int(rank), 1)
        phis.append(phi)
        sig.append(np.sqrt(s2 * m / free))
        dof.append(free)
    return phis, np.array(sig), dof


def _ar_fit(r, seg, p):
    """Least-squares AR(p) within poses; returns (phi, innovation variance, rows used)."""
    if p == 0:
        return np.zeros(0), float(np.mean(r ** 2)), len(r)
    xs, ys = [], []
    for k in np.unique(seg):
        rk = r[seg == k]
        if len(rk) <= p + 1:
            continue
        ys.append(rk[p:])
        xs.append(np.stack([rk[p - i: len(rk) - i] for i in range(1, p + 1)], 1))
    if not ys:
        return np.zeros(0), float(np.mean(r ** 2)), len(r)
    x, y = np.concatenate(xs), np.concatenate(ys)
    phi, *_ = np.linalg.lstsq(x, y, rcond=None)
    e = y - x @ phi
    return phi, float(np.mean(e ** 2)), len(y)
