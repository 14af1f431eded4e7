"""Signatures, projections and visibility: the nominal span, an effect's projected signature, its
directions without a signature or absorbed by the nominal parameters, canonical correlations
between effects (docs/diagnosis.md).

Everything here works on *whitened* quantities: the residual ``e`` (length ``m``, unit variance
under the nominal model) and Jacobians whose columns are derivatives of ``e``'s model per unit
of a parameter's scale (nominal parameters: ``Param.scale``; effects: their prior scale). So an
effect's coefficient ``b`` is in prior-scale units and its noncentrality is ``b^T I b``.

- the nominal span is an orthonormal basis ``U`` of ``J_theta`` (SVD; ``I - P`` is never formed);
- efficient score test per effect: ``J~ = J - U U^T J``, ``I = J~^T J~``, ``s = J~^T e``,
  ``LM = s^T I^+ s ~ chi2(rank I)``; grid effects take ``sup_g LM_g`` with a parametric bootstrap
  p-value (the scores are jointly Gaussian with covariance ``J~_g^T J~_h`` under H0);
- score Bayes factor under a Gaussian prior ``b ~ N(0, c^2)`` (prior-scale units):
  ``log BF = c^2 s^T (c^2 I + 1)^-1 s / 2 - log det(1 + c^2 I) / 2``, with ``c = 1`` (the prior
  scales themselves) or ``c^2 = lambda0 / tr I`` (the shape prior: the prior scales' shape,
  sized so that the expected noncentrality is ``lambda0`` on this design), or the g-prior
  ``b ~ N(0, (lambda0 / dof) I^-1)``; the default (design) prior is the equal mixture of the
  shape prior and the g-prior;
- visible fraction ``v = 1 - rho_max^2`` of the effect's signature after the nominal projection,
  null directions of the raw signature ("no signature on this bench"), the alias matrix
  ``A = J_theta^+ J_beta`` by name, and canonical correlations between projected signatures.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import special

__all__ = ["INDISTINGUISHABLE", "LAMBDA_80", "NULL_TOL", "SEPARABLE", "Signature", "VISIBLE_MIN",
           "canonical_correlation", "canonical_correlations", "check_effects", "chi2_sf",
           "coefficient_effect", "effect_family_name", "indistinguishable_classes", "nominal_basis",
           "onset_grid", "project_out", "signature_directions", "visibility_flag", "visible"]


LAMBDA_80 = 7.85  # noncentrality giving 80 % power at alpha = 0.05, 1 dof


SEPARABLE = 0.9  # docs/goals.md: separable = largest projected canonical correlation <= this


INDISTINGUISHABLE = 0.98  # docs/diagnosis.md stage 3: pairs at or above "cannot be told apart"


NULL_TOL = 1e-6  # relative singular value of a raw signature direction counted as no signature


@dataclasses.dataclass(frozen=True)
class Signature:
    """One catalogued effect as the diagnosis sees it.

    - `name`, `family`: the effect's identifier (``rotor_tilt``) and family (``mounting``...).
    - `names`, `units`: its coefficients and their display units; `prior_scale`: their prior
      magnitude in display units.
    - `jac`: ``(G, m, p)`` whitened Jacobian per unit prior scale, one slice per grid value.
    - `grid`, `grid_name`, `grid_unit`: the values of a parameter identified only under the
      alternative (decay time, onset, ...), in display units; empty for ordinary effects.
    - `kind`: ``"model"`` (a term of the rig's equations) or ``"output"`` (added to the channels).
    """

    name: str
    family: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    prior_scale: np.ndarray
    jac: np.ndarray
    grid: tuple[float, ...] = ()
    grid_name: str = ""
    grid_unit: str = ""
    kind: str = "model"

    def __post_init__(self):
        if self.jac.ndim != 3 or self.jac.shape[2] != len(self.names):
            raise ValueError(f"signature {self.name}: jac has shape {self.jac.shape}; expected "
                             f"(grid, samples, {len(self.names)})")


def coefficient_effect(effect: str, coefficient: str) -> str:
    """The name of one coefficient screened as an effect of its own (``per_coefficient``):
    ``"g_sensitivity:gsxy"``."""
    return f"{effect}:{coefficient}"


def effect_family_name(name: str) -> str:
    """The catalogue effect an effect name belongs to (``"g_sensitivity:gsxy"`` ->
    ``"g_sensitivity"``; a catalogue name is its own)."""
    return name.split(":", 1)[0]


def check_effects(effects, library, rig: str) -> None:
    """A clear error for effect names outside the rig's catalogue ``library``."""
    bad = [e for e in (effects or ()) if e not in library]
    if bad:
        raise ValueError(f"unknown effect(s) {bad} for --rig {rig}; the catalogue is "
                         f"{', '.join(library)}")


def onset_grid(t, n_train: int) -> np.ndarray:
    """A step's onset grid over the train span of a record sampled at ``t``: equally spaced
    interior values at most 5 % of the record apart (goal G8 asks onsets within one such
    window) and at least 8 of them; in ``t``'s units."""
    t = np.asarray(t, float)
    span = t[n_train - 1] - t[0]
    n_int = max(9, math.ceil(span / (0.05 * (t[-1] - t[0])) - 1e-9))
    return t[0] + span * np.arange(1, n_int) / n_int


def nominal_basis(jn: np.ndarray, *, rtol: float = 1e-10) -> np.ndarray:
    """Orthonormal basis of the span of the nominal Jacobian (rank-revealing SVD)."""
    u, s, _ = np.linalg.svd(jn, full_matrices=False)
    return u[:, s > rtol * s[0]]


def project_out(u, j):
    return j - u @ (u.T @ j)


def _orth(j, rtol=1e-8):
    """Orthonormal basis of span(j) and the kept singular values."""
    if j.shape[1] == 0:
        return j, np.zeros(0)
    u, s, _ = np.linalg.svd(j, full_matrices=False)
    keep = s > rtol * max(s[0], 1e-300)
    return u[:, keep], s[keep]


def indistinguishable_classes(pairs: dict, names) -> list[list[str]]:
    """The diagnosis' ambiguity classes: the effects ``names`` merged into classes by their pairs at projected
    canonical correlation >= :data:`INDISTINGUISHABLE` (``pairs``: ``{(a, b): correlation}``,
    the *smallest* canonical correlation of the pair, so that a class means every direction of
    the smaller effect is mimicked by the other; connected components, in the order of
    ``names``). Only classes of two or more."""
    names = list(names)
    parent = {n: n for n in names}

    def root(n):
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = parent[n]
        return n
    for (a, b), v in pairs.items():
        if a in parent and b in parent and v >= INDISTINGUISHABLE:
            parent[root(b)] = root(a)
    groups = {}
    for n in names:
        groups.setdefault(root(n), []).append(n)
    return [g for g in groups.values() if len(g) > 1]


def canonical_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Largest canonical correlation between the column spans of ``a`` and ``b``."""
    return float(canonical_correlations(a, b)[0])


def canonical_correlations(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """All canonical correlations between the column spans of ``a`` and ``b``, largest first
    (``min(rank a, rank b)`` of them; ``[0.0]`` where a span is empty). The smallest is near 1
    only where the smaller span lies inside the other: every direction of one effect mimicked
    by the other, not just one."""
    qa, _ = _orth(a)
    qb, _ = _orth(b)
    if qa.shape[1] == 0 or qb.shape[1] == 0:
        return np.zeros(1)
    return np.minimum(1.0, np.linalg.svd(qa.T @ qb, compute_uv=False))


VISIBLE_MIN = 1e-6  # visible fraction below which a direction counts as absorbed (untested)


def visible(u, j) -> bool:
    """Whether the columns ``j`` keep a visible fraction >= ``VISIBLE_MIN`` of their energy
    once the nominal basis ``u`` is projected out."""
    return bool(np.sum(project_out(u, j) ** 2) >= VISIBLE_MIN * np.sum(j ** 2))


def signature_directions(j, jt):
    """The coefficient directions an effect's score test uses, their information, and
    :func:`_visibility`'s answer, from the raw signature ``j`` and its projection ``jt``
    (through their information matrices: no factorisation of the ``m`` rows).

    Raw-signature directions (relative singular value above ``NULL_TOL``) whose visible fraction
    ``1 - rho^2`` after the nominal projection is at least ``VISIBLE_MIN``: the generalised
    eigenvectors of ``(J~^T J~, J^T J)``, scaled so that ``D^T J~^T J~ D = diag(w)`` with ``w``
    the visible fractions. Directions below ``VISIBLE_MIN`` are absorbed by the nominal model
    (structurally confounded); what little of them survives the projection is second-order
    physics or round-off, and testing it would let such an effect claim any residual with an
    implausibly large coefficient. The singular values come from the eigenvalues of ``J^T J``:
    a direction without signature reads at most ``sqrt(eps) ~ 1.5e-8`` of the largest there,
    far below ``NULL_TOL``. Returns ``(D (p, k), w (k,), v_min, no-signature directions,
    confounded directions)``.
    """
    p = j.shape[1]
    if p == 1:  # one column: its norms say it all
        return _column_directions(float(np.sum(j * j)), float(np.sum(jt * jt)))
    lam, v = np.linalg.eigh(j.T @ j)
    s, v = np.sqrt(np.clip(lam[::-1], 0.0, None)), v[:, ::-1]  # largest first, as an SVD's
    if p == 0 or s[0] == 0:
        return np.zeros((p, 0)), np.zeros(0), 0.0, [v[:, i] for i in range(p)], []
    keep = s > NULL_TOL * s[0]
    null = [v[:, i] for i in range(p) if not keep[i]]
    vr = v[:, keep] / s[keep]  # J vr has orthonormal columns
    b = jt @ vr
    w, evec = np.linalg.eigh(b.T @ b)
    dirs = vr @ evec
    k = w >= VISIBLE_MIN
    w_vis = np.clip(w, 0.0, 1.0)
    confounded = [dirs[:, i] / np.linalg.norm(dirs[:, i]) for i in range(len(w))
                  if w_vis[i] < 1e-6]
    return dirs[:, k], w[k], float(w_vis[0]), null, confounded


def _column_directions(ss: float, ss_t: float):
    """:func:`signature_directions` of a one-column signature with squared norm ``ss`` (``ss_t`` after
    the projection): its direction is the coefficient itself, ``w = ss_t / ss``."""
    if ss <= 0.0:
        return np.zeros((1, 0)), np.zeros(0), 0.0, [np.ones(1)], []
    w = ss_t / ss
    d = np.full((1, 1), 1.0 / math.sqrt(ss))
    conf = [np.ones(1)] if w < 1e-6 else []
    ok = w >= VISIBLE_MIN
    return (d if ok else np.zeros((1, 0))), np.array([w] if ok else []), \
        min(max(w, 0.0), 1.0), [], conf


def _visibility(j, u):
    """Visible fraction of an effect's signature and its invisible directions.

    Raw directions (in the effect's coefficients) with relative singular value <= ``NULL_TOL``
    have no signature at all; on the rest, the generalised eigenproblem
    ``(J~^T J~, J^T J)`` gives each direction's visible fraction ``1 - rho^2``. Returns
    ``(v_min, no-signature directions, structurally confounded directions (v < 1e-6))``.
    """
    return signature_directions(j, project_out(u, j))[2:]


def visibility_flag(v: float, has_null: bool, visible_dims: int, n_confounded: int = 0) -> str:
    if visible_dims == 0:
        return "no signature"
    if v < 1e-6:
        return ("partly structurally confounded" if n_confounded < visible_dims
                else "structurally confounded")
    if v < 0.05:
        return "practically confounded"
    if v < 0.2:
        return "weakly identifiable"
    return "partly no signature" if has_null else "visible"


def chi2_sf(x, dof):
    """``scipy.stats.chi2.sf(x, dof)`` without its per-call overhead (~80 us against ~1 us):
    the same special function (``chdtrc``); ``x`` below 0 gives 1, as the distribution's does."""
    out = special.chdtrc(dof, np.maximum(x, 0.0))
    return float(out) if np.ndim(out) == 0 else out
