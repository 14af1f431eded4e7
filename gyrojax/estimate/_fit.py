"""``fit``: one verb for every estimator, returning a report in named parameters and units."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from .. import units
from ..models.esg import check_angle_units
from ..record import sample_noise
from ..simulate import integrate
from .kalman import esg_augmented_filter
from .least_squares import fit_trajectory
from .regression import integral_regression

__all__ = ["fit", "FitReport", "METHODS"]

METHODS = ("regression", "gauss-newton", "levenberg-marquardt", "kalman")


@dataclasses.dataclass(frozen=True)
class FitReport:
    """A fit in named parameters: ``params`` (full dict, internal units), ``stderr`` (free ones),
    ``residual_rms`` (output residual of the exact model at the estimate, rad), ``converged``."""

    method: str
    free: tuple[str, ...]
    params: dict
    stderr: dict
    residual_rms: float
    converged: bool
    space: object = dataclasses.field(repr=False)
    extra: dict = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        out = {}
        for n in self.free:
            p = self.space[n]
            se = self.stderr.get(n)
            out[n] = {"value": float(p.to_display(self.params[n])),
                      "stderr": None if se is None else float(p.to_display(se)),
                      "unit": p.display_unit}
        return {"method": self.method, "parameters": out,
                "residual_rms": float(self.residual_rms), "residual_rms_unit": "rad",
                "residual_rms_arcsec": float(np.degrees(self.residual_rms) * 3600),
                "converged": bool(self.converged)} | self.extra

    def table(self) -> str:
        return self.space.table(self.params, self.stderr, names=list(self.free))


def _linear_names(rig, effects):
    names = list(rig.drift_names)
    for e in effects:
        if e == "rotor_tilt":
            names += ["theta1", "theta2"]
        elif e == "base_misalignment":
            names += list(rig.base_names)
    return tuple(names)


def _check_record(rig, record):
    """The record a fit is given: the rig's channels, in its order (the fits read the columns by
    position), and samples as a record file must have them (:func:`gyrojax.io.validate_samples`:
    finite, strictly increasing times, at least 3), with gimbal angles in radians
    (:func:`gyrojax.models.esg.check_angle_units`). A record built in memory skipped those
    checks, and a NaN sample made every estimate NaN without a word."""
    from ..io import validate_samples

    if tuple(record.channels) != tuple(rig.channels):
        raise ValueError(f"record channels {list(record.channels)} are not the rig's "
                         f"{list(rig.channels)}; name (and order) the record's channels as the "
                         "rig's")
    validate_samples(record.t, record.y, record.channels)
    check_angle_units(record.y, record.t)


def fit(rig, record, conditions, *, effects: Sequence[str] = (), method: str = "gauss-newton",
        noise_std: float | None = None, transient_k: float = 3.0, window: int = 2,
        quadrature: str = "simpson") -> FitReport:
    """Identify the rig's nominal parameters plus those of ``effects`` from a record.

    **Arguments:**
    - `effects`: effect groups to free (e.g. ``("rotor_tilt", "base_misalignment")``); the others
      stay at their null values.
    - `method`: ``"regression"`` (integral equations, linear model), ``"gauss-newton"`` or
      ``"levenberg-marquardt"`` (exact model, started from the regression), ``"kalman"``
      (augmented-state square-root filter; with ``drift_transient`` it carries transient states
      with decay rate ``transient_k`` per unit tau).
    - `noise_std`: the angle noise (rad), when it is known (e.g. from the pick-off's own test).
      ``"kalman"``: the filter's measurement noise (default: estimated from the regression).
      ``"gauss-newton"`` / ``"levenberg-marquardt"``: the standard errors are taken at this noise,
      ``noise_std * sqrt(diag((J^T J)^-1))``, instead of at the residual's estimate
      ``sqrt(SSR / dof)`` (both are reported in ``extra``). ``"regression"`` estimates its own noise
      from the block residuals and refuses a given one.
    """
    space = rig.param_space
    if method not in METHODS:
        raise ValueError(f"method={method!r}; use one of {', '.join(METHODS)}")
    _check_record(rig, record)
    for e in effects:
        space.effect_names(e)  # raises with the list of valid effects
    effects = tuple(effects)
    lin = _linear_names(rig, effects)
    if method == "regression" and "drift_transient" in effects:
        raise ValueError("effect 'drift_transient' is nonlinear in time and cannot be fitted by "
                         "--method regression; use --method kalman or gauss-newton")
    other = [e for e in effects if e not in ("rotor_tilt", "base_misalignment", "drift_transient")]
    if other and method in ("regression", "kalman"):
        raise ValueError(f"effect(s) {other} are fitted by --method gauss-newton or "
                         f"levenberg-marquardt only, not by --method {method}")
    if noise_std is not None:
        if method == "regression":
            raise ValueError("noise_std is not used by method='regression' (it estimates the noise "
                             "from its block residuals); drop it, or use method='gauss-newton' for "
                             "standard errors at a known noise, or 'kalman'")
        if not np.isfinite(noise_std) or noise_std <= 0:
            raise ValueError(f"noise_std={noise_std}: give the angle noise as a positive number "
                             "(rad; --noise-arcsec in arcsec), or leave it out to estimate it")
    reg = integral_regression(rig, record, conditions, window=window, quadrature=quadrature,
                              names=lin)
    y0 = record.y[0]
    p = space.make() | {"alpha10": y0[0], "alpha20": y0[1]} | reg.as_dict()
    stderr = reg.stderr_dict()
    free = lin
    converged = True
    extra = {}
    if method in ("gauss-newton", "levenberg-marquardt"):
        # the step onset is a grid parameter (zero derivative almost everywhere): held at its value
        free = space.free_names(effects, exclude=("t_step",) if "drift_step" in effects else ())
        if "drift_transient" in effects:
            p = p | {"k_tr": jnp.asarray(transient_k, float)}
        res = fit_trajectory(rig, record, conditions, p, free=free, method=method, throw=False)
        p, stderr = res.params, res.stderr_dict()
        extra["residual_noise_arcsec"] = float(np.degrees(res.noise_std) * 3600)
        if noise_std is not None:  # standard errors at the known noise, not at the residual's
            stderr = {k: v * (noise_std / res.noise_std) for k, v in stderr.items()}
            extra["noise_std_arcsec"] = float(np.degrees(noise_std) * 3600)
        converged = bool(res.converged)
        extra["num_steps"] = int(res.num_steps)
        extra["remaining_step_se"] = float(res.remaining_step_se)
    elif method == "kalman":
        sigma = noise_std if noise_std is not None else _noise_from_regression(reg)
        k = transient_k if "drift_transient" in effects else None
        kf = esg_augmented_filter(rig, record, conditions, noise_std=sigma, names=lin,
                                  transient_k=k)
        p = p | kf.as_dict() | {"alpha10": kf.smoothed_x[0, 0], "alpha20": kf.smoothed_x[0, 1]}
        if k is not None:
            p = p | {"k_tr": jnp.asarray(k, float)}
        stderr = kf.stderr_dict()
        free = kf.names
        innov = np.asarray(kf.filter.innovations[10:])
        extra["innovation_std"] = [float(x) for x in innov.std(axis=0)]
        extra["noise_std_arcsec"] = float(np.degrees(sigma) * 3600)
    pred = integrate(rig, p, conditions, record.t, throw=False)
    rms = float(jnp.sqrt(jnp.mean((pred - record.y) ** 2)))
    # the record's sample-to-sample noise (both channels), for the residual to be read against
    extra["sample_noise_arcsec"] = float(np.sqrt(np.mean(sample_noise(record.y) ** 2)) / units.ARCSEC)
    return FitReport(method, tuple(free), p, stderr, rms, converged, space, extra)


def _noise_from_regression(reg):
    """Angle noise estimate from the block residuals: each block increment of the measured angles
    carries the noise of its two end samples, 2 sigma^2 (model error inflates it)."""
    return float(reg.residual_rms) / np.sqrt(2.0)
