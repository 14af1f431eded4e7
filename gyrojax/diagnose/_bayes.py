"""Bayes factors of the score tests: under a Gaussian prior on an effect's coefficients (the prior
scales, the shape prior, the g-prior, their design mixture) and the shell prior on the
noncentrality (docs/diagnosis.md).

Whitened quantities throughout (see :mod:`gyrojax.diagnose._signatures`)."""

from __future__ import annotations

import math

import numpy as np
from scipy import special

__all__ = ["PRIORS", "PRIOR_LAMBDAS", "SHELL_DESIGN_LAMBDAS", "SHELL_RANGE", "design_log_bf",
           "grid_log_bf", "mix_log_bf", "noncentral_log_bf", "shape_log_bf", "shape_log_bf_scores",
           "shell_design_log_bf", "shell_log_bf", "zellner_log_bf"]


PRIORS = ("design", "shape", "zellner", "scale", "shell")  # Bayes-factor priors (see screen)


SHELL_RANGE = (8.0, 2.0 ** 24)  # the shell prior's noncentralities, log-uniform (see screen)


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
    blind suites' sizes it is the Bayes factor of their population (docs/goals.md: noncentrality
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


PRIOR_LAMBDAS = tuple(2.0 ** k for k in range(11))  # prior sizes of the evidence curve, 1-1024


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


def _grid_log_bf(lms, dofs, lambda0):
    """:func:`grid_log_bf` for many residuals: ``lms`` ``(G, B)``, ``dofs`` ``(G,)`` -> ``(B,)``;
    ``log BF_g = g / (1 + g) LM_g / 2 - dof_g log(1 + g) / 2``."""
    dofs = np.asarray(dofs, float)
    g = lambda0 / np.maximum(dofs, 1.0)
    lbf = 0.5 * (g / (1 + g))[:, None] * np.asarray(lms, float) - 0.5 * (
        dofs * np.log1p(g))[:, None]
    lbf = np.where(dofs[:, None] > 0, lbf, 0.0)
    return np.logaddexp.reduce(lbf, axis=0) - math.log(lbf.shape[0])
