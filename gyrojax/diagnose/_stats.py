"""The statistics of the gap diagnosis, rig-agnostic (spec gap-diagnosis §4.2-4.3).

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
from scipy import special, stats

__all__ = ["Signature", "Screen", "screen", "bh_qvalues", "gap_map_cells", "canonical_correlation"]

LAMBDA_80 = 7.85  # noncentrality giving 80 % power at alpha = 0.05, 1 dof
SEPARABLE = 0.9  # spec §5.6: separable = largest projected canonical correlation <= this
INDISTINGUISHABLE = 0.98  # spec §4.2 stage 3: pairs at or above "cannot be told apart"
NULL_TOL = 1e-6  # relative singular value of a raw signature direction counted as no signature
PRIORS = ("design", "shape", "zellner", "scale", "shell")  # Bayes-factor priors (see screen)
SHELL_RANGE = (8.0, 2.0 ** 24)  # the shell prior's noncentralities, log-uniform (see screen)


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
    interior values at most 5 % of the record apart (spec §6 G8 asks onsets within one such
    window) and at least 8 of them; in ``t``'s units."""
    t = np.asarray(t, float)
    span = t[n_train - 1] - t[0]
    n_int = max(9, math.ceil(span / (0.05 * (t[-1] - t[0])) - 1e-9))
    return t[0] + span * np.arange(1, n_int) / n_int


def chi2_sf(x, dof):
    """``scipy.stats.chi2.sf(x, dof)`` without its per-call overhead (~80 us against ~1 us):
    the same special function (``chdtrc``); ``x`` below 0 gives 1, as the distribution's does."""
    out = special.chdtrc(dof, np.maximum(x, 0.0))
    return float(out) if np.ndim(out) == 0 else out


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
    """Spec §4.2 stage 3: the effects ``names`` merged into classes by their pairs at projected
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


def _lm(jt, e, raw_scale, rtol=1e-10):
    """Score statistic, its dof, the one-step estimate and its covariance (pseudo-inverse over
    the information's eigenvalues above ``rtol * raw_scale``)."""
    info = jt.T @ jt
    s = jt.T @ e
    w, v = np.linalg.eigh(info)
    keep = w > rtol * max(raw_scale, 1e-300)
    winv = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
    cov = (v * winv) @ v.T
    return float(s @ cov @ s), int(keep.sum()), cov @ s, cov, info, s


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


def grid_log_bf(lms, dofs, lambda0) -> float:
    """Zellner g-prior Bayes factor (log) of a grid effect: the score Bayes factor under the
    design-relative prior ``b ~ N(0, g I^-1)`` with ``g = lambda0 / dof`` at each
    grid value (score ``lms[g]`` on ``dofs[g]`` dof; 0 dof: factor 1), averaged over the grid
    with equal weights. The prior expects noncentrality ``lambda0`` whatever the effect's units,
    so over-flexible effects pay ``dof/2 log(1 + g)`` and no prior scale can tilt it."""
    return float(_grid_log_bf(np.asarray(lms, float)[:, None], dofs, lambda0)[0])


def _log_bf(info, s):
    p = info.shape[0]
    a = info + np.eye(p)
    _, logdet = np.linalg.slogdet(a)
    return 0.5 * float(s @ np.linalg.solve(a, s)) - 0.5 * logdet


def shape_log_bf(jts, e, lambdas) -> np.ndarray:
    """Shape-prior Bayes factors (log) of one effect at each prior size in ``lambdas``.

    ``jts``: the effect's projected whitened Jacobians ``J~_g`` (one per grid value, columns per
    unit prior scale); ``e``: the whitened residual. At each grid value the coefficients get
    ``b ~ N(0, c^2 I)`` in prior-scale units -- the prior scales' *shape* (coefficients independent,
    spread in proportion to their prior scales) -- with ``c^2 = lambda / tr(J~^T J~)`` so that the
    expected noncentrality ``E[b^T I b]`` is ``lambda`` on this design. Then (exact for the
    linearised model) ``log BF = s'^T (I' + 1)^-1 s' / 2 - log det(I' + 1) / 2`` with
    ``I' = c^2 J~^T J~``, ``s' = c J~^T e``; a grid effect averages the factors over its grid
    with equal weights. Unlike a g-prior (``b ~ N(0, g I^-1)``), the prior does not give the
    directions the design sees worst -- those shared with other effects -- the largest
    coefficients. Returns ``(len(lambdas),)``, or ``(len(lambdas), B)`` for ``B`` residuals
    ``e`` ``(m, B)``; an effect without signature gets 0."""
    e = np.asarray(e, float)
    return shape_log_bf_scores([(jt.T @ jt, jt.T @ e) for jt in jts], lambdas)


def shape_log_bf_scores(blocks, lambdas) -> np.ndarray:
    """:func:`shape_log_bf` from each grid value's information ``J~^T J~`` and score
    ``J~^T e`` (``(p,)`` or ``(p, B)``): ``blocks`` is a list of ``(info, score)`` pairs. A refit
    that estimates ``b^`` gives the same factor with ``score = info @ b^`` (exact when the
    model is linear)."""
    out = _shape_log_bf_grid(blocks, lambdas)
    return np.logaddexp.reduce(out, axis=0) - math.log(out.shape[0])


def _info_eig(info):
    """``(trace, eigenvalues clipped at 0, eigenvectors)`` of an information matrix."""
    if info.shape == (1, 1):  # one coefficient: its information is its eigenvalue
        x = float(info[0, 0])
        return x, np.array([max(x, 0.0)]), np.ones((1, 1))
    w, v = np.linalg.eigh((info + info.T) / 2)
    return float(np.trace(info)), np.clip(w, 0.0, None), v


def _shape_log_bf_grid(blocks, lambdas, eigs=None) -> np.ndarray:
    """:func:`shape_log_bf_scores` at each grid value, before the grid average:
    ``(G, len(lambdas), ...)``; ``eigs``: each block's :func:`_info_eig`, where the caller has
    them."""
    lambdas = np.atleast_1d(np.asarray(lambdas, float))
    out = []
    for k, (info, score) in enumerate(blocks):
        score = np.asarray(score, float)
        tr, w, v = eigs[k] if eigs is not None else _info_eig(info)
        if tr <= 0.0:
            out.append(np.zeros((lambdas.size,) + score.shape[1:]))
            continue
        z2 = (v.T @ score) ** 2  # squared scores in the information's eigenbasis
        c2w = lambdas[:, None] / tr * w  # (L, p)
        fit = np.tensordot(c2w / np.where(w > 0, w, 1.0) / (1 + c2w), z2, axes=(1, 0))
        out.append(0.5 * fit - 0.5 * np.sum(np.log1p(c2w), axis=1).reshape(
            (-1,) + (1,) * (score.ndim - 1)))
    return np.asarray(out)


def zellner_log_bf(lms, dofs, lambdas) -> np.ndarray:
    """:func:`grid_log_bf` at each prior size in ``lambdas``: ``lms`` ``(G,)`` or ``(G, B)``
    -> ``(len(lambdas),)`` or ``(len(lambdas), B)``."""
    lms = np.asarray(lms, float)
    flat = lms.reshape(lms.shape[0], -1)  # (G, B)
    dofs = np.asarray(dofs, float)
    g = np.atleast_1d(np.asarray(lambdas, float))[:, None] / np.maximum(dofs, 1.0)  # (L, G)
    lbf = 0.5 * (g / (1 + g))[:, :, None] * flat[None] - 0.5 * (dofs * np.log1p(g))[:, :, None]
    lbf = np.where(dofs[None, :, None] > 0, lbf, 0.0)
    out = np.logaddexp.reduce(lbf, axis=1) - math.log(flat.shape[0])  # all sizes at once
    return out.reshape((out.shape[0],) + lms.shape[1:])


def noncentral_log_bf(lms, dofs, lambdas) -> np.ndarray:
    """Log Bayes factor of a (grid) effect whose noncentrality is exactly ``lambda``, its
    direction uniform over the tested directions: the density ratio of the score statistic,
    noncentral over central chi-square, ``exp(-lambda/2) 0F1(; dof/2; lambda LM / 4)``
    (exact for the linearised model; one dof: ``exp(-lambda/2) cosh(sqrt(lambda LM))``),
    averaged over the grid with equal weights. Its mean under the null is 1 at every
    ``lambda``. ``lms`` ``(G,)`` or ``(G, B)``, ``dofs`` ``(G,)`` -> ``(len(lambdas),)`` or
    ``(len(lambdas), B)``; 0 dof: factor 1.

    Unlike the Gaussian priors (:func:`zellner_log_bf`, :func:`shape_log_bf`), which put most
    of their mass on effects far smaller than ``lambda``, the shell puts none there: at the
    spec's sizes it is the Bayes factor of its validation population (§5.4: noncentrality
    8, 16, 32 or 64, direction uniform), and :func:`shell_log_bf` mixes it over sizes."""
    lms = np.asarray(lms, float)
    flat = np.maximum(lms.reshape(lms.shape[0], -1), 0.0)[None]  # (1, G, B)
    dofs = np.asarray(dofs, float)[None, :, None]
    lam = np.atleast_1d(np.asarray(lambdas, float))[:, None, None]
    nu = np.maximum(dofs, 1.0) / 2 - 1
    y = np.sqrt(lam * flat)
    safe = np.where(y > 1e-8, y, 1.0)
    # 0F1(; nu + 1; y^2 / 4) = Gamma(nu + 1) (y / 2)^-nu I_nu(y), with I_nu scaled by exp(-y)
    log_f = special.gammaln(nu + 1) - nu * np.log(safe / 2) + np.log(special.ive(nu, safe)) + safe
    lbf = -0.5 * lam + np.where(y > 1e-8, log_f, 0.0)
    lbf = np.where(dofs > 0, lbf, 0.0)
    out = np.logaddexp.reduce(lbf, axis=1) - math.log(flat.shape[1])
    return out.reshape((out.shape[0],) + lms.shape[1:])


def shell_log_bf(lms, noncentrality=SHELL_RANGE) -> np.ndarray:
    """Log Bayes factor of an effect of one coefficient whose noncentrality is log-uniform over
    ``noncentrality = (lo, hi)``, at each score ``lms`` (any shape; one dof): the mixture of
    :func:`noncentral_log_bf` over the sizes. With ``s = sqrt(lambda)`` and ``z = sqrt(LM)``,
    ``BF = e^(LM/2) / log(hi/lo) * int (phi(s - z) + phi(s + z)) sqrt(2 pi) / s ds`` over
    ``[sqrt lo, sqrt hi]``: a unit-width bump at ``s = z`` whatever the score, integrated by
    Simpson's rule on 481 points within 12 of it (the rest is below ``e^-72``)."""
    lms = np.maximum(np.asarray(lms, float), 0.0)
    z = np.sqrt(lms)[..., None]
    sa, sb = math.sqrt(noncentrality[0]), math.sqrt(noncentrality[1])
    half = 12.0
    a = np.maximum(sa, np.minimum(z - half, sb - 2 * half))
    b = np.minimum(sb, a + 2 * half)
    t = np.linspace(0.0, 1.0, 481)
    x = a + (b - a) * t  # (..., 481)
    # log of (exp(-(x - z)^2 / 2) + exp(-(x + z)^2 / 2)) / x, stable for large x z
    f = -0.5 * (x - z) ** 2 + np.log1p(np.exp(-2.0 * x * z)) - np.log(x)
    top = f.max(axis=-1, keepdims=True)
    w = np.r_[1.0, np.tile([4.0, 2.0], (t.size - 3) // 2), 4.0, 1.0] * (b - a) / (3 * (t.size - 1))
    integral = top[..., 0] + np.log(np.sum(np.exp(f - top) * w, axis=-1))
    return 0.5 * lms + integral - math.log(math.log(noncentrality[1] / noncentrality[0]))


def design_log_bf(jts, bases, e, lambdas) -> np.ndarray:
    """The screening's default Bayes factor (log) at each prior size in ``lambdas``: the equal
    mixture of the shape prior (:func:`shape_log_bf`: coefficients spread as their prior
    scales) and the g-prior (:func:`grid_log_bf` on the tested directions, bases ``bases``),
    both sized to expect noncentrality ``lambda`` on this design. The shape prior is right when
    the prior scales say how an effect's coefficients compare (ESG: 400 blind cases, ECE 0.037,
    the g-prior alone 0.108); the g-prior is invariant to them, so the mixture stays sound when
    they do not (an IMU drift drawn without regard to them: shape prior alone top-1 0.33, the
    mixture 0.66, the g-prior 0.68). Shapes as :func:`shape_log_bf`."""
    e = np.asarray(e, float)
    lms = np.stack([np.sum((b.T @ e) ** 2, axis=0) for b in bases])
    return mix_log_bf(shape_log_bf(jts, e, lambdas),
                      zellner_log_bf(lms, [b.shape[1] for b in bases], lambdas))


def mix_log_bf(shape, zellner):
    """The design prior's log Bayes factor from its two parts' (the equal mixture)."""
    return np.logaddexp(shape, zellner) - math.log(2)


@dataclasses.dataclass
class Screen:
    """Screening result of one effect (see :func:`screen`)."""

    sig: Signature
    lm: float
    dof: int
    p: float
    log_bf: float
    grid_index: int
    beta: np.ndarray  # one-step estimate, prior-scale units
    beta_se: np.ndarray
    visible_fraction: float
    flag: str
    null_directions: list  # coefficient vectors of raw-signature null directions
    confounded_directions: list  # directions whose signature the nominal span absorbs (v < 1e-6)
    alias: np.ndarray  # (p_nominal, p_effect), nominal scale units per prior-scale unit
    alias_std: np.ndarray  # the same in the nominal parameters' standard errors
    projected: np.ndarray  # J~ at the chosen grid value
    lm_grid: np.ndarray
    dof_grid: np.ndarray  # tested dof at each grid value (visible directions differ along a grid)
    log_bf_curve: dict = dataclasses.field(default_factory=dict)  # design prior, per size
    posterior: float = 0.0
    # grid value of the visibility, flag, aliases and hidden directions: the posterior median of
    # the visible fraction over the grid (see :func:`screen`); ``grid_index`` without a grid
    vis_index: int = 0
    grid_weights: np.ndarray | None = None  # posterior over the grid values (grid effects only)
    q: float | None = None  # weighted-BH q-value, set by the pipeline


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


@dataclasses.dataclass
class SignatureDesign:
    """The data-independent part of one signature's score test (see :func:`screen_designs`).

    - `jt`, `d`, `w`: per grid value, the projected Jacobian ``J~``, the tested directions and
      their information (:func:`signature_directions`);
    - `bases`: per grid value, the orthonormal basis ``J~ D / sqrt(w)`` of the tested directions
      (``LM_g = |W_g^T e|^2``);
    - `sup_null`: for grid effects, the bootstrap draws of ``sup_g LM_g`` under H0 (sorted);
    - `vis`: per grid value, :func:`_visibility`'s ``(v_min, no-signature directions,
      confounded directions)``;
    - `infos`: per grid value, the information ``J~^T J~`` (`info_eigs`: its
      :func:`_info_eig`); `stacked`: the bases side by side.
    """

    sig: Signature
    jt: list
    d: list
    w: list
    bases: list
    sup_null: np.ndarray | None
    vis: list
    infos: list | None = None  # per grid value, J~^T J~ (computed when not given)

    def __post_init__(self):
        if self.infos is None:
            self.infos = [x.T @ x for x in self.jt]
        self.info_eigs = [_info_eig(x) for x in self.infos]  # the shape prior's, once
        self.ks = np.array([b.shape[1] for b in self.bases], int)
        # the grid values' bases side by side: ``e`` is read once by one product
        self.stacked = (self.bases[0] if len(self.bases) == 1 else
                        np.concatenate(self.bases, axis=1) if self.bases else np.zeros((0, 0)))


def screen_designs(jn: np.ndarray, sigs: list[Signature], *, n_boot: int = 2000,
                   seed: int = 0) -> tuple[np.ndarray, list[SignatureDesign]]:
    """The nominal basis ``U`` and each signature's :class:`SignatureDesign`: everything of the
    score tests that does not depend on the residual, so that many residuals (the observed one,
    and the null draws of the calibrated global test) are scored by matrix products."""
    u = nominal_basis(jn)
    rng = np.random.default_rng(seed)
    blocks = [(i, g) for i, sig in enumerate(sigs) for g in range(sig.jac.shape[0])]
    # one-column signatures are projected together (one product) and their directions read
    # off the column norms; wider ones block by block, where each copy stays small
    ones = [b for b in blocks if sigs[b[0]].jac.shape[2] == 1]
    part = {}
    if ones:
        j = np.stack([sigs[i].jac[g][:, 0] for i, g in ones])  # (n, m): one row each
        jt = j - (j @ u) @ u.T
        for b, row, ss, ss_t in zip(ones, jt, np.sum(j * j, axis=1), np.sum(jt * jt, axis=1)):
            part[b] = (row[:, None], _column_directions(float(ss), float(ss_t)))
    out = []
    for i, sig in enumerate(sigs):
        jts, ds, ws, bases, vis, infos = [], [], [], [], [], []
        for g in range(sig.jac.shape[0]):
            if (i, g) in part:
                jt, (d, w, *v) = part[(i, g)]
            else:
                j = sig.jac[g]
                jt = project_out(u, j)
                d, w, *v = signature_directions(j, jt)
            jts.append(jt)
            infos.append(jt.T @ jt)
            ds.append(d)
            ws.append(w)
            vis.append(tuple(v))
            bases.append(jt @ (d / np.sqrt(w)) if w.size else np.zeros((jt.shape[0], 0)))
        sup = _sup_null(bases, n_boot, rng) if len(bases) > 1 else None
        out.append(SignatureDesign(sig, jts, ds, ws, bases, sup, vis, infos))
    return u, out


def _grid_lm(design: SignatureDesign, e: np.ndarray) -> np.ndarray:
    """Score statistics ``(G, ...)`` at every grid value for residual(s) ``e`` (``m`` or
    ``m x B``).

    The grid values' bases are stacked into one ``m x sum(k_g)`` matrix, so that ``e`` is read
    once by one matrix product instead of once per grid value (a grid effect has 8-15 values of
    1-3 columns each, and the calibrated global test scores ~500 residuals at once)."""
    ks = design.ks
    sq = (design.stacked.T @ e) ** 2
    out = np.zeros((len(ks), *sq.shape[1:]))
    full = ks > 0
    if full.any():
        starts = np.concatenate([[0], np.cumsum(ks)[:-1]])[full]
        out[full] = np.add.reduceat(sq, starts, axis=0)
    return out


def _grid_log_bf(lms, dofs, lambda0):
    """:func:`grid_log_bf` for many residuals: ``lms`` ``(G, B)``, ``dofs`` ``(G,)`` -> ``(B,)``;
    ``log BF_g = g / (1 + g) LM_g / 2 - dof_g log(1 + g) / 2``."""
    dofs = np.asarray(dofs, float)
    g = lambda0 / np.maximum(dofs, 1.0)
    lbf = 0.5 * (g / (1 + g))[:, None] * np.asarray(lms, float) - 0.5 * (
        dofs * np.log1p(g))[:, None]
    lbf = np.where(dofs[:, None] > 0, lbf, 0.0)
    return np.logaddexp.reduce(lbf, axis=0) - math.log(lbf.shape[0])


def _pvalue(design: SignatureDesign, lm, dof):
    """p-value of the (sup-)score ``lm`` (array) with ``dof`` tested directions at its grid value."""
    lm, dof = np.asarray(lm, float), np.asarray(dof)
    if design.sup_null is None:
        p = chi2_sf(lm, np.maximum(dof, 1))
    else:
        p = _smooth_bootstrap_p(design.sup_null, lm, len(design.bases), np.maximum(dof, 1))
    return np.where(dof == 0, 1.0, p)


def _smooth_bootstrap_p(sup, lm, n_grid, dof):
    """Bootstrap p-value ``P(sup >= lm)`` from the sorted draws ``sup``, made continuous in
    ``lm``: ``(1 + #{sup >= lm} + f) / (1 + B)`` with ``f`` the linear position of ``lm`` between
    its neighbouring draws, and beyond the largest draw the Bonferroni tail of the grid
    (``n_grid chi2.sf(lm, dof)``) scaled to meet ``1 / (1 + B)`` there. The raw count has
    atoms at multiples of ``1 / (1 + B)``, which make the smallest q-value discrete and the
    calibrated global test (:func:`gyrojax.diagnose._diagnose._calibrated_level`) conservative
    at ties; the smooth version keeps the same values at the draws."""
    n_boot = sup.size
    lm = np.asarray(lm, float)
    idx = np.searchsorted(sup, lm, side="left")  # first draw >= lm
    count = n_boot - idx
    hi = sup[np.minimum(idx, n_boot - 1)]
    lo = sup[np.maximum(idx - 1, 0)]
    frac = np.where((idx > 0) & (idx < n_boot) & (hi > lo), (hi - lm) / np.where(hi > lo,
                                                                                hi - lo, 1.0), 0.0)
    p = (1 + count + frac) / (1 + n_boot)
    tail = chi2_sf(lm, dof) / np.maximum(chi2_sf(sup[-1], dof), 1e-300)
    p_tail = np.minimum(1.0 / (1 + n_boot) * tail, n_grid * chi2_sf(lm, dof))
    return np.where(idx >= n_boot, p_tail, np.minimum(p, 1.0))


def library_pvalues(designs: list[SignatureDesign], e: np.ndarray) -> np.ndarray:
    """The screening p-values of every signature for residuals ``e`` (``m x B``): ``(K, B)``."""
    rows = []
    for des in designs:
        lms = _grid_lm(des, e)
        gi = np.argmax(lms, axis=0)
        dofs = np.array([w.size for w in des.w])
        rows.append(_pvalue(des, lms[gi, np.arange(lms.shape[1])], dofs[gi]))
    return np.array(rows).reshape(len(designs), e.shape[1])


PRIOR_LAMBDAS = tuple(2.0 ** k for k in range(11))  # prior sizes of the evidence curve, 1-1024


def screen(e: np.ndarray, jn: np.ndarray, sigs: list[Signature], *, n_boot: int = 2000,
           seed: int = 0, prior_none: float = 0.5, prior: str = "design",
           lambda0: float = 32.0, designs=None) -> list[Screen]:
    """Efficient-score screening of every signature against the residual ``e`` (whitened).

    ``jn``: whitened nominal Jacobian (``m x p``, columns per nominal scale). Grid effects get the
    sup over their grid with a bootstrap p-value from ``n_boot`` draws (seeded). Posteriors use
    prior probability ``prior_none`` for "no effect" and the rest shared equally by the effects
    with a signature (an effect without one gets posterior 0: :func:`_posteriors`); the Bayes factor
    uses ``prior="design"`` (the default, :func:`design_log_bf`: the equal mixture of the two
    next, both expecting noncentrality ``lambda0``), ``prior="shape"`` (the prior scales' shape,
    :func:`shape_log_bf`), ``prior="zellner"`` (the g-prior ``b ~ N(0, g I^-1)``,
    ``g = lambda0 / dof``, on the tested directions: :func:`grid_log_bf`) or ``prior="scale"``
    (``b ~ N(0, prior_scale^2)``, spec §4.2 step 5) or ``prior="shell"`` (the noncentrality
    log-uniform over :data:`SHELL_RANGE`, not fixed: an effect of one coefficient gets the
    exact factor, :func:`shell_log_bf`; any other the design prior's mixed over the same sizes,
    :func:`_shell_grid`). Each row also carries ``log_bf_curve``, the
    design prior's factor at the sizes ``PRIOR_LAMBDAS`` (how the evidence depends on the prior
    size). ``designs``: the output of :func:`screen_designs` for these ``jn`` and ``sigs``
    (computed here when not given).

    A grid effect's score, one-step estimate and refit take the grid value of the largest score;
    its visible fraction, flag, aliases and hidden directions take the posterior median of the
    visible fraction over the grid (:func:`grid_posterior`): the flag the posterior over the grid
    favours. At the largest score, a weak effect's flag would follow the noise that picks it (on
    the gyrotheodolite a drift transient's visible fraction spans 0.04-0.21 over its decay
    times); with a clear signal the posterior settles on one grid value and the two agree.
    """
    if prior not in PRIORS:
        raise ValueError(f"prior={prior!r}; use one of {', '.join(map(repr, PRIORS))}")
    u, designs = designs if designs is not None else screen_designs(jn, sigs, n_boot=n_boot,
                                                                    seed=seed)
    cov_n = np.linalg.pinv(jn.T @ jn)
    se_n = np.sqrt(np.maximum(np.diag(cov_n), 1e-300))
    out = []
    for des in designs:
        sig = des.sig
        lms = [float(x) for x in _grid_lm(des, e)]
        dofs = [w.size for w in des.w]
        gi = int(np.argmax(lms))
        jt, d, w, dof = des.jt[gi], des.d[gi], des.w[gi], dofs[gi]
        scores = [x.T @ e for x in des.jt]  # J~^T e per grid value
        sd = d.T @ scores[gi]
        beta = d @ (sd / w) if w.size else np.zeros(jt.shape[1])
        cov = (d / w) @ d.T if w.size else np.zeros((jt.shape[1], jt.shape[1]))
        lams = PRIOR_LAMBDAS + (lambda0,)
        shape_grid = _shape_log_bf_grid(list(zip(des.infos, scores)), lams,
                                        des.info_eigs)  # (G, L)
        shape = np.logaddexp.reduce(shape_grid, axis=0) - math.log(shape_grid.shape[0])
        zell = zellner_log_bf(lms, dofs, lams)
        curve = mix_log_bf(shape, zell)
        if prior == "scale":
            lbf = [_log_bf(info, sc) for info, sc in zip(des.infos, scores)]
            log_bf = float(np.logaddexp.reduce(lbf) - math.log(len(lbf)))
        elif prior == "shell":
            lbf = _shell_grid(des, scores, lms, dofs)
            log_bf = float(np.logaddexp.reduce(lbf) - math.log(len(lbf)))
        else:
            log_bf = float({"design": curve, "shape": shape, "zellner": zell}[prior][-1])
        p = float(_pvalue(des, lms[gi], dof))
        gw = None if len(des.vis) == 1 else grid_posterior(des, e, lms, dofs, lambda0, prior,
                                                            shape=shape_grid[:, -1])
        gv = gi if gw is None else _median_index([x[0] for x in des.vis], gw)
        v, null, conf = des.vis[gv]
        flag = visibility_flag(v, bool(null), sig.jac.shape[2] - len(null), len(conf))
        alias = cov_n @ (jn.T @ sig.jac[gv])
        alias_std = alias / se_n[:, None]
        out.append(Screen(sig, lms[gi], dof, p, log_bf, gi, beta, np.sqrt(np.diag(cov)), v, flag,
                          null, conf, alias, alias_std, jt, np.asarray(lms), np.asarray(dofs),
                          log_bf_curve=dict(zip(PRIOR_LAMBDAS, map(float, curve[:-1]))),
                          vis_index=gv, grid_weights=gw))
    _posteriors(out, prior_none)
    return out


# the design prior's sizes under prior="shell": powers of 2 over SHELL_RANGE, trapezoid weights in
# log lambda (the Gaussian factors vary slowly with the size, unlike the shell's)
SHELL_DESIGN_LAMBDAS = 2.0 ** np.arange(math.log2(SHELL_RANGE[0]), math.log2(SHELL_RANGE[1]) + 1)
_SHELL_DESIGN_LOGW = np.log(np.r_[0.5, np.ones(len(SHELL_DESIGN_LAMBDAS) - 2), 0.5]
                            / (len(SHELL_DESIGN_LAMBDAS) - 1))


def shell_design_log_bf(shape, zell) -> np.ndarray:
    """``prior="shell"`` for an effect of more than one coefficient: the design prior (the
    equal mixture of the ``shape`` and ``zell`` log factors, each given at the sizes
    :data:`SHELL_DESIGN_LAMBDAS` on the last axis) averaged over those sizes."""
    return np.logaddexp.reduce(mix_log_bf(shape, zell) + _SHELL_DESIGN_LOGW, axis=-1)


def _shell_grid(design: SignatureDesign, scores, lms, dofs) -> np.ndarray:
    """``prior="shell"``'s log factor at each grid value of one effect (:func:`screen`): the
    noncentrality log-uniform over :data:`SHELL_RANGE`. An effect of one coefficient (the
    shape and the g-prior are one prior there) gets :func:`shell_log_bf`, the exact factor;
    any other the design prior's (:func:`design_log_bf`) averaged over the same sizes, which
    keeps its spread of the coefficients' directions (the shell would have to assume one).
    ``scores``: ``J~^T e`` per grid value."""
    lms, dofs = np.asarray(lms, float), np.asarray(dofs, float)
    if design.sig.jac.shape[2] == 1:
        return np.where(dofs > 0, shell_log_bf(lms), 0.0)
    lams = SHELL_DESIGN_LAMBDAS
    shape = _shape_log_bf_grid(list(zip(design.infos, scores)), lams, design.info_eigs)  # (G, L)
    g = lams[None, :] / np.maximum(dofs, 1.0)[:, None]
    zell = np.where(dofs[:, None] > 0, 0.5 * g / (1 + g) * lms[:, None]
                    - 0.5 * dofs[:, None] * np.log1p(g), 0.0)
    return shell_design_log_bf(shape, zell)


def grid_posterior(design: SignatureDesign, e, lms, dofs, lambda0: float = 32.0,
                   prior: str = "design", shape=None) -> np.ndarray:
    """Posterior weights of a grid effect's grid values given that the effect is present: each
    value's share of the grid-averaged Bayes factor of :func:`screen`'s ``prior`` (equal prior
    weight per grid value, as that average assumes). ``lms``, ``dofs``: the score and its dof at
    each grid value for the residual ``e``; ``shape``: the shape prior's log factor at each grid
    value at ``lambda0``, where the caller has it."""
    if prior == "scale":
        lbf = np.array([_log_bf(x.T @ x, x.T @ e) for x in design.jt])
    else:
        if shape is None:
            shape = np.array([shape_log_bf([jt], e, [lambda0])[0] for jt in design.jt])
        if prior == "shell":
            lbf = _shell_grid(design, [x.T @ e for x in design.jt], lms, dofs)
        else:
            zell = np.array([zellner_log_bf([lm], [d], [lambda0])[0]
                             for lm, d in zip(lms, dofs)])
            lbf = {"design": mix_log_bf(shape, zell), "shape": shape, "zellner": zell}[prior]
    return np.exp(lbf - np.logaddexp.reduce(lbf))


def _median_index(values, weights) -> int:
    """Index of the weighted median of ``values``: the first, in increasing order, at which the
    cumulative weight reaches half."""
    order = np.argsort(np.asarray(values, float), kind="stable")
    cum = np.cumsum(np.asarray(weights, float)[order])
    return int(order[min(np.searchsorted(cum, 0.5 * cum[-1]), len(order) - 1)])


def _sup_null(bases, n_boot, rng):
    """Draws of ``sup_g LM_g`` under H0 (sorted), by Monte Carlo over the joint law of the scores.

    Each grid value's standardised score is ``t_g = W_g^T z`` with ``W_g`` the orthonormal basis
    of its tested directions (already orthogonal to the nominal span) and ``z ~ N(0, I_m)``; so
    the stacked scores are ``N(0, W^T W)`` and are drawn in that small space (``sum_g dof_g``
    dimensions) instead of drawing ``m``-vectors: the same law at a fraction of the cost.
    """
    if sum(b.shape[1] for b in bases) == 0:
        return np.full(n_boot, 0.0)
    sup = np.zeros(n_boot)
    for tb in score_draws(bases, n_boot, rng):
        sup = np.maximum(sup, np.sum(tb * tb, axis=0))
    return np.sort(sup)


def score_draws(bases, n: int, rng) -> list[np.ndarray]:
    """``n`` joint null draws of the standardised scores ``W_g^T z`` (``z ~ N(0, I_m)``) of
    every orthonormal basis in ``bases``, drawn in their own small space: the stacked scores are
    ``N(0, W^T W)`` with ``W`` the bases side by side. Returns one ``(dof_g, n)`` block per
    basis."""
    w = np.concatenate(bases, axis=1)
    gram = w.T @ w
    ev, evec = np.linalg.eigh((gram + gram.T) / 2)
    root = evec * np.sqrt(np.clip(ev, 0.0, None))  # gram = root root^T
    t = root @ rng.standard_normal((w.shape[1], n))
    edges = np.cumsum([0] + [b.shape[1] for b in bases])
    return [t[a:b] for a, b in zip(edges[:-1], edges[1:])]


def _sup_pvalue(bases, observed, n_boot, rng):
    """P(sup_g LM_g >= observed) under H0 from :func:`_sup_null`'s draws."""
    if sum(b.shape[1] for b in bases) == 0:
        return 1.0
    sup = _sup_null(bases, n_boot, rng)
    return float((1 + np.sum(sup >= observed)) / (1 + n_boot))


def has_signature(row: Screen) -> bool:
    """Whether an effect has a tested direction at some grid value: one whose signature the
    nominal fit absorbs whole (or that has none on the bench) cannot make a gap."""
    return bool(np.any(np.asarray(row.dof_grid) > 0))


def _posteriors(rows, prior_none):
    """Posterior of each effect: prior ``prior_none`` for "no effect", the rest shared equally
    by the effects with a signature (:func:`has_signature`). An effect without one leaves the
    data as likely as no effect (Bayes factor 1 whatever the record): it is part of "no gap",
    not a candidate cause of one, and gets posterior 0. Given the prior share, its factor of 1
    took mass from every visible effect: on the IMU's still stand, whose nine gyro scale
    factors and misalignments have no signature, the top posterior's ECE went 0.095 -> 0.057
    and the 90 % sets shrank (docs/notes.md, stop 72)."""
    for r in rows:
        r.posterior = 0.0
    seen = [r for r in rows if has_signature(r)]
    if not seen:
        return 1.0
    logs = np.array([math.log(prior_none)] + [math.log((1 - prior_none) / len(seen)) + r.log_bf
                                              for r in seen])
    post = np.exp(logs - np.logaddexp.reduce(logs))
    for r, pk in zip(seen, post[1:]):
        r.posterior = float(pk)
    return float(post[0])


def ambiguity_set(rows: list[Screen], mass: float = 0.9) -> list[Screen]:
    """Smallest set of effects holding ``mass`` of the posterior given that some effect is
    present (effects without a signature hold none: :func:`_posteriors`)."""
    order = sorted((r for r in rows if has_signature(r)), key=lambda r: -r.posterior)
    total = sum(r.posterior for r in order) or 1.0
    chosen, acc = [], 0.0
    for r in order:
        chosen.append(r)
        acc += r.posterior / total
        if acc >= mass:
            break
    return chosen


def bh_qvalues(p: np.ndarray, weights=None) -> np.ndarray:
    """Benjamini-Hochberg q-values; with ``weights`` (positive, rescaled to mean 1) the weighted
    procedure of Genovese, Roeder & Wasserman (2006), BH on ``p / w``, which keeps the FDR at
    the level for weights fixed before the data are seen. ``p`` may be ``(..., n)``: one family
    per row (the calibrated level's null draws)."""
    p = np.asarray(p, float)
    n = p.shape[-1]
    if n == 0:
        return p
    if weights is not None:
        w = np.asarray(weights, float)
        if w.shape != p.shape[-1:] or np.any(w <= 0):
            raise ValueError(f"BH weights must be positive, one per p-value; got {w}")
        p = p / (w / w.mean())
    order = np.argsort(p, axis=-1)
    q = np.take_along_axis(p, order, axis=-1) * n / np.arange(1, n + 1)
    q = np.flip(np.minimum.accumulate(np.flip(q, -1), axis=-1), -1)
    out = np.empty_like(q)
    np.put_along_axis(out, order, np.minimum(q, 1.0), axis=-1)
    return out


def fisher_g_pvalue(g, q: int):
    """P(Fisher's g >= g) for ``q`` periodogram ordinates of white noise (exact series,
    ``sum_j (-1)^(j-1) C(q, j) (1 - j g)^(q-1)`` over ``j g < 1``); ``g`` a float or an array.

    The terms grow huge when ``g`` is far below its null typical value ``~ln(q)/q`` and the
    alternating sum then cancels to noise (it returned 0 at ``g = 0.003, q = 539``); there the
    p-value is 1 to many digits and is returned as such (largest term above ``1e6``).
    """
    scalar = np.ndim(g) == 0
    g = np.atleast_1d(np.asarray(g, float))
    if q < 2:
        p = np.ones_like(g)
        return float(p[0]) if scalar else p
    jmax = int(min(q, np.floor(1.0 / max(float(g.min()), 1.0 / q))))
    j = np.arange(1, jmax + 1, dtype=float)
    logc = special.gammaln(q + 1) - special.gammaln(j + 1) - special.gammaln(q - j + 1)
    x = 1.0 - j[None, :] * g[:, None]
    # capped at 1e7: a term beyond 1e6 makes p 1 below, so the cap changes no p-value, and an
    # uncapped exp overflowed (a RuntimeWarning on the user's terminal) once C(q, j) or a term
    # passed float64's range (q ~ 1000 and up: the Schuler test's 1-s records)
    expo = logc + (q - 1) * np.log(np.where(x > 0, x, 1.0))
    term = np.where(x > 0, np.exp(np.minimum(expo, np.log(1e7))), 0.0)
    total = np.sum(np.where(j % 2 == 1, 1.0, -1.0) * term, axis=1)
    p = np.where(term.max(axis=1) > 1e6, 1.0, np.clip(total, 0.0, 1.0))
    return float(p[0]) if scalar else p


@dataclasses.dataclass
class MapDesign:
    """The data-independent part of the gap map (:func:`map_design`): its cells, in order, and
    what each needs to be evaluated on a residual."""

    n: int
    c: int
    t: np.ndarray
    channels: tuple
    noise_dof: float
    windows: list  # (level, k, a, b, channel, expected)
    score_cells: list  # (axis, label, channel, basis J~ (n c, k), cov (k, k), dof, info dict)
    tau_cells: list  # (m, clusters, channel, mean, scale g, edf h)
    fisher: bool
    overlapping: bool = True  # the tau cells' Allan form (fully overlapping or not)

    @property
    def n_cells(self) -> int:
        return (len(self.windows) + len(self.score_cells) + len(self.tau_cells)
                + (self.c if self.fisher else 0))


def _score_cell(u, cols, *, min_visible=VISIBLE_MIN):
    """Projected basis, pseudo-inverse information and dof of a score cell with raw columns
    ``cols`` (``n c x k``): directions whose visible fraction after projecting out ``u`` is
    below ``min_visible`` are absorbed (not tested)."""
    jt = project_out(u, cols)
    _, dof, _, cov, _, _ = _lm(jt, np.zeros(len(cols)), float(np.max(np.sum(cols ** 2, 0))),
                               rtol=min_visible)
    return jt, cov, dof


def _channel_columns(w, ch, c):
    """Columns ``w`` (``n x k``) placed on channel ``ch`` of ``n x c`` rows, flattened."""
    cols = np.zeros((w.shape[0], c, w.shape[1]))
    cols[:, ch, :] = w
    return cols.reshape(-1, w.shape[1])


def tau_band_moments(u, n: int, c: int, ch: int, m: int):
    """Null mean and variance of the Allan quadratic form ``Q = sum_k (S_k+1 - S_k)^2 / (2 m)``
    (``S_k``: sums of ``K = n // m`` consecutive clusters of ``m`` samples of channel ``ch``) of
    a unit white residual with the span ``u`` (orthonormal, ``n c`` rows) projected out:
    ``Q = z' (I - P) M' M (I - P) z``, so ``E Q = tr T`` and ``var Q = 2 tr T^2`` with
    ``T = M (I - P) M' = M M' - (M u)(M u)'`` and ``M M'`` the tridiagonal (1, -1/2)."""
    k = n // m
    uc = u.reshape(n, c, -1)[: k * m, ch, :]
    mu = np.diff(uc.reshape(k, m, -1).sum(1), axis=0) / np.sqrt(2 * m)  # (K-1, p)
    # with A = M M' and B = (M u)(M u)': tr T = tr A - tr B and
    # tr T^2 = |A|_F^2 - 2 <A, B> + |mu' mu|_F^2, <A, B> = tr B - sum_i mu_i . mu_i+1
    tr_b = float(np.sum(mu * mu))
    ab = tr_b - float(np.sum(mu[1:] * mu[:-1]))
    tr_a, var_a = white_allan_moments(k)  # tr A and 2 |A|_F^2
    g = mu.T @ mu
    return tr_a - tr_b, var_a + 2 * (-2 * ab + float(np.sum(g * g)))


def map_design(t: np.ndarray, channels: tuple[str, ...], *, n_params: int, noise_dof: float,
               lines: dict[str, float], jn: np.ndarray, min_window: int = 16,
               levels: int = 5, segments=None, nuisance=None, min_clusters: int = 9,
               aux=None, overlapping: bool = True) -> MapDesign:
    """The cells of :func:`gap_map_cells` for ``n = len(t)`` samples of ``channels``.

    ``segments``: the record's test positions, ``[(label, condition, w)]`` with ``w``
    (``n x c``) the whitened per-channel signature of a position offset on the train rows (zero
    off the position); ``nuisance``: whitened columns (``n c x k``) fitted outside ``jn`` (the
    platform's dwell offsets), projected out with it; ``aux``: bins of the record's auxiliary
    channels, ``[(label, aux channel, w)]`` with ``w`` the whitened signature of an offset on the
    rows of one bin (e.g. a temperature range): one 1-dof cell per bin and channel and the joint
    test of one auxiliary channel's bins per channel (axis ``aux``); ``overlapping``: the tau
    cells' Allan form (fully overlapping, or the non-overlapping one of :func:`allan_form`)."""
    n, c = len(t), len(channels)
    frac = 1.0 - n_params / max(n * c, 1)
    windows = []
    for lev in range(levels):
        nw = n >> lev
        if nw < min_window:
            break
        for k in range(1 << lev):
            a, b = k * nw, (k + 1) * nw if k < (1 << lev) - 1 else n
            for ch in range(c):
                windows.append((lev, k, a, b, ch, (b - a) * frac))
    u = nominal_basis(jn if nuisance is None else np.concatenate([jn, nuisance], axis=1))
    score_cells = []
    for name, period in lines.items():
        w = 2 * np.pi / period
        for ch in range(c):
            cols = _channel_columns(np.stack([np.sin(w * t), np.cos(w * t)], 1), ch, c)
            jt, cov, dof = _score_cell(u, cols, min_visible=1e-10)
            score_cells.append(("frequency", f"{name} ({period / 3600:.4g} h)", ch, jt, cov,
                                dof, {"period_s": float(period)}))
    segments = list(segments or [])
    score_cells += _member_cells(u, segments, c, "position", "condition")
    conds = list(dict.fromkeys(cond for _, cond, _ in segments))
    if len(conds) > 1:
        score_cells += _group_cells(u, segments, c, "condition", "positions")
    aux = list(aux or [])
    score_cells += _member_cells(u, aux, c, "aux", "aux")
    score_cells += _group_cells(u, aux, c, "aux", "bins", suffix=" (all bins)", key="aux")
    tau_cells = []
    uc = u.reshape(n, c, -1)
    sums = [np.concatenate([np.zeros((uc.shape[2], 1)), np.cumsum(uc[:, ch, :].T, axis=1)],
                           axis=1) for ch in range(c)] if overlapping else None
    m = 2
    while n // m >= min_clusters:
        for ch in range(c):
            if overlapping:
                mean, var = projected_overlapping_allan_moments(sums[ch], n, m)
            else:
                mean, var = tau_band_moments(u, n, c, ch, m)
            if mean > 0 and var > 0:
                tau_cells.append((m, n // m, ch, mean, var / (2 * mean), 2 * mean ** 2 / var))
        m *= 2
    return MapDesign(n, c, np.asarray(t, float), tuple(channels), noise_dof, windows,
                     score_cells, tau_cells, n >= 16, overlapping)


def projected_overlapping_allan_moments(sums: np.ndarray, n: int, m: int) -> tuple[float, float]:
    """Null mean and variance of :func:`overlapping_allan_form` of a unit white residual of
    ``n`` samples with the span of an orthonormal basis ``U`` projected out: ``Q = z'(I - P) A
    (I - P) z``, so ``E Q = tr A - tr U'AU`` and ``var Q = 2 (tr A^2 - 2 |AU|_F^2 +
    |U'AU|_F^2)`` (:func:`projected_overlapping_allan_traces`). ``sums``: the running sums of
    this channel's rows of ``U`` with a leading zero, ``(K, n + 1)``."""
    tr_a, var_a = white_overlapping_allan_moments(n, m)
    tr_uau, au2, uau2 = projected_overlapping_allan_traces([sums], m)
    return tr_a - tr_uau, var_a + 2.0 * (uau2 - 2.0 * au2)


def _member_cells(u, members, c, axis, key):
    """1-dof score cells of each member ``(label, group, w)`` per channel:
    ``(axis, label, channel, J~, cov, dof, {key: group})``."""
    out = []
    for label, group, w in members:
        for ch in range(c):
            jt, cov, dof = _score_cell(u, _channel_columns(w[:, ch:ch + 1], ch, c))
            if dof:
                out.append((axis, str(label), ch, jt, cov, dof, {key: group}))
    return out


def _group_cells(u, members, c, axis, count, *, suffix="", key=None):
    """Joint score cells of the members ``[(label, group, w)]`` that share a group, per
    channel: ``(axis, group + suffix, channel, J~, cov, dof, {count: members[, key: group]})``."""
    out = []
    for group in dict.fromkeys(g for _, g, _ in members):
        ws = [w for _, g, w in members if g == group]
        for ch in range(c):
            jt, cov, dof = _score_cell(u, _channel_columns(
                np.stack([w[:, ch] for w in ws], 1), ch, c))
            if dof:
                out.append((axis, f"{group}{suffix}", ch, jt, cov, dof,
                            {count: len(ws)} | ({key: group} if key else {})))
    return out


def allan_form(e: np.ndarray, m: int, csum: np.ndarray | None = None) -> np.ndarray:
    """``Q = sum_k (S_k+1 - S_k)^2 / (2 m)`` over the cluster sums ``S_k`` of ``m`` samples of
    ``e`` (``B x n x c``): ``(B, c)``; ``Q / (K - 1)`` is the non-overlapping Allan variance at
    ``tau = m tau_0`` over its white-noise value ``1 / m`` (unit noise). ``csum``: the running
    sums of ``e`` with a leading zero (``B x n+1 x c``), shared between cluster sizes."""
    if csum is None:
        csum = np.concatenate([np.zeros_like(e[:, :1]), np.cumsum(e, axis=1)], axis=1)
    edges = np.arange(e.shape[1] // m + 1) * m
    s = np.diff(csum[:, edges], axis=1)
    return np.sum(np.diff(s, axis=1) ** 2, axis=1) / (2 * m)


def white_allan_moments(k: int) -> tuple[float, float]:
    """Mean and variance of the Allan quadratic form :func:`allan_form` over ``k >= 2`` clusters
    of unit white noise: ``Q = d' d`` with ``d`` the ``k - 1`` differences of the cluster sums
    over ``sqrt(2 m)``, whose covariance ``M M'`` is the tridiagonal ``(1, -1/2)``; so
    ``E Q = k - 1`` and ``var Q = 2 tr (M M')^2 = 2 ((k - 1) + (k - 2) / 2)``."""
    return float(k - 1), 2.0 * ((k - 1) + 0.5 * (k - 2))


def overlapping_allan_form(x: np.ndarray, m: int) -> float:
    """``Q = sum_j (S_{j+m} - S_j)^2 / (2 m)`` over *every* window start ``j`` (``S_j`` the sum
    of ``x[j:j+m]``): ``Q / (n - 2m + 1)`` is the fully overlapping Allan variance at ``tau = m
    tau_0`` over its white-noise value ``1 / m`` (unit noise)."""
    cs = np.concatenate([[0.0], np.cumsum(np.asarray(x, float))])
    s = cs[m:] - cs[:-m]
    return float(np.sum((s[m:] - s[:-m]) ** 2) / (2 * m))


def overlapping_allan_forms(csum: np.ndarray, m: int) -> np.ndarray:
    """:func:`overlapping_allan_form` of every series at once from their running sums with a
    leading zero, ``csum`` (``B x n+1 x c``): ``(B, c)``."""
    s = csum[:, m:] - csum[:, :-m]
    return np.sum((s[:, m:] - s[:, :-m]) ** 2, axis=1) / (2 * m)


def white_overlapping_allan_moments(n: int, m: int) -> tuple[float, float]:
    """Mean and variance of :func:`overlapping_allan_form` on ``n`` samples of unit white noise:
    ``Q = |D z|^2`` with ``L = n - 2m + 1`` rows ``d_j`` of unit norm, whose inner products
    depend on the offset ``k = |i - j|`` alone: ``(2m - 3k) / (2m)`` below ``m``, ``-(2m - k) /
    (2m)`` from ``m`` to ``2m - 1``, 0 beyond. So ``E Q = L`` and ``var Q = 2 |D D'|_F^2 =
    2 (L + 2 sum_k (L - k) c_k^2)``."""
    big_l = n - 2 * m + 1
    if big_l < 1:
        raise ValueError(f"white_overlapping_allan_moments: n={n} < 2 m = {2 * m}")
    k = np.arange(1, min(2 * m, big_l))
    c = np.where(k < m, (2 * m - 3 * k) / (2 * m), -(2 * m - k) / (2 * m))
    return float(big_l), 2.0 * (big_l + 2.0 * float(np.sum((big_l - k) * c * c)))


class _RemovedSpan:
    """The span of the columns a least-squares fit removed from a set of pieces (coefficients
    shared over the pieces), for the white moments of :func:`overlapping_allan_form`: an
    orthonormal basis ``U`` (:func:`nominal_basis`) and the traces of
    :func:`projected_overlapping_allan_traces` per cluster size, computed once.
    :meth:`of` reuses a span already prepared when the new columns span it (the channels of one
    record often share their bias, drift and warm-up columns)."""

    def __init__(self, u: np.ndarray, sizes: list[int]):
        self.u, self.sizes, self.dim = u, sizes, u.shape[1]
        self._sums = None
        self._traces: dict[int, tuple[float, float, float]] = {}

    @classmethod
    def of(cls, columns: list, sizes: list[int], known: list[_RemovedSpan]) -> _RemovedSpan:
        mats = [np.asarray(c, float) for c in columns]
        if any(m.ndim != 2 or len(m) != n for m, n in zip(mats, sizes)) or \
                len({m.shape[1] for m in mats}) != 1:
            raise ValueError("full_rate_tau_cells: give the removed columns as one (n_i, K) "
                             "array per piece, n_i its samples, the same K for every piece; got "
                             f"shapes {[m.shape for m in mats]} for pieces of {list(sizes)}")
        x = np.concatenate(mats)
        norm = np.linalg.norm(x, axis=0)
        x = x[:, norm > 0] / norm[norm > 0]
        for span in known:  # x = U C exactly when x lies in span(U); then rank x = rank C
            if span.sizes == list(sizes) and span.dim:
                c = span.u.T @ x
                if np.linalg.norm(x - span.u @ c) <= 1e-8 * math.sqrt(x.shape[1]):
                    sv = np.linalg.svd(c, compute_uv=False)
                    if np.sum(sv > 1e-10 * sv[0]) == span.dim:
                        return span
        span = cls(nominal_basis(x) if x.shape[1] else np.zeros((len(x), 0)), list(sizes))
        known.append(span)
        return span

    def traces(self, m: int) -> tuple[float, float, float]:
        if m not in self._traces:
            if self._sums is None:
                self._sums = [np.concatenate([np.zeros((self.dim, 1)), np.cumsum(b.T, axis=1)],
                                             axis=1)
                              for b in np.split(self.u, np.cumsum(self.sizes)[:-1])]
            self._traces[m] = projected_overlapping_allan_traces(self._sums, m)
        return self._traces[m]


def projected_overlapping_allan_traces(sums: list[np.ndarray], m: int) -> tuple[float, float,
                                                                                 float]:
    """What removing the columns of an orthonormal basis ``U`` (over all pieces) takes from the
    white-noise moments of :func:`overlapping_allan_form` summed over pieces:
    ``(tr U'AU, |AU|_F^2, |U'AU|_F^2)``, ``A`` the block-diagonal form (one block per piece).
    ``sums``: per piece the running sums of its rows of ``U`` with a leading zero, ``(K, n_i +
    1)`` (shared between cluster sizes); pieces shorter than ``2 m`` are skipped.

    ``Q = |D x|^2`` per piece with ``(D x)_j = (c_{j+2m} - 2 c_{j+m} + c_j) / sqrt(2m)`` on the
    running sums ``c``; ``A U = D'(D U)``, the adjoint by one more running sum: O(n K)."""
    au2, uau = 0.0, None
    scale = 1.0 / math.sqrt(2 * m)
    for c in sums:
        k, n = c.shape[0], c.shape[1] - 1
        if n < 2 * m:
            continue
        length = n - 2 * m + 1
        d = np.empty((k, length))  # D U
        g = np.empty(n)
        for i in range(k):  # one column at a time: its running sums stay in cache
            ci, di = c[i], d[i]
            np.subtract(ci[2 * m:], ci[m:-m], out=di)
            di -= ci[m:-m]
            di += ci[: -2 * m]
            di *= scale
            # the adjoint onto the running sums c_0..c_{n-1} (c_n, the total, gets nothing:
            # the weights (1, -2, 1) of every row sum to zero), then x_l enters c_i for i > l:
            # (D'v)_l = sum_{i > l} g_i = -sum_{i <= l} g_i
            g[:length] = di
            g[length:] = 0.0
            g[m:m + length] -= 2.0 * di
            g[2 * m:] += di[: n - 2 * m]
            np.cumsum(g, out=g)
            au2 += float(g @ g) * scale * scale  # |A U|^2 = |D' D U|^2
        uau = d @ d.T if uau is None else uau + d @ d.T
    if uau is None:
        return 0.0, 0.0, 0.0
    return float(np.trace(uau)), au2, float(np.sum(uau * uau))


def full_rate_tau_cells(pieces: dict, channels: tuple[str, ...], tau0: float, *,
                        min_clusters: int = 9, overlapping: bool = True,
                        removed: dict | None = None) -> list[dict]:
    """Tau band x channel at the full sampling rate: the fully overlapping Allan variance
    (``overlapping=False``: the non-overlapping one) of residual ``pieces`` (channel index ->
    list of 1-D arrays, e.g. the static intervals of one record, sampled every ``tau0`` s) over
    its value for white noise (below), at ``tau = m tau0`` for ``m = 1, 2, 4, ...`` while the
    pieces hold ``>= min_clusters`` non-overlapping clusters. The overlapping form uses every
    window start: its equivalent dof are ~2x the non-overlapping form's (2.03x at 9 clusters),
    and a rate random walk's smallest-p cell landed within 3 octaves of the longest tau in 0.91
    of 45 static-design cases (lambda 32-128), 0.73 with the non-overlapping form.

    This is the axis that localises noise-model effects whose excess lives below a gap map's
    row spacing (quantization at the shortest tau) as well as the slow ones (bias instability,
    rate random walk at the longest). The white value is that of the pieces' own mean square
    ``s^2`` (per channel), for which the null mean and variance of ``Q / s^2`` are exact (see
    the comment below), so every cell holds its level. A term that carries much of the variance
    raises ``s^2`` and so also lowers the ratio away from its band (strong quantization: an
    excess at one sample, a deficit at long tau); the one-sided p-values see only the excess.
    (A noise-model fit's white level as the reference, tried instead, moved the smallest p of
    weak slow terms to the shortest band: that level's own error, with ~N/10 dof from the
    fitted band, outweighs a short band's sampling error.) Cells
    are reported, not decided on (``q`` None, ``decision`` False, like the lag axis): the
    decision family tests the noise-model effects themselves; these say where in tau their
    excess lies. ``rate`` is ``"full"``.

    ``removed`` (channel index -> one ``(n_i, K)`` array per piece): the columns a least-squares
    fit took out of the residual (coefficients shared over the pieces). The white reference is
    then that of white noise with those columns projected out, as the residual is: a mean fit's
    slow columns (bias, ramp, warm-up exponentials) lower the longest cells' white mean by up to
    ~20 %, which the plain reference reads as a deficit of slow noise."""
    if removed is not None and not overlapping:
        raise ValueError("full_rate_tau_cells: removed= needs the overlapping form")
    out, spans = [], []
    for ch, pcs in pieces.items():
        cols = (removed or {}).get(ch)
        if cols is not None and len(cols) != len(pcs):
            raise ValueError(f"full_rate_tau_cells: channel {ch} has {len(pcs)} pieces but "
                             f"{len(cols)} arrays of removed columns; give one per piece")
        keep = [i for i, p in enumerate(pcs) if np.size(p) >= 2]
        pcs = [np.asarray(pcs[i], float) for i in keep]
        n_all = sum(p.size for p in pcs)
        if not n_all:
            continue
        s = math.sqrt(sum(float(np.sum(p * p)) for p in pcs) / n_all)
        if s == 0.0:
            continue
        span = None if cols is None else \
            _RemovedSpan.of([cols[i] for i in keep], [p.size for p in pcs], spans)
        dim = 0 if span is None else span.dim
        m = 1
        while True:
            use = [(p, p.size // m) for p in pcs if p.size // m >= 2]
            clusters = sum(k for _, k in use)
            if clusters < min_clusters:
                break
            if overlapping:
                q = sum(overlapping_allan_form(p / s, m) for p, _ in use)
                mom = np.array([white_overlapping_allan_moments(p.size, m)
                                for p, _ in use]).sum(0)
            else:
                q = sum(float(allan_form(p[None, :, None] / s, m)[0, 0]) for p, _ in use)
                mom = np.array([white_allan_moments(k) for _, k in use]).sum(0)
            # Q / s^2 = N z'Bz / z'z over the N' = N - K dimensions the fit leaves (B = PAP,
            # P the projector off the removed columns) is independent of z'z (spherical
            # symmetry): its mean is N tr B / N' and its variance
            # N^2 2 (N' tr B^2 - (tr B)^2) / (N'^2 (N' + 2)): well below the known-level
            # 2 tr A^2 at the short bands, where Q and s^2 share their samples; and with slow
            # columns removed (a mean fit's bias, ramp, warm-up), the mean falls well below
            # tr A at the longest bands (0.80 tr A at N / 11 samples for 8 such columns)
            tr_a, tr_a2 = float(mom[0]), 0.5 * float(mom[1])
            tr_uau, au2, uau2 = (0.0, 0.0, 0.0) if span is None else span.traces(m)
            tr_b, tr_b2 = tr_a - tr_uau, tr_a2 - 2.0 * au2 + uau2
            dof = n_all - dim
            mean = n_all * tr_b / dof
            var = n_all ** 2 * 2.0 * (dof * tr_b2 - tr_b ** 2) / (dof ** 2 * (dof + 2))
            g, h = var / (2 * mean), 2 * mean ** 2 / var
            out.append(tau_cell(m * tau0, channels[ch], q / mean, mean, h,
                                float(chi2_sf(q / g, h)), clusters, rate="full", q=None,
                                significant=False, decision=False))
            m *= 2
    return out


def lag_one_moments(sizes) -> tuple[float, float]:
    """Exact mean and variance, for white noise, of the pooled lag-one autocorrelation
    :func:`quantization_score` reads: ``r = sum x_k x_{k+1} / sum x_k^2`` over pieces of
    ``sizes`` samples, each mean-removed.

    Per piece ``r`` is ``x'Ax / x'Cx`` with ``A`` the symmetric lag-one form (``1/2`` off the
    diagonal) and ``C`` the centring projector; over the pieces' ``N' = sum (n - 1)`` free
    dimensions the ratio ``w'Bw / w'w`` (``B = CAC``) has mean ``tr B / N'`` and variance
    ``2 (N' tr B^2 - (tr B)^2) / (N'^2 (N' + 2))``, with ``tr B = -(n - 1) / n`` and
    ``tr B^2 = (n - 1) / 2 - 2 (n - 3/2) / n + (n - 1)^2 / n^2`` per piece."""
    n = np.asarray(sizes, float)
    n = n[n >= 2]
    if n.size == 0:
        raise ValueError("lag_one_moments: no piece of at least 2 samples")
    dof = float(np.sum(n - 1))
    tr = float(np.sum(-(n - 1) / n))
    tr2 = float(np.sum((n - 1) / 2 - 2 * (n - 1.5) / n + (n - 1) ** 2 / n ** 2))
    return tr / dof, 2 * (dof * tr2 - tr * tr) / (dof * dof * (dof + 2))


def quantization_score(pieces, tau0: float) -> tuple[float, float, float]:
    """Score (Rao) test for quantization on white-noise residual ``pieces`` sampled every
    ``tau0`` s: returns ``(p, z, Q)``, ``z`` positive where ``r`` lies below its white mean.

    Angle quantization adds the first difference of a white angle error to the rate: white +
    quantization is an MA(1) process with a negative coefficient (lag-one autocovariance
    ``-Q^2 / tau0^2``, all else zero), and the score test of an MA(1) coefficient at zero is the
    lag-one autocorrelation ``r`` (Box-Jenkins). ``z = (r - E r) / sd r`` with the exact white
    moments of :func:`lag_one_moments`; one-sided (``p = Phi(z)``): a negative ``r`` is
    quantization; slow terms, an anti-alias roll-off and settling motion make ``r`` positive and
    the test only conservative. It uses every sample pair up to the Nyquist frequency, where
    quantization's spectrum ``4 sin^2(pi f tau0) Q^2 / tau0^2`` lives; a band-limited fit (the
    Whittle one up to ``rate / 10``) keeps a tenth of it. ``Q`` (the pieces' unit times s) is
    ``tau0 sqrt(-c1)`` from the lag-one autocovariance ``c1`` (0 when ``c1 >= 0``)."""
    pcs = [np.asarray(x, float) - np.mean(x) for x in pieces if np.size(x) >= 2]
    if not pcs:
        raise ValueError("quantization_score: no piece of at least 2 samples")
    c0 = sum(float(np.dot(x, x)) for x in pcs)
    if c0 == 0.0:
        raise ValueError("quantization_score: the pieces are constant")
    c1 = sum(float(np.dot(x[1:], x[:-1])) for x in pcs)
    mean, var = lag_one_moments([x.size for x in pcs])
    z = (c1 / c0 - mean) / math.sqrt(var)
    c1 /= sum(x.size - 1 for x in pcs)
    return float(stats.norm.cdf(z)), float(-z), tau0 * math.sqrt(max(-c1, 0.0))


def outlier_score(pieces) -> tuple[float, float, float]:
    """One-sided test for outliers (heavy tails) on white-noise residual ``pieces``: the excess
    kurtosis ``k`` of the pieces' non-overlapping first differences (the differences remove a
    slow residual; taking every other one keeps them independent), ``z = k / sqrt(24 / n)`` its
    large-sample Gaussian law on ``n`` differences; returns ``(p, z, k)``, ``p = 1 - Phi(z)``
    (a knock or a spike makes the tails heavy, ``k > 0``)."""
    d = np.concatenate([np.diff(np.asarray(x, float))[::2] for x in pieces if np.size(x) >= 2])
    if d.size < 4:
        raise ValueError("outlier_score: fewer than 4 first differences in the pieces")
    d = d - d.mean()
    m2 = float(np.mean(d ** 2))
    if m2 == 0.0:
        raise ValueError("outlier_score: the pieces are constant")
    k = float(np.mean(d ** 4)) / m2 ** 2 - 3
    z = k / math.sqrt(24.0 / d.size)
    return float(stats.norm.sf(z)), z, k


def tau_cell(tau_s: float, channel: str, r: float, mean: float, h: float, p: float,
             clusters: int, *, rate: str | None = None, **extra) -> dict:
    """One tau-band cell of a report's ``where``: the Allan ratio ``r`` at ``tau_s`` over its
    white-noise value (null mean ``mean`` counts, equivalent dof ``h``), its p-value and its EDF
    95 % interval. ``rate="full"`` marks the full-rate band (:func:`full_rate_tau_cells`)."""
    return dict(axis="tau", cell=f"tau {_duration(tau_s)}" + (f" ({rate} rate)" if rate else ""),
                channel=channel, statistic=r, dof=h, expected=1.0, excess=(r - 1.0) * mean,
                p=p, tau_s=tau_s, clusters=clusters,
                ci95=[r * h / float(stats.chi2.ppf(0.975, h)),
                      r * h / float(stats.chi2.ppf(0.025, h))],
                **({"rate": rate} if rate else {}), **extra)


def map_statistics(design: MapDesign, e: np.ndarray):
    """Statistics, p-values and (for the largest-line cells) periodogram peaks of the gap map for
    residuals ``e`` (``B x n x c``): arrays ``(B, cells)`` in :func:`gap_map_cells`' order."""
    bsz, n, c = e.shape
    stat, pv, extra = [], [], []
    cs = np.concatenate([np.zeros((bsz, 1, c)), np.cumsum(e * e, axis=1)], axis=1)
    if design.windows:
        _, _, a, b, ch, e0 = (np.array(x) for x in zip(*design.windows))
        x = cs[:, b, ch] - cs[:, a, ch]  # (B, windows)
        stat += list(x.T)
        pv += list(np.reshape(_f_sf(x / e0, e0, design.noise_dof), x.shape).T)
        extra += [np.zeros(bsz)] * x.shape[1]
    if design.score_cells:
        flat = e.reshape(bsz, n * c)
        sc_all = flat @ np.concatenate([x[3] for x in design.score_cells], axis=1)
        i = 0
        lms, dofs = [], []
        for _, _, _, jt, cov, dof, _ in design.score_cells:
            sc = sc_all[:, i:i + jt.shape[1]]
            i += jt.shape[1]
            lms.append(np.sum(sc * (sc @ cov), axis=1))
            dofs.append(dof)
            # one tested direction: the signed Wald z (its square is the statistic)
            extra.append(sc[:, 0] * np.sqrt(cov[0, 0]) if jt.shape[1] == 1 else np.zeros(bsz))
        stat += lms
        dofs = np.array(dofs, float)[:, None]
        pv += list(np.where(dofs > 0, chi2_sf(np.array(lms), np.maximum(dofs, 1)), 1.0))
    forms = {}
    csum = np.concatenate([np.zeros((bsz, 1, c)), np.cumsum(e, axis=1)], axis=1) \
        if design.tau_cells else None
    for m, _, ch, mean, g, h in design.tau_cells:
        if m not in forms:
            forms[m] = overlapping_allan_forms(csum, m) if design.overlapping else \
                allan_form(e, m, csum)
        q = forms[m][:, ch]
        stat.append(q / mean)
        pv.append(np.reshape(_f_sf(q / (g * h), h, design.noise_dof), q.shape))
        extra.append(np.zeros(bsz))
    if design.fisher:
        x = e - e.mean(axis=1, keepdims=True)
        power = np.abs(np.fft.rfft(x, axis=1)[:, 1:(n - 1) // 2 + 1]) ** 2  # (B, q, c)
        g = power.max(axis=1) / power.sum(axis=1)
        kmax = np.argmax(power, axis=1) + 1
        q = power.shape[1]
        for ch in range(c):
            stat.append(g[:, ch])
            pv.append(fisher_g_pvalue(g[:, ch], q))
            extra.append(kmax[:, ch].astype(float))
    return np.array(stat).T, np.array(pv).T, np.array(extra).T


def _duration(s: float) -> str:
    return f"{s:.3g} s" if s < 120 else f"{s / 60:.3g} min" if s < 7200 else f"{s / 3600:.3g} h"


def gap_map_cells(e: np.ndarray, t: np.ndarray, channels: tuple[str, ...], *, n_params: int,
                  noise_dof: float, lines: dict[str, float], jn: np.ndarray,
                  min_window: int = 16, levels: int = 5, design: MapDesign | None = None,
                  segments=None, nuisance=None, aux=None) -> list[dict]:
    """The Stage-1 map of a whitened residual ``e`` (``n x c``).

    - time x channel: windowed sums of squares over dyadic windows, against
      ``E0 = n_w (1 - p/n)`` with an F reference when the noise level was estimated with
      ``noise_dof`` degrees of freedom (``inf``: known);
    - frequency: 2-dof score tests at the known ``lines`` (name -> period in s) per channel with
      the nominal span projected out, and Fisher's g for the largest unlisted line;
    - position x channel: 1-dof score test of each test position's offset signature (``segments``,
      see :func:`map_design`) with the nominal span projected out (the per-position mean in the
      Wald form that accounts for the fitted parameters); condition x channel: the joint test of
      one condition's positions, where the record has more than one condition;
    - aux x channel: the same for the bins of an auxiliary channel (``aux``), one cell per bin and
      the joint test of its bins;
    - tau band x channel: the fully overlapping Allan variance of the residual at
      ``tau = m tau_0`` (``m = 2, 4, ...`` while at least 9 non-overlapping clusters) over its
      null prediction, with the exact null mean and variance of the quadratic form after the
      projection and a scaled chi-square (Satterthwaite; F when the level was estimated) upper
      tail; ``ci95``: its equivalent-dof confidence interval. (``map_design(...,
      overlapping=False)``: the non-overlapping form, ~half the equivalent dof at the longest
      bands: an ESG angle random walk's smallest-p cell fell at the longest band in 0.84 of the
      detected cases against 0.96 with the overlapping form, 200 cases each.)
    Cells: dicts with axis, cell, channel, statistic, dof, expected, p. ``design``: the
    :func:`map_design` of these arguments (computed here when not given).
    """
    n, c = e.shape
    if design is None:
        design = map_design(t, channels, n_params=n_params, noise_dof=noise_dof, lines=lines,
                            jn=jn, min_window=min_window, levels=levels, segments=segments,
                            nuisance=nuisance, aux=aux)
    stat, pv, extra = (x[0] for x in map_statistics(design, e[None]))
    cells = []
    i = 0
    for lev, k, a, b, ch, e0 in design.windows:
        cells.append(dict(axis="time", cell=f"{t[a] / 3600:.2f}-{t[b - 1] / 3600:.2f} h",
                          channel=channels[ch], statistic=float(stat[i]), dof=e0, expected=e0,
                          excess=float(stat[i]) - e0, p=float(pv[i]), t0=float(t[a]),
                          t1=float(t[b - 1]), level=lev))
        i += 1
    for axis, label, ch, jt, _, dof, info in design.score_cells:
        cells.append(dict(axis=axis, cell=label, channel=channels[ch], statistic=float(stat[i]),
                          dof=dof, expected=dof, excess=float(stat[i]) - dof, p=float(pv[i]),
                          **info, **({"z": float(extra[i])} if jt.shape[1] == 1 else {})))
        i += 1
    tau0 = float(np.median(np.diff(t))) if n > 1 else 0.0
    for m, k, ch, mean, g, h in design.tau_cells:
        cells.append(tau_cell(m * tau0, channels[ch], float(stat[i]), mean, h, float(pv[i]), k))
        i += 1
    if design.fisher:
        q = (n - 1) // 2
        dt = (t[-1] - t[0]) / (n - 1)
        for ch in range(c):
            period = n * dt / extra[i]
            cells.append(dict(axis="frequency", cell=f"largest line ({period / 3600:.3g} h)",
                              channel=channels[ch], statistic=float(stat[i]), dof=q,
                              expected=1.0 / q, excess=0.0, p=float(pv[i]), period_s=period))
            i += 1
    return cells


def ljung_box(x: np.ndarray, lags: int):
    """Ljung-Box portmanteau of a series ``x``: ``(Q, p, acf)`` with ``p`` from chi2(lags)."""
    x = x - x.mean()
    n = len(x)
    acf = np.array([np.sum(x[k:] * x[:-k]) for k in range(1, lags + 1)]) / max(
        float(np.sum(x * x)), 1e-300)
    q = float(n * (n + 2) * np.sum(acf ** 2 / (n - np.arange(1, lags + 1))))
    return q, float(chi2_sf(q, lags)), acf


def lag_cells(e: np.ndarray, channels: tuple[str, ...], lags: int = 20,
              aux: dict | None = None) -> list[dict]:
    """Ljung-Box whiteness per channel of a whitened residual ``e`` (``n x c``), the ``resid``-
    style lag axis, and with ``aux`` (name -> ``n`` values of an auxiliary channel on the same
    rows) the cross-correlation of each channel with the auxiliary channel's increments at lags
    ``-L..L`` (largest ``|r| sqrt(n)``, Bonferroni over the lags against N(0, 1)): reported for
    compatibility, never a decision statistic (no q-value)."""
    n = e.shape[0]
    lags = max(1, min(lags, n // 5))
    out = []
    for ch, name in enumerate(channels):
        q, p, acf = ljung_box(e[:, ch], lags)
        out.append(dict(axis="lag", cell=f"lags 1-{lags} (Ljung-Box)", channel=name,
                        statistic=q, dof=lags, expected=float(lags), excess=q - lags, p=p,
                        acf=[float(a) for a in acf[:5]], q=None, significant=False,
                        decision=False))
    for aname, a in (aux or {}).items():
        da = np.diff(np.asarray(a, float)[:n])
        if da.size < 3 or not np.any(da != da[0]):
            continue
        for ch, name in enumerate(channels):
            r, lag = cross_correlation(e[1:, ch], da, lags)
            z = float(np.max(np.abs(r)) * np.sqrt(da.size))
            p = float(min(1.0, len(r) * 2 * stats.norm.sf(z)))
            out.append(dict(axis="lag", cell=f"CCF with d{aname} (lags -{lags}..{lags})",
                            channel=name, statistic=z, dof=len(r), expected=1.0, excess=0.0,
                            p=p, lag=int(lag[np.argmax(np.abs(r))]), q=None,
                            significant=False, decision=False))
    return out


def cross_correlation(x: np.ndarray, y: np.ndarray, lags: int):
    """Sample cross-correlation ``r_k = corr(x_t, y_{t-k})`` of two equal-length series at
    ``k = -lags..lags``: ``(r, k)``."""
    x = (x - x.mean()) / max(float(np.std(x)), 1e-300)
    y = (y - y.mean()) / max(float(np.std(y)), 1e-300)
    n = len(x)
    ks = np.arange(-lags, lags + 1)
    r = np.array([np.sum(x[k:] * y[:n - k]) if k >= 0 else np.sum(x[:n + k] * y[-k:])
                  for k in ks]) / n
    return r, ks


def _f_sf(ratio, d1, d2):
    """Upper tail of the F(d1, d2) law (chi2(d1)/d1 when ``d2`` is infinite); arrays or floats."""
    if not np.isfinite(d2):
        out = chi2_sf(np.asarray(ratio) * d1, d1)
    else:
        out = special.fdtrc(d1, d2, np.maximum(ratio, 0.0))  # stats.f.sf without its overhead
    return float(out) if np.ndim(out) == 0 else out
