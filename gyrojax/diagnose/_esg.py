"""The non-contact gyro rig as the diagnosis sees it: nominal fit, Jacobians, refits, designs.

Everything runs on the rig with the base misalignment as a rotation vector ``dchi1..3`` (so the
structural null direction ``dchi || u`` shows as "no signature", and a refit can reproduce what the
screening tested). The nominal fit starts from the integral regression of the rig's default
``eps``-normal-to-``u`` form; the two forms agree exactly at null effects. The nominal fit and
every refit are one compiled Levenberg-Marquardt fit (optimistix) over the same superset of
parameters, the ones not fitted masked. The nominal noise model is white per channel or, on
request, white + flicker (``flicker_b`` given, or a REML level): then every row -- tests, refits,
held-out gap -- is whitened by the flicker model's Kalman innovations
(:mod:`gyrojax.analysis.flicker`).
"""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..analysis.flicker import (
    FLICKER_STD_PER_B,
    flicker_taus,
    innovations,
    reml_rho,
    rho_to_b,
    whiten,
)
from ..estimate._lstsq import convergence_note, solve_least_squares
from ..estimate.regression import integral_regression
from ..models.esg import SCHEMES, ESGConditions, ESGRig, check_angle_units
from ..record import BenchRecord
from ..simulate import integrate
from ._problem import AbstractGapProblem, first_difference_level
from ._signatures import Signature, check_effects, onset_grid

__all__ = ["ESGProblem", "ESG_LIBRARY", "NOISE_MODELS", "SIDEREAL_DAY"]

SIDEREAL_DAY = 2 * np.pi / units.EARTH_RATE  # s
# effect -> (family, prior scale per coefficient in display units, grid)
ESG_LIBRARY = {
    "rotor_tilt": ("mounting", 600.0),  # arcsec (10 arcmin, the source's figure)
    "base_misalignment": ("mounting", 60.0),  # arcsec (1 arcmin)
    "drift_transient": ("transient", 0.3),  # deg/h (m0 - m*), decay time on a grid
    "drift_ramp": ("trend", 0.002),  # deg/h per h
    "drift_step": ("step", 0.05),  # deg/h, onset on a grid
    "diurnal_line": ("line", 5.0),  # arcsec on each gimbal angle (pier tilt, HVAC)
}
TRANSIENT_TIMES_H = tuple(float(x) for x in np.geomspace(0.25, 3.0, 8))
_GRID_PARAM = {"drift_transient": "k_tr", "drift_step": "t_step"}  # effect -> its grid parameter
_GRID_EFFECTS = tuple(_GRID_PARAM)

_MAX_ITER = 30  # optimistix steps (trust-region trials included) of the nominal fit and each refit
# the nominal noise model of the gimbal angles: white, or white + flicker (GM sum) at a given
# level or one estimated by REML on the full-model residual (:mod:`gyrojax.analysis.flicker`)
NOISE_MODELS = ("white", "white+flicker")


def _grid_value(effect: str, hours: float) -> float:
    """The rig's grid parameter (internal units) at a grid value in hours: the transient's decay
    rate ``k_tr`` from its decay time, the step's onset ``t_step``."""
    tau = hours * 3600 * units.EARTH_RATE
    return 1.0 / tau if effect == "drift_transient" else tau


@eqx.filter_jit
def _screen_jacobians(rig, params, conditions, ts, free, vec_names, sizes):
    """Forward sensitivities of the noise-free channels, ``(n c, k)`` in internal units, to the
    scalar parameters ``free`` and then to every entry of the vector-valued ``vec_names`` (of
    lengths ``sizes``): the transient's amplitudes, one per decay rate of ``params["k_tr"]``, and
    the step's sizes, one per onset of ``params["t_step"]`` (the rig sums a transient or step
    per entry). At null amplitudes the grid values do not move the trajectory, so one primal
    solve (stopping at every onset) carries one tangent per column of every grid value."""
    edges = np.cumsum([len(free), *sizes])

    def fn(x):
        p = dict(params) | {n: params[n] + x[i] for i, n in enumerate(free)}
        p |= {n: params[n] + x[a:b] for n, a, b in zip(vec_names, edges[:-1], edges[1:])}
        return integrate(rig, p, conditions, ts, adjoint=diffrax.ForwardMode(),
                         throw=False).reshape(-1)

    x0 = jnp.zeros(int(edges[-1]))
    return jax.vmap(lambda v: jax.jvp(fn, (x0,), (v,))[1], out_axes=1)(jnp.eye(x0.size))


@eqx.filter_jit
def _predict(rig, params, conditions, ts):
    return integrate(rig, params, conditions, ts, throw=False)


@eqx.filter_jit
def _masked_fit(rig, p, conditions, ts, y, w, cols, free, mask, line_on, rho, taus):
    """Levenberg-Marquardt (:func:`~gyrojax.estimate.solve_least_squares`) on the whitened rows
    (per channel the flicker model's innovations at the variance ratio ``rho``, GM correlation
    times ``taus``, then the weights ``w``; ``rho`` 0: weighted least squares) over the rig
    parameters ``free`` (those with ``mask`` 0 held: their Jacobian columns are zero, so the
    damped step leaves them) and the linear output coefficients ``beta`` of ``cols`` (rad per
    unit; held at 0 unless ``line_on``). The mask and ``line_on`` are arrays: one compiled
    solver serves the nominal fit and every refit. Returns (parameters, ``beta``, the
    :class:`~gyrojax.estimate.LeastSquaresSolution`)."""
    scales = rig.param_space.scales(free)
    n, c = ts.shape[0], rho.shape[0]
    dts = jnp.concatenate([jnp.array([jnp.inf]), jnp.diff(ts)])
    one = jax.vmap(lambda xc, rc: innovations(xc, dts, rc, taus)[0], in_axes=(1, 0),
                   out_axes=1)

    flicker = jnp.any(rho > 0)  # else the filter is the identity: skip it (a third of a fit)

    def wh(x):  # (n c, m) time-major rows -> whitened, weighted
        x = jax.lax.cond(flicker, lambda x: one(x.reshape(n, c, -1), rho).reshape(n * c, -1),
                         lambda x: x, x)
        return x * w[:, None]

    ct = wh(cols) * line_on
    k = len(free)

    def params_at(x):
        return p | {name: p[name] + x[i] * scales[i] for i, name in enumerate(free)}

    def resid(z, _):
        model = integrate(rig, params_at(z[:k] * mask), conditions, ts, throw=False,
                          adjoint=diffrax.ForwardMode()).reshape(-1)
        return wh((y - model)[:, None])[:, 0] - ct @ z[k:]

    sol = solve_least_squares(resid, jnp.zeros(k + cols.shape[1]), max_steps=_MAX_ITER)
    return params_at(sol.value[:k] * mask), sol.value[k:] * line_on, sol


def _stack(jn, sigs):
    """The nominal columns, then each signature's grid slices side by side: ``(rows, k)``."""
    return np.concatenate([jn] + [np.concatenate(list(s.jac), axis=1) for s in sigs], axis=1)


class ESGProblem(AbstractGapProblem):
    """One ESG record split into train / held-out, with the rig pieces the diagnosis needs.

    **Options:** `order`: ``"exact"`` (model 5.1) or ``"first"`` (3.1); `noise_model`:
    ``"white"`` or ``"white+flicker"``; `flicker_b`: the flicker's B (rad, one or per channel;
    implies ``"white+flicker"``). The record's conditions must give ``scheme`` and
    ``latitude_deg``."""

    NOISE_UNITS = {"alpha": (units.ARCSEC, "arcsec")}
    OPTIONS = {"order": "'exact' (model 5.1) or 'first' (the paper's 3.1)",
               "noise_model": "'white' or 'white+flicker'",
               "flicker_b": "the flicker's bias-instability coefficient B (rad)"}

    @classmethod
    def catalogue(cls, **options) -> dict:
        """The catalogue: effect name -> family."""
        return {k: v[0] for k, v in ESG_LIBRARY.items()}

    def __init__(self, record: BenchRecord, *, holdout: float = 0.25, noise_std=None,
                 effects=None, order: str = "exact", noise_model: str | None = None,
                 flicker_b=None):
        c = record.conditions
        missing = [k for k in ("latitude_deg", "scheme") if k not in c]
        if missing:
            raise ValueError(f"record lacks the condition(s) {missing}; give --latitude DEG and "
                             "--scheme NAME (or store them as NetCDF attributes)")
        if order not in ("exact", "first"):
            raise ValueError(f"order={order!r}; use 'exact' (model 5.1) or 'first' (model 3.1)")
        check_effects(effects, ESG_LIBRARY, "esg")
        noise_model = noise_model or ("white+flicker" if flicker_b is not None else "white")
        if noise_model not in NOISE_MODELS:
            raise ValueError(f"noise_model={noise_model!r}; the ESG's noise models are "
                             f"{', '.join(NOISE_MODELS)}")
        if flicker_b is not None and (noise_model != "white+flicker"
                                      or not np.all(np.asarray(flicker_b) >= 0)):
            raise ValueError(f"flicker_b={flicker_b!r}: a flicker level (bias-instability "
                             "coefficient B, rad, >= 0, one or per channel) goes with "
                             "noise_model='white+flicker'")
        c = record.conditions
        self.scheme, self.latitude = str(c["scheme"]), float(c["latitude_deg"])
        self.conditions = ESGConditions.create(self.scheme, self.latitude)
        self.fit_rig = ESGRig.for_scheme(self.scheme, self.latitude, order=order)
        self.screen_rig = ESGRig(base_param="rotvec", order=order)
        self.record = record
        self.t = np.asarray(record.t, float)
        self.y = np.asarray(record.y, float)
        check_angle_units(self.y, self.t)
        self.channels = record.channels
        n = len(self.t)
        self.n_train = n - int(round(holdout * n)) if holdout > 0 else n
        self.noise_std = noise_std
        self.effects = tuple(effects) if effects is not None else tuple(ESG_LIBRARY)
        space = self.fit_rig.param_space
        self.nominal_names = space.nominal_names()
        self.nominal_scales = space.scales(self.nominal_names)
        self.nominal_units = tuple(space[k].display_unit for k in self.nominal_names)
        self.nominal_display_scales = self.nominal_scales / np.array(
            [space[k].display_factor for k in self.nominal_names])
        # the step's onset grid, one onset every 5 % of the train span
        # (docs/decisions/0018-grid-effects.md)
        self.step_grid_h = tuple(float(x) for x in onset_grid(self.t / 3600, self.n_train))
        self.lines = {"sidereal day": SIDEREAL_DAY, "half sidereal day": SIDEREAL_DAY / 2}
        self.notes: list[str] = []
        # white, or white + flicker at a given level B or (None) one estimated by REML
        self.noise_model = noise_model
        self.flicker_b = None if flicker_b is None else np.broadcast_to(
            np.asarray(flicker_b, float), (len(self.channels),)).copy()
        self.sample_s = float(np.median(np.diff(self.t)))
        self._rho = np.zeros(len(self.channels))
        self._noise_fit: dict = {"model": self.noise_model}

    # -- nominal fit -----------------------------------------------------------------------
    def train_record(self) -> BenchRecord:
        return self.record.slice(0, self.n_train)

    def fit_nominal(self) -> dict:
        """Nominal fit on the train split: the integral regression's drifts (window 2, Simpson, as
        :func:`gyrojax.estimate.fit` starts from), then Levenberg-Marquardt on the exact model with
        every effect at its null (the refits' compiled solver, the effects masked). Returns the
        screening rig's parameter dict."""
        rec = self.train_record()
        reg = integral_regression(self.fit_rig, rec, self.conditions, window=2,
                                  quadrature="simpson", names=self.fit_rig.drift_names)
        y0 = np.asarray(rec.y[0])
        p = self.screen_rig.param_space.make() | {"alpha10": jnp.asarray(y0[0]),
                                                  "alpha20": jnp.asarray(y0[1])} | reg.as_dict()
        # equal weights on the two angle channels, as fit() has (the scale sets the stop rule)
        p, *_ = self._fit(p, set(self.nominal_names),
                                     np.full(len(self.channels), units.ARCSEC), line_on=False,
                                     what="the nominal fit")
        if self.noise_model == "white+flicker":
            if self.flicker_b is None:
                self._fit_flicker(p)
            else:
                self._given_flicker(p)
            if np.any(self._rho > 0):  # the nominal fit again, on the flicker-whitened rows
                p, *_ = self._fit(p, set(self.nominal_names),
                                             np.full(len(self.channels), units.ARCSEC),
                                             line_on=False, what="the nominal fit (GLS)")
        return p

    def _fit_flicker(self, params):
        """Per channel, the flicker-to-white variance ratio by REML on the train residual of the
        nominal fit with the nominal and *every* catalogued effect's columns (every grid value)
        projected out, so a catalogued slow effect is not taken for flicker."""
        n, c = self.n_train, len(self.channels)
        jn, sigs = self._raw_jacobians(params, self.conditions, self.t)
        x = _stack(jn, sigs)[: n * c]
        resid = (self.y - self.predict(params))[:n]
        lr = np.zeros(c)
        for ch in range(c):
            self._rho[ch], lr[ch] = reml_rho(resid[:, ch], x[ch::c], self.t[:n], self.sample_s)
        sigma_w = first_difference_level(self._whiten_unit(resid, self.t[:n]))  # as noise_level
        self._noise_fit |= {
            "flicker_B_arcsec": [float(b) for b in rho_to_b(self._rho, sigma_w) / units.ARCSEC],
            "flicker_lr": [float(v) for v in lr], "flicker_source": "REML"}

    def _given_flicker(self, params):
        """The variance ratio of a given flicker level ``B``: against the given white level,
        or against the white part of the residual's first-difference level (the flicker's own
        share of it, ``s^2 sum_i (1 - phi_i)``, taken off)."""
        n = self.n_train
        s2 = (FLICKER_STD_PER_B * self.flicker_b) ** 2
        if self.noise_std is not None:
            white2 = np.broadcast_to(np.asarray(self.noise_std, float) ** 2, s2.shape)
        else:
            fd2 = first_difference_level((self.y - self.predict(params))[:n]) ** 2
            share = np.sum(1 - np.exp(-self.sample_s / flicker_taus(self.sample_s)))
            white2 = fd2 - s2 * share
            if np.any(white2 <= 0.05 * fd2):
                raise ValueError(
                    f"the given flicker B = {self.flicker_b / units.ARCSEC} arcsec accounts for "
                    "the residual's whole first-difference level "
                    f"{np.sqrt(fd2) / units.ARCSEC} arcsec: give a smaller B (from an Allan "
                    "deviation test of this instrument) or the white level too (noise_std)")
        self._rho = s2 / white2
        self._noise_fit |= {"flicker_B_arcsec": [float(b) for b in self.flicker_b / units.ARCSEC],
                           "flicker_source": "given"}

    def _whiten_unit(self, x, t):
        """Per channel, the flicker model's ``L^-1`` along time of ``x`` (``(N, c, ...)``): the
        innovations of the white + GM-sum covariance at the estimated ratio (identity where it
        is 0)."""
        out = np.array(x, float, copy=True)
        for ch, rho in enumerate(self._rho):
            if rho > 0:
                out[:, ch] = whiten(out[:, ch], t, rho, self.sample_s)
        return out

    def _weigh(self, jac, t, sigma):
        """Whitened rows of raw columns ``jac`` (``(N c, k)``, time-major rows)."""
        rows, k = jac.shape
        c = len(self.channels)
        x = self._whiten_unit(np.asarray(jac).reshape(rows // c, c, k), t)
        return (x / np.asarray(sigma)[None, :, None]).reshape(rows, k)

    @property
    def noise_fit(self) -> dict:
        return self._noise_fit

    def noise_level(self, resid):
        """White level per channel (after the flicker whitening, from first differences) and
        its source; a given ``noise_std`` is a white model."""
        n = len(resid)
        if self.noise_std is not None:
            s = np.broadcast_to(np.asarray(self.noise_std, float), (resid.shape[1],)).copy()
            dof, src = np.inf, "given"
        else:
            s = first_difference_level(self._whiten_unit(resid, self.t[:n]))
            dof, src = 2 * (n - 1) / 3, "estimated from first differences of the residual"
        if self.noise_model == "white+flicker":
            b = ", ".join(f"{x:.3g}" for x in self.noise_fit["flicker_B_arcsec"])
            how = ("given" if self.flicker_b is not None
                   else "by REML on the full-model residual")
            src += (f"; rows whitened by a white + flicker (GM sum) model, B = {b} arcsec "
                    f"{how}")
        return s, dof, src

    def verdict_notes(self, verdict) -> list[str]:
        """A gap the white model cannot place may be flicker it does not model: say so, and
        how to test it (measured: ``benchmarks/RESULTS.md``, ``gap_blind_nulls_flicker``)."""
        if self.noise_model != "white" or verdict["kind"] not in ("ambiguous", "partial", "unexplained"):
            return []
        return ["the nominal noise model is white: flicker on the gimbal angles reads as a slow "
                "gap (on 24 h records a flicker floor near the white noise's scatter over the "
                "record, ~0.03 arcsec for 1 arcsec per minute, already raises false alarms); "
                "if the instrument's Allan test shows a flicker floor, rerun with "
                "--flicker-arcsec B (Allan floor / 0.664)"]

    def standardize(self, resid, sigma):
        return self._whiten_unit(resid, self.t[: len(resid)]) / np.asarray(sigma)

    def predict(self, params: dict, extra=None) -> np.ndarray:
        """Model channels over the whole record (train + held-out) for a parameter dict of the
        screening rig (rotation-vector base misalignment)."""
        pred = np.asarray(_predict(self.screen_rig, params, self.conditions, jnp.asarray(self.t)))
        if extra is not None:
            pred = pred + extra
        return pred

    # -- Jacobians -------------------------------------------------------------------------
    def _screen_params(self, params):
        sp = self.screen_rig.param_space
        return sp.make() | {k: params[k] for k in self.nominal_names}

    def _all_free(self):
        sp = self.screen_rig.param_space
        free = list(self.nominal_names)
        for e in self.effects:
            if e in sp.effects:
                free += [n for n in sp.effect_names(e) if n not in _GRID_PARAM.values()]
        return tuple(n for n in sp.names if n in free)

    def jacobians(self, params, sigma, *, conditions=None, t=None):
        """Whitened Jacobians over ``t`` (default: the whole record): nominal (per Param.scale)
        and one :class:`Signature` per library effect (per prior scale, grid slices); the
        rows whitened by the noise model (flicker innovations, then the white level)."""
        cond = conditions if conditions is not None else self.conditions
        t = self.t if t is None else t
        jn, sigs = self._raw_jacobians(params, cond, t)
        # one whitening pass over every column (a fixed width per library: one compilation)
        x = self._weigh(_stack(jn, sigs), t, sigma)
        out, k = [], jn.shape[1]
        for sg in sigs:
            g, m, p = sg.jac.shape
            out.append(dataclasses.replace(
                sg, jac=np.moveaxis(x[:, k: k + g * p].reshape(m, g, p), 1, 0)))
            k += g * p
        return x[:, : jn.shape[1]], out

    def _raw_jacobians(self, params, cond, t):
        """:meth:`jacobians` before the noise model's whitening (rad per scale)."""
        sp = self.screen_rig.param_space
        free = self._all_free()
        p = self._screen_params(params)
        # the effect columns that depend on a grid value (decay time, onset): the rig's
        # transient amplitudes and step sizes as vectors, one entry per grid value; every
        # other column once (at null effects the grid values do not move the trajectory)
        grids = {"drift_transient": TRANSIENT_TIMES_H, "drift_step": self.step_grid_h}
        vec = {}  # grid-dependent name -> its effect's grid length
        for e, gname in _GRID_PARAM.items():
            if e in self.effects and e in sp.effects:
                values = [_grid_value(e, h) for h in grids[e]]
                p[gname] = jnp.asarray(values)
                for n in sp.effect_names(e):
                    if n != gname:
                        vec[n] = len(values)
                        p[n] = jnp.zeros(len(values))
        fi = tuple(n for n in free if n not in vec)
        vnames = tuple(n for n in free if n in vec)
        jac_all = np.asarray(_screen_jacobians(self.screen_rig, p, cond, jnp.asarray(t), fi,
                                               vnames, tuple(vec[n] for n in vnames)))
        col = {n: k for k, n in enumerate(fi)}
        j0 = jac_all[:, : len(fi)]
        start = dict(zip(vnames, len(fi) + np.cumsum([0] + [vec[n] for n in vnames[:-1]])))
        jn = j0[:, [col[n] for n in self.nominal_names]] * self.nominal_scales
        sigs = []
        for e in self.effects:
            fam, prior = ESG_LIBRARY[e]
            if e == "diurnal_line":
                sigs.append(self._line_signature(t, np.ones(len(self.channels)), prior))
                continue
            names = tuple(n for n in sp.effect_names(e) if n not in _GRID_PARAM.values())
            factor = np.array([sp[n].display_factor for n in names]) * prior
            if e in _GRID_EFFECTS:
                jac = np.stack([jac_all[:, [start[n] + g for n in names]]
                                for g in range(vec[names[0]])]) * factor
            else:
                jac = j0[None, :, [col[n] for n in names]] * factor
            grid, gname, gunit = (), "", ""
            if e == "drift_transient":
                grid, gname, gunit = TRANSIENT_TIMES_H, "decay time", "h"
            elif e == "drift_step":
                grid, gname, gunit = self.step_grid_h, "onset", "h"
            sigs.append(Signature(e, fam, names, tuple(sp[n].display_unit for n in names),
                                  np.full(len(names), prior), jac, grid, gname, gunit))
        return jn, sigs

    def _line_signature(self, t, sigma, prior):
        n, c = len(t), len(self.channels)
        w = 2 * np.pi / SIDEREAL_DAY
        cols = np.zeros((n, c, 2 * c))
        names = []
        for ch in range(c):
            cols[:, ch, 2 * ch] = np.sin(w * t) * prior * units.ARCSEC / sigma[ch]
            cols[:, ch, 2 * ch + 1] = np.cos(w * t) * prior * units.ARCSEC / sigma[ch]
            names += [f"{self.channels[ch]}_sin", f"{self.channels[ch]}_cos"]
        return Signature("diurnal_line", "line", tuple(names), ("arcsec",) * (2 * c),
                         np.full(2 * c, prior), cols.reshape(n * c, 2 * c)[None], kind="output")

    # -- refits ----------------------------------------------------------------------------
    def refit(self, params0: dict, sig_choices: list[tuple[Signature, int]], sigma):
        """Refit nominal + the chosen effects (grid values fixed at the screened best) on the
        train split; returns (full-record prediction, fitted effect coefficients in display
        units, fitted parameters).

        Every refit (and the nominal fit) is one Levenberg-Marquardt fit on the exact model over the same
        superset of parameters (the nominal, every library rig effect in the screening's
        parametrisation, the diurnal-line output columns), those not chosen masked to zero
        columns: one compiled solver serves every candidate set. The screening's
        parametrisation is the one to refit in: a base misalignment as the rotation vector
        ``dchi1..3`` (the ``eps`` form has no component along ``u``, which the g-sensitive drifts
        make weakly visible, so its refit could not reproduce what the screening tested). Output
        effects (lines) are linear and join the rig parameters in the same fit
        (alternating the two fits converges slowly when a line is nearly a nominal signature, as
        the sidereal line is). The minimum-norm step leaves a direction the record cannot see
        (``dchi || u`` in the first-order model) at its start.
        """
        sp = self.screen_rig.param_space
        p = self._screen_params(params0)
        chosen = set(self.nominal_names)
        line_on = False
        for sig, g in sig_choices:
            if sig.kind == "output":
                line_on = True
                continue
            chosen |= {n for n in sp.effect_names(sig.name) if n not in _GRID_PARAM.values()}
            if sig.name in _GRID_PARAM:
                p[_GRID_PARAM[sig.name]] = jnp.asarray(_grid_value(sig.name, sig.grid[g]))
        p, beta, cols, _ = self._fit(p, chosen, sigma, line_on=line_on,
                                           what=f"the refit with {[s.name for s, _ in sig_choices]}")
        extra = (cols @ beta).reshape(self.y.shape) if line_on else None
        coeffs = {}
        for sig, _ in sig_choices:
            if sig.kind == "output":
                for k, name in enumerate(sig.names):
                    coeffs[name] = float(beta[k])
            else:
                for name in sig.names:
                    coeffs[name] = float(sp[name].to_display(p[name])) if name in sp else None
        return self.predict(p, extra), coeffs, p

    def _fit(self, p, chosen: set, sigma, *, line_on: bool, what: str):
        """:func:`_masked_fit` on the train rows over the parameters ``chosen`` (the
        others of the superset held at their values in ``p``) and, with ``line_on``, the diurnal
        line; returns (parameters, line coefficients, the line's full-record columns in rad per
        display unit, the :class:`~gyrojax.estimate.LeastSquaresSolution` in the fitted
        coordinates: the superset's parameters per scale, then the line's). A fit that does not
        converge is noted in :attr:`notes`."""
        free = self._all_free()
        unknown = chosen - set(free)
        if unknown:
            raise ValueError(f"{what}: parameters {sorted(unknown)} are not in this problem's "
                             f"library {self.effects}; pass effects= that include them")
        n, c = self.n_train, len(self.channels)
        sig_arr = np.asarray(sigma, float)
        full = self._line_signature(self.t, sig_arr, ESG_LIBRARY["diurnal_line"][1])
        cols = (full.jac[0] / np.asarray(full.prior_scale)[None, :]
                * np.tile(sig_arr, len(self.t))[:, None])
        mask = np.array([k in chosen for k in free], float)
        p = {k: jnp.asarray(v, dtype=float) for k, v in p.items()}  # traced, never static
        p, beta, sol = _masked_fit(
            self.screen_rig, p, self.conditions, jnp.asarray(self.t[:n]),
            jnp.asarray(self.y[:n].reshape(-1)), jnp.asarray(np.tile(1.0 / sig_arr, n)),
            jnp.asarray(cols[: n * c]), free, jnp.asarray(mask), jnp.asarray(float(line_on)),
            jnp.asarray(self._rho), jnp.asarray(flicker_taus(self.sample_s)))
        note = convergence_note(sol, what)
        if note is not None:
            self.notes.append(note)
        return dict(p), np.asarray(beta), cols, sol

    # -- designs for the advisor -----------------------------------------------------------
    def designs(self):
        """Candidate test designs: the other mounting schemes; the record doubled (and, for a
        record shorter than a day, four times as long); each other scheme with each longer
        record."""
        dt = (self.t[-1] - self.t[0]) / (len(self.t) - 1)
        hours = (self.t[-1] - self.t[0]) / 3600
        other = [(s, ESGConditions.create(s, self.latitude)) for s in SCHEMES
                 if s != self.scheme]
        out = [(f"{s} scheme", c, self.t) for s, c in other]
        for k in (2, 4) if hours < 23.5 else (2,):
            long_t = self.t[0] + dt * np.arange(k * (len(self.t) - 1) + 1)
            long = f"{k * hours:.0f} h record"
            out += [(long, self.conditions, long_t)]
            out += [(f"{s} scheme, {long}", c, long_t) for s, c in other]
        return out

    def display_nominal(self, params) -> dict:
        sp = self.fit_rig.param_space
        return {k: float(sp[k].to_display(params[k])) for k in self.nominal_names}
