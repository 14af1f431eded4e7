"""Observability of the Schuler test (docs/rigs/schuler.md): Fisher information of the 12
unknowns from autodiff sensitivities of the nonlinear model, Cramer-Rao bounds with the prior,
correlations, the weakly separable pairs by name, and the velocity-only variant (the classical
pass/fail test's measurement)."""

from __future__ import annotations

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..estimate.schuler import THETA_NAMES, _prior_std, schuler_residuals
from ..models.schuler import SchulerConditions, SchulerRig
from ..simulate import integrate

__all__ = ["SchulerObservability", "schuler_observability"]


@dataclasses.dataclass(frozen=True)
class SchulerObservability:
    """Information of one test design.

    - ``fisher``: Fisher information of ``theta / sigma_prior`` (12, 12), data only ("prior
      units": an eigenvalue below 1 means the data inform that direction less than the prior);
    - ``crlb``: Cramer-Rao standard deviations with the prior (12,), internal units;
    - ``correlation``: of the posterior (12, 12); ``rank``: numerical rank of the data-only
      information (relative tolerance 1e-12); ``condition``: its condition number.
    """

    names: tuple[str, ...]
    duration_s: float
    channels: str
    fisher: np.ndarray
    crlb: np.ndarray
    correlation: np.ndarray
    rank: int
    condition: float

    def weak_pairs(self, threshold: float = 0.95) -> list[tuple[str, str, float]]:
        """Pairs whose posterior correlation exceeds ``threshold`` in magnitude, strongest first."""
        c = self.correlation
        out = [(self.names[i], self.names[j], float(c[i, j])) for i in range(len(self.names))
               for j in range(i + 1, len(self.names)) if abs(c[i, j]) > threshold]
        return sorted(out, key=lambda p: -abs(p[2]))

    def weakest_directions(self, k: int = 3) -> list[tuple[float, str]]:
        """The ``k`` least-informed directions: (Fisher eigenvalue in prior units, combination)."""
        from .observability import format_combination

        w, v = np.linalg.eigh(self.fisher)
        return [(float(w[i]), format_combination(v[:, i], self.names, tol=0.1)) for i in range(k)]

    def table(self) -> str:
        space = SchulerRig().param_space
        rows = [f"Schuler test, {self.duration_s / 60:.1f} min, channels: {self.channels}; "
                f"rank {self.rank}/12, condition {self.condition:.2g}",
                f"{'name':8s} {'CRLB':>10s} unit"]
        for n, s in zip(self.names, self.crlb, strict=True):
            p = space[n]
            rows.append(f"{n:8s} {float(p.to_display(s)):10.3g} {p.display_unit}")
        rows.append("weak pairs: " + ", ".join(f"{a}/{b} {c:+.3f}" for a, b, c in self.weak_pairs()))
        return "\n".join(rows)


def schuler_observability(rig: SchulerRig, conditions: SchulerConditions, duration_s: float, *,
                          dt: float = 1.0, sigma_v: float = 0.05,
                          sigma_theta: float = units.ARCMIN, channels: str = "all",
                          prior_std: dict | None = None, params=None) -> SchulerObservability:
    """Fisher information and Cramer-Rao bounds of a Schuler test of ``duration_s`` seconds
    sampled every ``dt`` s, linearised at ``params`` (default: error-free), from forward-mode
    sensitivities of the nonlinear model. ``channels``: ``"all"`` (velocities and attitude) or
    ``"velocity"`` (the classical test's model velocities only)."""
    if channels not in ("all", "velocity"):
        raise ValueError(f"channels={channels!r}: use 'all' or 'velocity'")
    if not duration_s > 0 or not dt > 0 or duration_s < 2 * dt:
        raise ValueError(f"duration_s={duration_s}, dt={dt}: need 0 < 2 dt <= duration")
    ts = jnp.arange(0.0, duration_s + 0.5 * dt, dt)
    sig = _prior_std(rig, prior_std)
    base = rig.param_space.make({}) if params is None else params
    theta0 = jnp.array([base[n] for n in THETA_NAMES])
    y = integrate(rig, base, conditions, ts)
    w = 1.0 / jnp.array([sigma_v, sigma_v, sigma_theta, sigma_theta, sigma_theta])
    keep = 2 if channels == "velocity" else 5
    jac = np.asarray(_jacobian(rig, conditions, ts, y, w, sig, theta0, keep))
    fisher = jac.T @ jac
    post = np.linalg.inv(fisher + np.eye(len(THETA_NAMES)))
    crlb_u = np.sqrt(np.diag(post))
    corr = post / np.outer(crlb_u, crlb_u)
    s = np.linalg.svd(jac, compute_uv=False)
    rank = int(np.sum(s > 1e-12 * s[0]))
    return SchulerObservability(THETA_NAMES, float(ts[-1]), channels, fisher,
                                crlb_u * np.asarray(sig), corr, rank,
                                float(s[0] ** 2 / s[-1] ** 2) if s[-1] > 0 else np.inf)


@eqx.filter_jit
def _jac_all(rig, conditions, ts, y, w, sig, theta0):
    def resid(u):
        params = dict(zip(THETA_NAMES, theta0 + u * sig, strict=True))
        r = schuler_residuals(rig, conditions, ts, y, params, adjoint=diffrax.ForwardMode())
        return r * w

    return jax.jacfwd(resid)(jnp.zeros_like(sig))  # (N, 5, 12)


def _jacobian(rig, conditions, ts, y, w, sig, theta0, keep):
    jac = _jac_all(rig, conditions, ts, y, w, sig, theta0)
    return jac[:, :keep].reshape(-1, sig.shape[0])
