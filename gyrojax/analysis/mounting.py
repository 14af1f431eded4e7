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

__all__ = ["mounting_error_tables", "mounting_error_budget", "MountingTables", "MountingBudget",
           "PAPER_TABLE2", "PAPER_TABLE3"]

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


def mounting_error_budget(key: PRNGKeyArray, n_draws: int, latitude_deg: float = 55.75, *, schemes=SCHEMES,
                          drift: float = 0.01, dchi_std_arcmin: float = 1.0,
                          theta_std_arcmin: float = 10.0, noise_arcsec: float = 0.0,
                          hours: float = 24.0, sample_s: float = 60.0, alpha20_deg: float = 0.0,
                          chunk_size: int = 512, progress=False,
                          processes: int | str | None = None) -> MountingBudget:
    """Monte Carlo error budget over random mounting errors for each scheme.

    Each draw: ``dchi ~ N(0, dchi_std)`` (rotation vector, 3 axes), ``theta ~ N(0, theta_std)``
    (2 axes), white angle noise; simulate the exact model; regress (a) the six drifts only and
    (b) drifts + theta + dchi (the rank-deficient direction dchi || u is dropped by the
    minimum-norm solution). Returns the drift errors in deg/h. ``processes``: as in
    :func:`~gyrojax.analysis.monte_carlo` (``"all"``: one worker process per CPU core).
    """
    if n_draws < 1:
        raise ValueError(f"n_draws={n_draws}: need at least one Monte Carlo draw")
    for name, v in (("dchi_std_arcmin", dchi_std_arcmin), ("theta_std_arcmin", theta_std_arcmin),
                    ("noise_arcsec", noise_arcsec)):
        if not np.isfinite(v) or v < 0:
            raise ValueError(f"{name}={v}: a standard deviation must be finite and >= 0")
    schemes = tuple(schemes)
    rig = ESGRig(base_param="rotvec")
    space = rig.param_space
    ts = jnp.arange(0.0, hours * 3600.0 + 0.5 * sample_s, sample_s)
    base = space.make({n: drift for n in DRIFT_NAMES}, alpha20=alpha20_deg * units.DEG)
    conds = _stack_conditions(schemes, latitude_deg)
    ns = len(schemes)
    k1, k2, k3 = jax.random.split(key, 3)
    total = n_draws * ns
    dchi = jax.random.normal(k1, (total, 3)) * dchi_std_arcmin * units.ARCMIN
    theta = jax.random.normal(k2, (total, 2)) * theta_std_arcmin * units.ARCMIN
    keys = jax.random.key_data(jax.random.split(k3, total))
    sidx = jnp.repeat(jnp.arange(ns), n_draws)
    joint_names = rig.regression_names
    masks = jnp.stack([jnp.array([n in DRIFT_NAMES for n in joint_names]),
                       jnp.ones(len(joint_names), bool)])
    noise = noise_arcsec * units.ARCSEC
    # one fixed step grid for every draw (each step's error is still checked against the
    # tolerance): about 3x faster than adaptive steps in a batch
    counts = [grid_steps(rig, base, jax.tree.map(lambda x: x[i], conds), ts) for i in range(ns)]
    steps = None if None in counts else max(counts)

    def simulate(draw):
        i, dc, th, _ = draw
        c = jax.tree.map(lambda x: x[i], conds)
        p = base | {"theta1": th[0], "theta2": th[1], "dchi1": dc[0], "dchi2": dc[1],
                    "dchi3": dc[2]}
        return integrate(rig, p, c, ts, steps=steps)

    def identify(draw, y):
        # noise in the regression's sub-batch, where the record is in cache (see `staged`);
        # noise-free budgets draw no deviates
        if noise != 0.0:
            y = y + gaussian_noise(jax.random.wrap_key_data(draw[3]), y.shape, noise)
        c = jax.tree.map(lambda x: x[draw[0]], conds)
        rec = BenchRecord(ts, y, rig.channels)
        a, b, _ = regression_design(rig, rec, c, names=joint_names)
        # both fits from one design in one batched solve: two independent LAPACK solves after a
        # while_loop in one graph can deadlock jaxlib 0.10.2's CPU runtime
        # (docs/decisions/0007-monte-carlo-worker-processes.md)
        est = jax.vmap(lambda m: scaled_lstsq(a * m, b)[0][:6])(masks)
        err = (est - drift) * units.EARTH_RATE_DEG_PER_HOUR
        return err[0], err[1]

    e_only, e_joint = monte_carlo(staged(simulate, identify), (sidx, dchi, theta, keys),
                                  chunk_size=chunk_size, progress=progress,
                                  devices=jax.devices()[:1] if processes is None else None,
                                  vectorized=True, processes=processes)
    drift_only = {s: e_only[sidx == i] for i, s in enumerate(schemes)}
    joint = {s: e_joint[sidx == i] for i, s in enumerate(schemes)}
    return MountingBudget(schemes, drift_only, joint, n_draws)
