"""Mounting-error studies of the ESG rig: the paper's Tables 2-3 and a Monte Carlo error budget.

Table 2 (docs/rigs/esg.md): maximum angle error over a 24 h run caused by a base misalignment
``dchi = 1'`` on every axis or a rotor tilt ``theta = 10'`` on both axes, against the error-free run.
Table 3: maximum drift-identification error (deg/h) when only the six drift coefficients are
regressed on data that contain those mounting errors. Reconstruction of the unstated conditions
(docs/rigs/esg.md): all drifts 0.01, latitude 55.75 deg, Euler-increment ``dchi``, 1-min samples, window 1,
trapezoid rule.

The Monte Carlo budget draws random mounting errors for each scheme and reports the drift
identification error with and without the mounting errors estimated jointly.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

from .. import units
from ..estimate._linalg import scaled_lstsq
from ..estimate.regression import integral_regression, regression_design
from ..models.esg import DRIFT_NAMES, SCHEMES, ESGConditions, ESGRig
from ..record import BenchRecord
from ..simulate import gaussian_noise, grid_steps, integrate
from .montecarlo import monte_carlo, staged

__all__ = ["mounting_error_tables", "mounting_error_budget", "mounting_budget_stats",
           "MountingTables", "MountingBudget", "MountingBudgetStats", "PAPER_TABLE2",
           "PAPER_TABLE3"]

PAPER_TABLE2 = {"polar": (200, 1500), "equatorial": (125, 45), "horizontal": (291, 1000),
                "vertical": (120, 1700)}
"""Paper's Table 2, arcsec: (dchi ~ 1', theta ~ 10')."""
PAPER_TABLE3 = {"polar": (0.0069, 0.044), "equatorial": (0.0079, 0.0014),
                "horizontal": (0.014, 0.14), "vertical": (0.004, 0.046)}
"""Paper's Table 3, deg/h: (dchi ~ 1', theta ~ 10')."""


def _stack_conditions(schemes, latitude_deg):
    conds = [ESGConditions.create(s, latitude_deg) for s in schemes]
    return jax.tree.map(lambda *x: jnp.stack(x), *conds)


@dataclasses.dataclass(frozen=True)
class MountingTables:
    """Tables 2 and 3 per scheme: ``angle_arcsec[scheme] = (dchi case, theta case)``,
    ``drift_deg_h[scheme]`` likewise, ``worst[scheme]`` the worst drift parameter per case."""

    schemes: tuple[str, ...]
    angle_arcsec: dict
    drift_deg_h: dict
    worst: dict

    def markdown(self) -> str:
        rows = ["| scheme | T2 dchi~1' (\") | paper | T2 theta~10' (\") | paper | "
                "T3 dchi (deg/h) | paper | worst | T3 theta (deg/h) | paper | worst |",
                "|---|---|---|---|---|---|---|---|---|---|---|"]
        for s in self.schemes:
            a, d, w = self.angle_arcsec[s], self.drift_deg_h[s], self.worst[s]
            pa, pd = PAPER_TABLE2[s], PAPER_TABLE3[s]
            rows.append(f"| {s} | {a[0]:.0f} | {pa[0]} | {a[1]:.0f} | {pa[1]} | {d[0]:.4f} | "
                        f"{pd[0]} | {w[0]} | {d[1]:.4f} | {pd[1]} | {w[1]} |")
        return "\n".join(rows)

    def to_json(self) -> dict:
        return {s: {"table2_arcsec": {"dchi": self.angle_arcsec[s][0],
                                      "theta": self.angle_arcsec[s][1]},
                    "table3_deg_per_h": {"dchi": self.drift_deg_h[s][0],
                                         "theta": self.drift_deg_h[s][1]},
                    "worst_parameter": {"dchi": self.worst[s][0], "theta": self.worst[s][1]},
                    "paper_table2_arcsec": PAPER_TABLE2[s], "paper_table3_deg_per_h": PAPER_TABLE3[s]}
                for s in self.schemes}


def mounting_error_tables(latitude_deg: float = 55.75, *, schemes=SCHEMES, drift: float = 0.01,
                          dchi_arcmin: float = 1.0, theta_arcmin: float = 10.0,
                          dchi_mode: str = "euler", hours: float = 24.0,
                          sample_s: float = 60.0) -> MountingTables:
    """Reproduce Tables 2 and 3 (all schemes and error cases in one vmapped batch)."""
    schemes = tuple(schemes)
    rig = ESGRig(base_param=dchi_mode)
    space = rig.param_space
    ts = jnp.arange(0.0, hours * 3600.0 + 0.5 * sample_s, sample_s)
    base = space.make({n: drift for n in DRIFT_NAMES})
    dchi = dchi_arcmin * units.ARCMIN
    theta = theta_arcmin * units.ARCMIN
    cases = [base, base | {n: jnp.asarray(dchi) for n in rig.base_names},
             base | {"theta1": jnp.asarray(theta), "theta2": jnp.asarray(theta)}]
    conds = _stack_conditions(schemes, latitude_deg)
    ns, nc = len(schemes), len(cases)
    params = jax.tree.map(lambda *x: jnp.tile(jnp.stack(x), ns), *cases)
    cond_b = jax.tree.map(lambda x: jnp.repeat(x, nc, axis=0), conds)

    def simulate(draw):
        p, c = draw
        return integrate(rig, p, c, ts)

    def identify(draw, y):
        rec = BenchRecord(ts, y, rig.channels)
        return y, integral_regression(rig, rec, draw[1], names=DRIFT_NAMES).values

    # one device: batched LAPACK on several CPU devices can deadlock jaxlib 0.10.2 (notes)
    ys, est = monte_carlo(staged(simulate, identify), (params, cond_b), chunk_size=ns * nc,
                          devices=jax.devices()[:1], vectorized=True)
    ys = ys.reshape(ns, nc, *ys.shape[1:])
    est = est.reshape(ns, nc, -1)
    angle, drift_err, worst = {}, {}, {}
    for i, s in enumerate(schemes):
        da = [np.max(np.abs(ys[i, j] - ys[i, 0])) / units.ARCSEC for j in (1, 2)]
        de = [np.abs(est[i, j] - drift) * units.EARTH_RATE_DEG_PER_HOUR for j in (1, 2)]
        angle[s] = tuple(float(x) for x in da)
        drift_err[s] = tuple(float(np.max(x)) for x in de)
        worst[s] = tuple(DRIFT_NAMES[int(np.argmax(x))] for x in de)
    return MountingTables(schemes, angle, drift_err, worst)


@dataclasses.dataclass(frozen=True)
class MountingBudget:
    """Monte Carlo drift-identification errors (deg/h) per scheme and draw.

    ``drift_only[s]`` (N, 6): error of the six drifts when mounting errors are ignored;
    ``joint[s]`` (N, 6): when theta and dchi are estimated with them.
    """

    schemes: tuple[str, ...]
    drift_only: dict
    joint: dict
    n_draws: int

    def rms(self, which="drift_only") -> dict:
        d = getattr(self, which)
        return {s: np.sqrt(np.mean(d[s] ** 2, axis=0)) for s in self.schemes}

    def rms_se(self, which="drift_only") -> dict:
        """Standard error of :meth:`rms` (delta method on the mean of the squares)."""
        d, r = getattr(self, which), self.rms(which)
        return {s: np.std(d[s] ** 2, axis=0, ddof=1) / np.sqrt(len(d[s])) / (2 * r[s])
                for s in self.schemes}

    def markdown(self) -> str:
        rows = ["| scheme | fit | " + " | ".join(DRIFT_NAMES) + " |",
                "|---|---|" + "---|" * len(DRIFT_NAMES)]
        for which, label in (("drift_only", "drift only"), ("joint", "drift + mounting")):
            r = self.rms(which)
            for s in self.schemes:
                rows.append(f"| {s} | {label} | " + " | ".join(f"{x:.2e}" for x in r[s]) + " |")
        return "\n".join(rows)

    def to_json(self) -> dict:
        return {"n_draws": self.n_draws, "unit": "deg/h", "statistic": "RMS over draws",
                "drift_only": {s: dict(zip(DRIFT_NAMES, map(float, v)))
                               for s, v in self.rms("drift_only").items()},
                "joint": {s: dict(zip(DRIFT_NAMES, map(float, v)))
                          for s, v in self.rms("joint").items()}}


class _BudgetTrial:
    """The budget's trial pieces, shared by :func:`mounting_error_budget` (draws up front) and
    :func:`mounting_budget_stats` (draws from keys, reduced to statistics)."""

    def __init__(self, latitude_deg, schemes, drift, noise_arcsec, hours, sample_s, alpha20_deg):
        self.schemes = tuple(schemes)
        self.rig = ESGRig(base_param="rotvec")
        self.ts = jnp.arange(0.0, hours * 3600.0 + 0.5 * sample_s, sample_s)
        self.drift = drift
        self.base = self.rig.param_space.make({n: drift for n in DRIFT_NAMES},
                                              alpha20=alpha20_deg * units.DEG)
        self.conds = _stack_conditions(self.schemes, latitude_deg)
        self.joint_names = self.rig.regression_names
        self.masks = jnp.stack([jnp.array([n in DRIFT_NAMES for n in self.joint_names]),
                                jnp.ones(len(self.joint_names), bool)])
        self.noise = noise_arcsec * units.ARCSEC
        # one fixed step grid for every draw (each step's error is still checked against the
        # tolerance): about 3x faster than adaptive steps in a batch
        counts = [grid_steps(self.rig, self.base, jax.tree.map(lambda x: x[i], self.conds),
                             self.ts) for i in range(len(self.schemes))]
        self.steps = None if None in counts else max(counts)

    def simulate(self, i, dchi, theta):
        c = jax.tree.map(lambda x: x[i], self.conds)
        p = self.base | {"theta1": theta[0], "theta2": theta[1], "dchi1": dchi[0],
                         "dchi2": dchi[1], "dchi3": dchi[2]}
        return integrate(self.rig, p, c, self.ts, steps=self.steps)

    def identify(self, i, y, noise_key):
        """Drift errors (deg/h) of the drift-only and the joint fit, each ``(6,)``."""
        # noise in the regression's sub-batch, where the record is in cache (see `staged`);
        # noise-free budgets draw no deviates
        if self.noise != 0.0:
            y = y + gaussian_noise(noise_key, y.shape, self.noise)
        c = jax.tree.map(lambda x: x[i], self.conds)
        rec = BenchRecord(self.ts, y, self.rig.channels)
        a, b, _ = regression_design(self.rig, rec, c, names=self.joint_names)
        # both fits from one design in one batched solve: two independent LAPACK solves after a
        # while_loop in one graph can deadlock jaxlib 0.10.2's CPU runtime
        # (docs/decisions/0007-monte-carlo-worker-processes.md)
        est = jax.vmap(lambda m: scaled_lstsq(a * m, b)[0][:6])(self.masks)
        err = (est - self.drift) * units.EARTH_RATE_DEG_PER_HOUR
        return err[0], err[1]


def _check_budget(n_draws, dchi_std_arcmin, theta_std_arcmin, noise_arcsec):
    if n_draws < 1:
        raise ValueError(f"n_draws={n_draws}: need at least one Monte Carlo draw")
    for name, v in (("dchi_std_arcmin", dchi_std_arcmin), ("theta_std_arcmin", theta_std_arcmin),
                    ("noise_arcsec", noise_arcsec)):
        if not np.isfinite(v) or v < 0:
            raise ValueError(f"{name}={v}: a standard deviation must be finite and >= 0")


def mounting_error_budget(key: PRNGKeyArray, n_draws: int, latitude_deg: float = 55.75, *,
                          schemes=SCHEMES, drift: float = 0.01, dchi_std_arcmin: float = 1.0,
                          theta_std_arcmin: float = 10.0, noise_arcsec: float = 0.0,
                          hours: float = 24.0, sample_s: float = 60.0, alpha20_deg: float = 0.0,
                          chunk_size: int = 512, progress=False,
                          processes: int | str | None = None) -> MountingBudget:
    """Monte Carlo error budget over random mounting errors for each scheme.

    Each draw: ``dchi ~ N(0, dchi_std)`` (rotation vector, 3 axes), ``theta ~ N(0, theta_std)``
    (2 axes), white angle noise; simulate the exact model; regress (a) the six drifts only and
    (b) drifts + theta + dchi (the rank-deficient direction dchi || u is dropped by the
    minimum-norm solution). Returns every draw's drift errors in deg/h (all held in memory:
    for large budgets use :func:`mounting_budget_stats`). ``processes``: as in
    :func:`~gyrojax.analysis.monte_carlo` (``"all"``: one worker process per CPU core).
    """
    _check_budget(n_draws, dchi_std_arcmin, theta_std_arcmin, noise_arcsec)
    bt = _BudgetTrial(latitude_deg, schemes, drift, noise_arcsec, hours, sample_s, alpha20_deg)
    ns = len(bt.schemes)
    k1, k2, k3 = jax.random.split(key, 3)
    total = n_draws * ns
    dchi = jax.random.normal(k1, (total, 3)) * dchi_std_arcmin * units.ARCMIN
    theta = jax.random.normal(k2, (total, 2)) * theta_std_arcmin * units.ARCMIN
    keys = jax.random.key_data(jax.random.split(k3, total))
    sidx = jnp.repeat(jnp.arange(ns), n_draws)

    def simulate(draw):
        return bt.simulate(draw[0], draw[1], draw[2])

    def identify(draw, y):
        return bt.identify(draw[0], y, jax.random.wrap_key_data(draw[3]))

    e_only, e_joint = monte_carlo(staged(simulate, identify), (sidx, dchi, theta, keys),
                                  chunk_size=chunk_size, progress=progress,
                                  devices=jax.devices()[:1] if processes is None else None,
                                  vectorized=True, processes=processes)
    drift_only = {s: e_only[sidx == i] for i, s in enumerate(bt.schemes)}
    joint = {s: e_joint[sidx == i] for i, s in enumerate(bt.schemes)}
    return MountingBudget(bt.schemes, drift_only, joint, n_draws)


@dataclasses.dataclass(frozen=True)
class MountingBudgetStats:
    """The budget as statistics (:func:`mounting_budget_stats`): per fit (``drift_only``,
    ``joint``), scheme and drift parameter, the RMS error, the bias (mean) and the quantiles of
    the error, each with its standard error, in deg/h. `stats` is the underlying
    :class:`~gyrojax.analysis.streaming.MonteCarloStats`."""

    schemes: tuple[str, ...]
    stats: object

    def _leaf(self, which: str):
        return self.stats[f"[{which!r}]"]

    @property
    def n_draws(self) -> int:
        return self.stats.n_trials

    def rms(self, which: str = "drift_only") -> dict:
        r = self._leaf(which).rms.reshape(len(self.schemes), -1)
        return {s: r[i] for i, s in enumerate(self.schemes)}

    def rms_se(self, which: str = "drift_only") -> dict:
        """Standard error of :meth:`rms`."""
        r = self._leaf(which).rms_se.reshape(len(self.schemes), -1)
        return {s: r[i] for i, s in enumerate(self.schemes)}

    def to_xarray(self, quantiles=(0.5, 0.95)):
        """``xarray.Dataset`` over ``fit`` x ``scheme`` x ``parameter`` (x ``quantile``): ``rms``,
        ``rms_se``, ``bias``, ``bias_se``, ``std``, ``min``, ``max``, ``error_quantile`` (deg/h)."""
        import xarray as xr

        shape = (len(self.schemes), len(DRIFT_NAMES))
        fits = ("drift_only", "joint")
        out = {}
        for name, get in (("rms", lambda s: s.rms), ("rms_se", lambda s: s.rms_se),
                          ("bias", lambda s: s.mean), ("bias_se", lambda s: s.sem),
                          ("std", lambda s: s.std), ("min", lambda s: s.min),
                          ("max", lambda s: s.max)):
            out[name] = (("fit", "scheme", "parameter"),
                         np.stack([get(self._leaf(f)).reshape(shape) for f in fits]))
        if self._leaf("joint").hist is not None:
            out["error_quantile"] = (("fit", "quantile", "scheme", "parameter"), np.stack(
                [np.stack([self._leaf(f).quantile(q).reshape(shape) for q in quantiles])
                 for f in fits]))
        ds = xr.Dataset(out, coords={"fit": list(fits), "scheme": list(self.schemes),
                                     "parameter": list(DRIFT_NAMES),
                                     **({"quantile": list(quantiles)} if "error_quantile" in out
                                        else {})},
                        attrs={"unit": "deg/h", "n_draws": self.stats.n_trials,
                               "nonfinite": self.stats.nonfinite})
        return ds

    def markdown(self) -> str:
        ds = self.to_xarray()
        rows = ["| scheme | fit | " + " | ".join(DRIFT_NAMES) + " |",
                "|---|---|" + "---|" * len(DRIFT_NAMES)]
        for fit, label in (("drift_only", "drift only"), ("joint", "drift + mounting")):
            for s in self.schemes:
                cells = [f"{float(r):.2e} ± {float(e):.1e}" for r, e in zip(
                    ds["rms"].sel(fit=fit, scheme=s).values,
                    ds["rms_se"].sel(fit=fit, scheme=s).values)]
                rows.append(f"| {s} | {label} | " + " | ".join(cells) + " |")
        return "\n".join(rows)

    def to_json(self) -> dict:
        ds = self.to_xarray()
        out = {"n_draws": int(self.stats.n_trials), "unit": "deg/h",
               "nonfinite": int(self.stats.nonfinite), "statistic": "RMS over draws, with its "
               "standard error; bias (mean) with its standard error; quantiles of the error"}
        for fit in ("drift_only", "joint"):
            out[fit] = {s: {p: {k: float(ds[k].sel(fit=fit, scheme=s, parameter=p))
                                for k in ("rms", "rms_se", "bias", "bias_se")}
                            for p in DRIFT_NAMES} for s in self.schemes}
        return out


BUDGET_BINS = np.concatenate([-np.logspace(1, -6, 400), [0.0], np.logspace(-6, 1, 400)])
"""Histogram edges of the budget's drift errors (deg/h): log-spaced from 1e-6 to 10 on either
side of 0, ~4 % wide, for the quantiles."""


def mounting_budget_stats(key: PRNGKeyArray, n_draws: int, latitude_deg: float = 55.75, *,
                          schemes=SCHEMES, drift: float = 0.01, dchi_std_arcmin: float = 1.0,
                          theta_std_arcmin: float = 10.0, noise_arcsec: float = 0.0,
                          hours: float = 24.0, sample_s: float = 60.0,
                          alpha20_deg: float = 0.0, block_size: int = 256,
                          scheduler: str | None = None, client=None, resume=None,
                          progress: bool = False, stop_after: int | None = None
                          ) -> MountingBudgetStats:
    """The mounting-error budget of :func:`mounting_error_budget` as statistics, for budgets of
    any size: draw ``i`` comes from ``fold_in(key, i)`` (its ``dchi``, ``theta`` and noise key;
    every scheme sees the same draw), each block of `block_size` draws is reduced to mergeable
    statistics in its compiled program, and nothing per draw reaches the host. The result is the
    same bit for bit whatever runs it: this process (`scheduler` ``None``), a local Dask
    cluster (``"local"``), a scheduler address or `client`. `resume`, `progress`, `stop_after`:
    as in :func:`~gyrojax.analysis.streaming.monte_carlo_stats`. Other arguments as in
    :func:`mounting_error_budget`.

    **Returns:** a :class:`MountingBudgetStats` (``to_xarray()``, ``to_json()``, ``markdown()``).
    """
    from .streaming import monte_carlo_stats

    _check_budget(n_draws, dchi_std_arcmin, theta_std_arcmin, noise_arcsec)
    config = (float(latitude_deg), tuple(schemes), float(drift), float(dchi_std_arcmin),
              float(theta_std_arcmin), float(noise_arcsec), float(hours), float(sample_s),
              float(alpha20_deg))
    schemes, trial, draw = _budget_functions(*config)
    stats = monte_carlo_stats(trial, draw, key, n_draws, vectorized=True, block_size=block_size,
                              bins=BUDGET_BINS, scheduler=scheduler, client=client,
                              resume=resume, progress=progress, stop_after=stop_after)
    return MountingBudgetStats(schemes, stats)


@functools.lru_cache(maxsize=8)
def _budget_functions(latitude_deg, schemes, drift, dchi_std_arcmin, theta_std_arcmin,
                      noise_arcsec, hours, sample_s, alpha20_deg):
    """The budget's ``(schemes, trial, draw)``, the same function objects for the same budget
    (so a second budget reuses the compiled block program, here and on the workers)."""
    bt = _BudgetTrial(latitude_deg, schemes, drift, noise_arcsec, hours, sample_s, alpha20_deg)
    ns = len(bt.schemes)
    dchi_std = dchi_std_arcmin * units.ARCMIN
    theta_std = theta_std_arcmin * units.ARCMIN

    def draw(k):
        k1, k2, k3 = jax.random.split(k, 3)
        return (jax.random.normal(k1, (3,)) * dchi_std, jax.random.normal(k2, (2,)) * theta_std,
                jax.random.key_data(k3))

    def first(d):  # one draw, every scheme: the ODE solves, vmapped over the whole block
        dchi, theta, _ = d
        return jax.vmap(lambda i: bt.simulate(i, dchi, theta))(jnp.arange(ns))

    def second(d, ys):  # the regressions, in cache-sized sub-batches (see `staged`)
        noise_key = jax.random.wrap_key_data(d[2])
        e_only, e_joint = jax.vmap(lambda i, y: bt.identify(i, y, noise_key))(jnp.arange(ns), ys)
        return {"drift_only": e_only, "joint": e_joint}

    return bt.schemes, staged(first, second, batch_size=2), draw
