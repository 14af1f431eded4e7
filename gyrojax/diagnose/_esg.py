"""The non-contact gyro rig as the diagnosis sees it: nominal fit, Jacobians, refits, designs.

Screening uses the rig with the base misalignment as a rotation vector ``dchi1..3`` (so the
structural null direction ``dchi || u`` shows as "no signature"); fits and refits use the rig's
default ``eps``-normal-to-``u`` form, which has no null direction. The two agree exactly at null
effects, so their nominal Jacobians are the same.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .. import units
from ..estimate._fit import fit
from ..estimate.least_squares import fit_trajectory, trajectory_jacobian
from ..models.esg import SCHEMES, ESGConditions, ESGRig
from ..record import BenchRecord
from ..simulate import integrate
from ._stats import Signature

__all__ = ["ESGProblem", "ESG_LIBRARY", "SIDEREAL_DAY"]

SIDEREAL_DAY = 2 * np.pi / units.EARTH_RATE  # s
# effect -> (family, prior scale per coefficient in display units, grid)
ESG_LIBRARY = {
    "rotor_tilt": ("mounting", 600.0),  # arcsec (10 arcmin, seed 000)
    "base_misalignment": ("mounting", 60.0),  # arcsec (1 arcmin)
    "drift_transient": ("transient", 0.3),  # deg/h (m0 - m*), decay time on a grid
    "drift_ramp": ("trend", 0.002),  # deg/h per h
    "drift_step": ("step", 0.05),  # deg/h, onset on a grid
    "diurnal_line": ("line", 5.0),  # arcsec on each gimbal angle (pier tilt, HVAC)
}
TRANSIENT_TIMES_H = tuple(float(x) for x in np.geomspace(0.25, 3.0, 8))
_GRID_EFFECTS = ("drift_transient", "drift_step")


@eqx.filter_jit
def _jacobian(rig, params, conditions, ts, free):
    return trajectory_jacobian(rig, params, conditions, ts, free)


@eqx.filter_jit
def _predict(rig, params, conditions, ts):
    return integrate(rig, params, conditions, ts, throw=False)


class ESGProblem:
    """One ESG record split into train / held-out, with the rig pieces the diagnosis needs."""

    rig_name = "esg"

    def __init__(self, record: BenchRecord, *, holdout: float = 0.25, noise_std=None,
                 effects=None, order: str = "exact"):
        c = record.conditions
        self.scheme, self.latitude = str(c["scheme"]), float(c["latitude_deg"])
        self.conditions = ESGConditions.from_scheme(self.scheme, self.latitude)
        self.fit_rig = ESGRig.for_scheme(self.scheme, self.latitude, order=order)
        self.screen_rig = ESGRig(base_param="rotvec", order=order)
        self.record = record
        self.t = np.asarray(record.t, float)
        self.y = np.asarray(record.y, float)
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
        self.step_grid_h = tuple(float(x) for x in
                                 self.t[0] / 3600 + (self.t[self.n_train - 1] - self.t[0]) / 3600
                                 * np.arange(1, 9) / 9)
        self.lines = {"sidereal day": SIDEREAL_DAY, "half sidereal day": SIDEREAL_DAY / 2}

    # -- nominal fit -----------------------------------------------------------------------
    def train_record(self) -> BenchRecord:
        return self.record.slice(0, self.n_train)

    def fit_nominal(self) -> dict:
        rep = fit(self.fit_rig, self.train_record(), self.conditions, method="gauss-newton")
        return dict(rep.params)

    def predict(self, params: dict, extra=None, rig=None) -> np.ndarray:
        """Model channels over the whole record (train + held-out) for a param dict of ``rig``
        (default: the fit rig)."""
        pred = np.asarray(_predict(rig or self.fit_rig, params, self.conditions,
                                   jnp.asarray(self.t)))
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
                free += [n for n in sp.effect_names(e) if n not in ("k_tr", "t_step")]
        return tuple(n for n in sp.names if n in free)

    def jacobians(self, params, sigma, *, conditions=None, t=None):
        """Whitened Jacobians over ``t`` (default: the whole record): nominal (per Param.scale)
        and one :class:`Signature` per library effect (per prior scale, grid slices)."""
        cond = conditions if conditions is not None else self.conditions
        t = self.t if t is None else t
        sp = self.screen_rig.param_space
        free = self._all_free()
        p = self._screen_params(params)
        w = np.tile(1.0 / np.asarray(sigma), len(t))[:, None]
        grid_n = len(TRANSIENT_TIMES_H)
        jacs = []
        for g in range(grid_n if any(e in _GRID_EFFECTS for e in self.effects) else 1):
            pg = p | {"k_tr": jnp.asarray(1.0 / (TRANSIENT_TIMES_H[g] * 3600 * units.EARTH_RATE)),
                      "t_step": jnp.asarray(self.step_grid_h[g] * 3600 * units.EARTH_RATE)}
            j = np.asarray(_jacobian(self.screen_rig, pg, cond, jnp.asarray(t), free))
            jacs.append(j * w)
        col = {n: i for i, n in enumerate(free)}
        jn = jacs[0][:, [col[n] for n in self.nominal_names]] * self.nominal_scales
        sigs = []
        for e in self.effects:
            fam, prior = ESG_LIBRARY[e]
            if e == "diurnal_line":
                sigs.append(self._line_signature(t, sigma, prior))
                continue
            names = tuple(n for n in sp.effect_names(e) if n not in ("k_tr", "t_step"))
            idx = [col[n] for n in names]
            factor = np.array([sp[n].display_factor for n in names]) * prior
            slices = jacs if e in _GRID_EFFECTS else jacs[:1]
            jac = np.stack([jg[:, idx] * factor for jg in slices])
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

        Rig effects are refitted by Gauss-Newton (LM as fallback) on the exact model, in the
        screening's parametrisation: a base misalignment as the rotation vector ``dchi1..3`` (the
        ``eps`` form has no component along ``u``, which the g-sensitive drifts make weakly
        visible, so its refit could not reproduce what the screening tested). Output effects
        (lines) are linear: they join the rig parameters in a joint Gauss-Newton on the train
        rows (alternating the two fits converges slowly when a line is nearly a nominal
        signature, as the sidereal line is).
        """
        rig = (self.screen_rig if any(sig.name == "base_misalignment" for sig, _ in sig_choices)
               else self.fit_rig)
        sp = rig.param_space
        p = self._screen_params(params0) if rig is self.screen_rig else dict(params0)
        free = list(self.nominal_names)
        out_cols = []
        for sig, g in sig_choices:
            if sig.kind == "output":  # full-record columns (the screened ones are train-only)
                full = self._line_signature(self.t, sigma, ESG_LIBRARY[sig.name][1])
                out_cols.append(full.jac[0] / np.asarray(full.prior_scale)[None, :])
                continue
            free += [n for n in sp.effect_names(sig.name) if n not in ("k_tr", "t_step")]
            if sig.name == "drift_transient":
                p["k_tr"] = jnp.asarray(1.0 / (sig.grid[g] * 3600 * units.EARTH_RATE))
            if sig.name == "drift_step":
                p["t_step"] = jnp.asarray(sig.grid[g] * 3600 * units.EARTH_RATE)
        free = tuple(n for n in sp.names if n in free)
        n = self.n_train
        rec = BenchRecord(jnp.asarray(self.t[:n]), jnp.asarray(self.y[:n]), self.channels,
                          self.record.attrs)
        # Gauss-Newton first: optimistix's LM can stop at the start when the effect's
        # coefficients begin at zero on a flat ridge; LM only when GN fails
        res = fit_trajectory(rig, rec, self.conditions, p, free=free, method="gauss-newton",
                             throw=False, max_steps=100)
        if not bool(res.converged):
            res = fit_trajectory(rig, rec, self.conditions, p, free=free,
                                 method="levenberg-marquardt", throw=False, max_steps=200)
        p = dict(res.params)
        beta_out = np.zeros(0)
        extra = None
        if out_cols or rig is self.screen_rig:
            # lines, and the rotation vector (whose component along u may be barely visible:
            # optimistix's GN then fails and its LM stops at the start) finish with a
            # least-squares Gauss-Newton
            w = np.tile(1.0 / np.asarray(sigma), n)
            cols = (np.concatenate(out_cols, axis=1) * np.tile(np.asarray(sigma), len(self.t))[
                :, None] if out_cols else np.zeros((self.y.size, 0)))  # rad per display unit
            p, beta_out = self._joint_gauss_newton(rig, p, free, cols, w)
            extra = (cols @ beta_out).reshape(self.y.shape) if out_cols else None
        coeffs = {}
        for sig, _ in sig_choices:
            if sig.kind == "output":
                for k, name in enumerate(sig.names):
                    coeffs[name] = float(beta_out[k])
            else:
                for name in sig.names:
                    coeffs[name] = float(sp[name].to_display(p[name])) if name in sp else None
        return self.predict(p, extra, rig=rig), coeffs, p

    def _joint_gauss_newton(self, rig, p, free, cols, w, max_iter: int = 8):
        """Gauss-Newton on the train rows over the rig parameters ``free`` and the linear output
        coefficients (columns ``cols``, rad per unit) together; ``w``: row whitening."""
        n, c = self.n_train, len(self.channels)
        scales = rig.param_space.scales(free)
        ct = cols[: n * c] * w[:, None]
        beta = np.zeros(cols.shape[1])
        ts = jnp.asarray(self.t[:n])
        for _ in range(max_iter):
            model = np.asarray(_predict(rig, p, self.conditions, ts)).reshape(-1)
            r = (self.y[:n].reshape(-1) - model) * w - ct @ beta
            jac = np.asarray(_jacobian(rig, p, self.conditions, ts, free)) * scales * w[:, None]
            a = np.concatenate([jac, ct], axis=1)
            step, *_ = np.linalg.lstsq(a, r, rcond=None)
            p = p | {k: p[k] + step[i] * scales[i] for i, k in enumerate(free)}
            beta = beta + step[len(free):]
            if np.sum((a @ step) ** 2) <= 1e-10 * max(float(r @ r), 1.0):
                break
        return p, beta

    # -- designs for the advisor -----------------------------------------------------------
    def designs(self):
        """Candidate test designs: the other mounting schemes, and the record doubled."""
        out = []
        for s in SCHEMES:
            if s != self.scheme:
                out.append((f"{s} scheme", ESGConditions.from_scheme(s, self.latitude), self.t))
        dt = (self.t[-1] - self.t[0]) / (len(self.t) - 1)
        out.append((f"{2 * (self.t[-1] - self.t[0]) / 3600:.0f} h record", self.conditions,
                    self.t[0] + dt * np.arange(2 * len(self.t) - 1)))
        return out

    def display_nominal(self, params) -> dict:
        sp = self.fit_rig.param_space
        return {k: float(sp[k].to_display(params[k])) for k in self.nominal_names}
