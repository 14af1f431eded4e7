"""Test design for the vibrating platform: Fisher information of position sets and amplitude pairs
(issue "beyond the paper" (b)).

Over a dwell of ``T`` s sampled every ``dt`` with white angle noise ``sigma``, the averaged model
moves the gimbal angles at the constant rate ``J_p D`` (``J_p`` = the rig's vector field
differentiated by autodiff with respect to the 30 coefficients at position ``p``), and the
position's unknown initial angles are nuisance parameters; the information the dwell carries about
``D`` is ``S_tt / sigma^2 J_p^T J_p`` with ``S_tt = sum (t_k - mean t)^2``. A design is a set of
(position, amplitude) dwells; its information is the sum. Criteria, in coefficient units scaled
by their typical magnitudes (``Param.scale``): D-optimality ``log det I`` (larger is better) and
the worst standard error relative to the coefficient's scale (smaller is better).
"""

from __future__ import annotations

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np

from .. import units
from ..models.platform import COEFF_NAMES, DEFAULT_MOUNTING, TABLE1_DEG, PlatformRig, schedule

__all__ = ["dwell_jacobians", "design_information", "DesignScore", "score_design",
           "propose_positions", "rank_amplitude_pairs", "candidate_positions"]

_RIG = PlatformRig()


def dwell_jacobians(positions_deg, a0: float, *, mounting=DEFAULT_MOUNTING) -> np.ndarray:
    """``J_p`` (P, 3, 30): angle-rate sensitivities to the coefficients at each position, in
    coefficient units of ``Param.scale`` (autodiff of the averaged model's vector field)."""
    space = _RIG.param_space
    base = space.make()
    scale = jnp.asarray(space.scales(COEFF_NAMES))

    def rates(x, c):
        p = base | dict(zip(COEFF_NAMES, x * scale))
        return _RIG.vector_field(0.0, c.angles0, p, c)

    conds = schedule(positions_deg, a0=a0, mounting=mounting)
    jac = jax.vmap(lambda c: jax.jacfwd(rates)(jnp.zeros(30), c))(conds)
    return np.asarray(jac)


def design_information(jacs, *, dwell_s: float = 100.0, dt: float = 0.025,
                       noise_arcsec: float = 1.0) -> np.ndarray:
    """Fisher information (30 x 30, scaled units) of dwells with Jacobians ``jacs`` (P, 3, 30)."""
    t = np.arange(0.0, dwell_s + 0.5 * dt, dt)
    s_tt = float(np.sum((t - t.mean()) ** 2))
    sigma = noise_arcsec * units.ARCSEC
    j = np.asarray(jacs).reshape(-1, 30)
    return s_tt / sigma**2 * (j.T @ j)


@dataclasses.dataclass(frozen=True)
class DesignScore:
    """``log_det`` (D-optimality; -inf if singular), ``worst_se`` (largest standard error in units
    of the coefficient's scale, inf if singular), ``worst`` (its name), ``rank``."""

    log_det: float
    worst_se: float
    worst: str
    rank: int


def score_design(info) -> DesignScore:
    w = np.linalg.eigvalsh(info)
    rank = int(np.sum(w > 1e-9 * w.max()))
    if rank < info.shape[0]:
        return DesignScore(-np.inf, np.inf, "singular", rank)
    cov = np.linalg.inv(info)
    se = np.sqrt(np.diag(cov))
    k = int(np.argmax(se))
    return DesignScore(float(np.sum(np.log(w))), float(se[k]), COEFF_NAMES[k], rank)


def candidate_positions(step_deg: float = 45.0) -> np.ndarray:
    """Positions with beta = 0 and alpha, gamma on a grid (the gimbals' reachable, non-locked set)."""
    g = np.arange(0.0, 360.0, step_deg)
    return np.array([[a, 0.0, c] for a in g for c in g])


def propose_positions(a0s, n_positions: int = 14, *, candidates=None, criterion: str = "d",
                      mounting=DEFAULT_MOUNTING, sweeps: int = 4, **info_kw):
    """Choose ``n_positions`` dwells from ``candidates`` (default: 45 deg grid) to run at every
    amplitude in ``a0s``, by a Fedorov-style exchange started from Table 1: swap a chosen position
    for a candidate while the criterion improves (``"d"``: log det; ``"worst"``: worst scaled
    standard error). Returns ``(positions_deg, DesignScore)``."""
    if criterion not in ("d", "worst"):
        raise ValueError(f"criterion={criterion!r}; use 'd' (D-optimal) or 'worst'")
    cand = candidate_positions() if candidates is None else np.asarray(candidates, float)
    jc = [dwell_jacobians(cand, a, mounting=mounting) for a in a0s]
    cand_info = np.stack([sum(design_information(j[i][None], **info_kw) for j in jc)
                          for i in range(len(cand))])

    def key(s: DesignScore):
        return s.log_det if criterion == "d" else -s.worst_se

    start = [int(np.argmin(np.sum(np.abs((cand - p + 180.0) % 360.0 - 180.0), axis=1)))
             for p in TABLE1_DEG]
    chosen = (start + [i for i in range(len(cand)) if i not in start])[:n_positions]
    best = score_design(sum(cand_info[i] for i in chosen))
    for _ in range(sweeps):
        improved = False
        for slot in range(len(chosen)):
            for c in range(len(cand)):
                trial = chosen.copy()
                trial[slot] = c
                s = score_design(sum(cand_info[i] for i in trial))
                if key(s) > key(best) + 1e-9:
                    chosen, best, improved = trial, s, True
        if not improved:
            break
    return cand[chosen], best


def rank_amplitude_pairs(table_amplitudes_g, *, attenuation: float = 1.5,
                         positions_deg=TABLE1_DEG, mounting=DEFAULT_MOUNTING, **info_kw):
    """Score every pair of table amplitudes (g) run over ``positions_deg`` (platform amplitude
    ``a / attenuation``); returns rows ``(a1, a2, DesignScore)`` best (smallest worst-se) first."""
    amps = sorted(set(float(a) for a in table_amplitudes_g))
    if any(a < 0 for a in amps):
        raise ValueError("table amplitudes must be >= 0 g")
    infos = {a: design_information(dwell_jacobians(positions_deg, a / attenuation,
                                                   mounting=mounting), **info_kw) for a in amps}
    rows = [(a1, a2, score_design(infos[a1] + infos[a2]))
            for a1, a2 in itertools.combinations(amps, 2)]
    return sorted(rows, key=lambda r: r[2].worst_se)
