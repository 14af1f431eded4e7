"""Polar-gyro logarithmic spiral (docs/rigs/esg.md, (4.2)-(4.6)) and its fit through optimistix.

For the polar scheme at small angles, the spin-axis trace is approximately the spiral (4.4)
$\\alpha_1 = \\alpha_{c1} + r e^{-\\lambda\\tau}\\cos(\\nu\\tau+\\psi)$,
$\\alpha_2 = \\alpha_{c2} - r e^{-\\lambda\\tau}\\sin(\\nu\\tau+\\psi)$ with centre, damping and frequency
(4.3) set by the drift. The fit minimizes (4.6) by Levenberg-Marquardt; (4.5) inverts the spiral to
``m11 m12 m21 m22`` when ``mc1, mc2`` are known. Accuracy is limited to 15-20 % by the neglected
ellipticity (docs/rigs/esg.md): use it as an initializer, not an estimator.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..record import BenchRecord
from ._lstsq import ScaledLevenbergMarquardt, solve_least_squares

__all__ = ["spiral_parameters", "spiral_trajectory", "fit_spiral", "invert_spiral", "SpiralResult"]

SPIRAL_NAMES = ("alpha_c1", "alpha_c2", "r", "lam", "nu", "psi")


def spiral_parameters(m, latitude):
    """Centre ``(alpha_c1, alpha_c2)``, damping ``lam`` and frequency ``nu`` of (4.3).

    ``m = (m11, m12, m21, m22, mc1, mc2)`` normalized; latitude in rad.
    """
    m11, m12, m21, m22, mc1, mc2 = m
    s, c = jnp.sin(latitude), jnp.cos(latitude)
    s2 = jnp.sin(2 * latitude)
    ac1 = mc1 + m21 * c - m22 * s2
    ac2 = mc2 - m11 * c + m12 * s2
    lam = m21 * s + m22 * (1 - 3 * s**2)
    nu = 1 - m11 * s - m12 * (1 - 3 * s**2)
    return ac1, ac2, lam, nu


def spiral_trajectory(theta: Float[ArrayLike, " 6"], tau: Float[ArrayLike, " n"]
                      ) -> Float[Array, "n 2"]:
    """(4.4) at normalized times ``tau``: shape ``(n, 2)``; ``theta`` = SPIRAL_NAMES values."""
    ac1, ac2, r, lam, nu, psi = theta
    e = r * jnp.exp(-lam * tau)
    ph = nu * tau + psi
    return jnp.stack([ac1 + e * jnp.cos(ph), ac2 - e * jnp.sin(ph)], axis=-1)


def invert_spiral(theta, latitude, mc1, mc2):
    """(4.5): ``m11 m12 m21 m22`` from the spiral parameters when ``mc1, mc2`` are known."""
    ac1, ac2, r, lam, nu, psi = theta
    s, c = jnp.sin(latitude), jnp.cos(latitude)
    s2 = jnp.sin(2 * latitude)
    m12 = ((1 - nu) * c + (ac2 - mc2) * s) / c**3
    m11 = (-ac2 + mc2 + m12 * s2) / c
    m22 = ((mc1 - ac1) * s + lam * c) / c**3
    m21 = (ac1 - mc1 + m22 * s2) / c
    return jnp.stack([m11, m12, m21, m22])


class SpiralResult(eqx.Module):
    """Spiral fit: `theta` (SPIRAL_NAMES), `drift` (m11 m12 m21 m22 by (4.5)), `residual_rms` (rad),
    `converged`."""

    theta: jax.Array
    drift: jax.Array
    residual_rms: jax.Array
    converged: jax.Array


@eqx.filter_jit
def _fit_spiral(tau, y, latitude, mc1, mc2, rtol, atol, max_steps):
    centre = jnp.mean(y, axis=0)
    d0 = y[0] - centre
    r0 = jnp.sqrt(jnp.mean(jnp.sum((y - centre) ** 2, axis=-1)))
    psi0 = jnp.arctan2(-d0[1], d0[0])
    x0 = jnp.stack([centre[0], centre[1], r0, jnp.zeros(()), jnp.ones(()), psi0])

    def resid(x, args):
        return (spiral_trajectory(x, tau) - y).reshape(-1)

    sol = solve_least_squares(resid, x0, solver=ScaledLevenbergMarquardt(rtol=rtol, atol=atol),
                              max_steps=max_steps, step_se_tol=0.0)
    return SpiralResult(sol.value, invert_spiral(sol.value, latitude, mc1, mc2),
                        jnp.sqrt(jnp.mean(sol.residual**2)), sol.converged)


def fit_spiral(record: BenchRecord, latitude, *, mc1=0.0, mc2=0.0, time_scale=None,
               rtol: float = 1e-10, atol: float = 1e-12, max_steps: int = 200) -> SpiralResult:
    """Fit the spiral (4.4) to a polar-scheme record by minimizing (4.6).

    **Arguments:** `record` (alpha1, alpha2 in rad), `latitude` (rad), `mc1`, `mc2` (known
    case-fixed drifts, normalized) for the inversion (4.5); `time_scale` (default Earth rate).
    """
    from ..units import EARTH_RATE

    tau = record.t * (EARTH_RATE if time_scale is None else time_scale)
    return _fit_spiral(tau - tau[..., :1], record.y, jnp.asarray(latitude, float),
                       jnp.asarray(mc1, float), jnp.asarray(mc2, float), rtol, atol, max_steps)
