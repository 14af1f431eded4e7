"""Observability by autodiff Jacobian rank tests, with null spaces named as parameter combinations.

For a test design (rig, conditions, sample times, nominal parameters) and a set of free parameters,
the sensitivity matrix ``J`` (trajectory Jacobian through diffrax, or the regression design ``A``
of (6.3)) is column-normalized and decomposed by SVD. Relative singular values below ``exact_tol``
(default 1e-6) are *unobservable*, those below ``weak_tol`` (default 1e-3) *weakly observable*
(docs/rigs/esg.md). Null directions are returned in natural units (all ESG parameters are
dimensionless or rad, so they are commensurate) and written as named combinations; the
identifiable combinations are the orthogonal complement, in reduced row-echelon form with nominal
parameters as pivots (e.g. ``mc1 - theta1 - eps2``).

The Fisher information and Cramer-Rao bound for white noise of std ``sigma`` are
``F = J^T J / sigma^2`` and ``CRLB = F^+``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..estimate.least_squares import trajectory_jacobian
from ..estimate.regression import regression_design
from ..simulate import check_inputs, simulate

__all__ = ["ObservabilityReport", "analyse_jacobian", "observability", "format_combination",
           "cramer_rao"]


def format_combination(coeffs, names, *, tol: float = 1e-3, digits: int = 3) -> str:
    """Write ``sum_i coeffs_i names_i`` as text, largest coefficient first normalized to 1."""
    coeffs = np.asarray(coeffs, float)
    big = np.max(np.abs(coeffs))
    if big == 0:
        return "0"
    terms = []
    for c, n in zip(coeffs / big, names):
        if abs(c) < tol:
            continue
        sign = "-" if c < 0 else "+"
        mag = "" if abs(abs(c) - 1) < 10 ** (-digits) else f"{abs(c):.{digits}g} "
        terms.append((sign, f"{mag}{n}"))
    if not terms:
        return "0"
    first = ("-" if terms[0][0] == "-" else "") + terms[0][1]
    return " ".join([first] + [f"{s} {t}" for s, t in terms[1:]])


# pivot threshold of the readable bases, on orthonormal rows: directions found numerically (the
# eigenvectors of a cluster of near-zero eigenvalues, whose span is good to ~1e-4 where the
# cluster is 1e-8 of the largest) would otherwise take a pivot from their error and print as
# combinations with huge coefficients, or twice; a genuine pivot this small would print as one
# anyway
RREF_TOL = 1e-3


def _rref(m, tol=1e-9):
    m = np.array(m, float)
    rows, cols = m.shape
    r = 0
    pivots = []
    for c in range(cols):
        if r >= rows:
            break
        p = r + int(np.argmax(np.abs(m[r:, c])))
        if abs(m[p, c]) < tol:
            continue
        m[[r, p]] = m[[p, r]]
        m[r] /= m[r, c]
        for i in range(rows):
            if i != r:
                m[i] -= m[i, c] * m[r]
        pivots.append(c)
        r += 1
    return m[:r], pivots


@dataclasses.dataclass(frozen=True)
class ObservabilityReport:
    """Result of an observability analysis.

    - `names`: the free parameters; `singular_values`: relative, largest first.
    - `rank`: number of relative singular values >= ``exact_tol``; `strong_rank`: >= ``weak_tol``.
    - `null_exact`, `null_weak`: null-space bases (rows, natural units) for the two thresholds.
    - `unobservable`, `weak`: the same as text combinations.
    - `identifiable`: identifiable combinations of the parameters touched by the (weak) null space.
    """

    names: tuple[str, ...]
    singular_values: np.ndarray
    rank: int
    strong_rank: int
    null_exact: np.ndarray
    null_weak: np.ndarray
    exact_tol: float
    weak_tol: float

    @property
    def unobservable(self) -> list[str]:
        return [format_combination(v, self.names) for v in _pretty_basis(self.null_exact)]

    @property
    def weak(self) -> list[str]:
        return [format_combination(v, self.names) for v in _pretty_basis(self.null_weak)]

    def identifiable(self, which: str = "weak") -> list[str]:
        """Combinations of the involved parameters that *are* determined (orthogonal complement of
        the null space within the parameters it touches), e.g. ``mc1 - theta1 - eps2``."""
        null = self.null_weak if which == "weak" else self.null_exact
        if null.shape[0] == 0:
            return []
        involved = np.where(np.max(np.abs(null), axis=0) > 1e-3 * np.max(np.abs(null)))[0]
        names = [self.names[i] for i in involved]
        return [format_combination(row, names) for row in complement_basis(null[:, involved])]

    def summary(self) -> str:
        lines = [f"{len(self.names)} parameters, rank {self.rank} (exact tol {self.exact_tol:g}), "
                 f"{self.strong_rank} strongly observable (weak tol {self.weak_tol:g})",
                 "relative singular values: " + " ".join(f"{s:.2e}" for s in self.singular_values)]
        if self.null_exact.shape[0]:
            lines.append("unobservable directions: " + "; ".join(self.unobservable))
        weak_only = self.null_weak.shape[0] - self.null_exact.shape[0]
        if weak_only > 0:
            lines.append("weakly observable null space: " + "; ".join(self.weak))
        ident = self.identifiable("weak")
        if ident:
            lines.append("identifiable combinations: " + "; ".join(ident))
        return "\n".join(lines)

    def to_json(self) -> dict:
        return {"parameters": list(self.names), "rank": self.rank,
                "strongly_observable_rank": self.strong_rank,
                "relative_singular_values": [float(s) for s in self.singular_values],
                "exact_tol": self.exact_tol, "weak_tol": self.weak_tol,
                "unobservable": self.unobservable, "weakly_observable": self.weak,
                "identifiable_combinations": self.identifiable("weak")}


def complement_basis(null) -> np.ndarray:
    """The combinations ``c`` (rows, reduced row-echelon form) with ``c . x = 0`` for every row
    ``x`` of ``null``: what a design with null space ``null`` determines among the parameters
    that ``null`` involves (its columns). Both in the same units, e.g. ``mc1 - theta1 - eps2``."""
    _, s, vt = np.linalg.svd(np.atleast_2d(null))
    comp = vt[int(np.sum(s > 1e-9 * s[0])):]
    return _rref(comp, RREF_TOL)[0] if comp.shape[0] else comp


def _pretty_basis(null):
    """A null-space basis in reduced row-echelon form (readable, unique up to ordering)."""
    if null.shape[0] == 0:
        return null
    _, s, vt = np.linalg.svd(null, full_matrices=False)
    rref, _ = _rref(vt[: int(np.sum(s > 1e-9 * s[0]))], RREF_TOL)
    return rref


def analyse_jacobian(jac: Float[ArrayLike, "m k"], names: Sequence[str], *, exact_tol: float = 1e-6,
                     weak_tol: float = 1e-3) -> ObservabilityReport:
    """Rank, relative singular values and named null spaces of a sensitivity matrix ``jac``
    (rows: observations, columns: ``names`` in natural units)."""
    jac = np.asarray(jac, float)
    if jac.shape[1] != len(names):
        raise ValueError(f"jacobian has {jac.shape[1]} columns but {len(names)} names")
    norms = np.linalg.norm(jac, axis=0)
    zero = norms <= 1e-12 * max(norms.max(), 1e-300)
    scale = np.where(zero, 1.0, norms)
    js = np.where(zero[None, :], 0.0, jac / scale)
    _, s, vt = np.linalg.svd(js, full_matrices=False)
    rel = s / s[0] if s[0] > 0 else s
    rank = int(np.sum(rel >= exact_tol))
    strong = int(np.sum(rel >= weak_tol))
    nat = vt / scale[None, :]  # back to natural units
    nat = nat / np.max(np.abs(nat), axis=1, keepdims=True)
    return ObservabilityReport(tuple(names), rel, rank, strong, nat[rank:], nat[strong:],
                               exact_tol, weak_tol)


def observability(rig, params: Mapping, conditions, ts: Float[ArrayLike, " n"], *,
                  free: Sequence[str],
                  method: str = "trajectory", exact_tol: float = 1e-6,
                  weak_tol: float = 1e-3, window: int = 1) -> ObservabilityReport:
    """Observability of ``free`` parameters in a test (noise-free, at ``params``).

    **Arguments:**
    - `method`: ``"trajectory"`` — autodiff Jacobian of the sampled channels through diffrax (any
      parameter of the rig, exact model); ``"regression"`` — the block design ``A`` of the linear
      model (6.3) evaluated on the simulated angles (only ``rig.regression_names``).
    """
    free = rig.param_space.check_names(free)
    check_inputs(rig, params, ts, what="observability")
    if method == "trajectory":
        jac = trajectory_jacobian(rig, params, conditions, ts, free)
    elif method == "regression":
        rec = simulate(rig, params, conditions, ts)
        jac, _, _ = regression_design(rig, rec, conditions, window=window, names=free)
    else:
        raise ValueError(f"method={method!r}; use 'trajectory' or 'regression'")
    return analyse_jacobian(jac, free, exact_tol=exact_tol, weak_tol=weak_tol)


def cramer_rao(jac: Float[ArrayLike, "m k"], noise_std: float) -> Float[Array, "k k"]:
    """Cramer-Rao bound ``sigma^2 (J^T J)^+`` for white Gaussian noise of std ``noise_std``."""
    jac = jnp.asarray(jac)
    return noise_std**2 * jnp.linalg.pinv(jac.T @ jac, hermitian=True)
