"""The efficient score tests of the catalogue: each effect's test on the residual with the nominal
span projected out, grid effects by a bootstrap sup-p, posteriors over the catalogue and the
ambiguity set (docs/diagnosis.md, stage 2).

Whitened quantities throughout (see :mod:`gyrojax.diagnose._signatures`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._bayes import (
    PRIOR_LAMBDAS,
    PRIORS,
    SHELL_DESIGN_LAMBDAS,
    _info_eig,
    _log_bf,
    _shape_log_bf_grid,
    mix_log_bf,
    shape_log_bf,
    shell_design_log_bf,
    shell_log_bf,
    zellner_log_bf,
)
from ._signatures import (
    Signature,
    _column_directions,
    chi2_sf,
    nominal_basis,
    project_out,
    signature_directions,
    visibility_flag,
)

__all__ = ["Screen", "SignatureDesign", "ambiguity_set", "grid_posterior", "has_signature",
           "library_pvalues", "score_draws", "screen", "screen_designs"]




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
    (``b ~ N(0, prior_scale^2)``, docs/diagnosis.md step 5) or ``prior="shell"`` (the noncentrality
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
    and the 90 % sets shrank (benchmarks/RESULTS.md)."""
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

