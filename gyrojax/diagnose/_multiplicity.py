"""Multiplicity control over the gap map and the library together: weighted Benjamini-Hochberg
q-values (docs/diagnosis.md).

Whitened quantities throughout (see :mod:`gyrojax.diagnose._signatures`)."""

from __future__ import annotations

import numpy as np

from ._gapmap import map_statistics
from ._screening import library_pvalues

__all__ = ["bh_qvalues"]


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


def rejected(p: float, q: float, level: float) -> bool:
    """Whether a test of the decision family is significant: its weighted-BH q-value below the
    level *and* its own p-value below it. The second condition matters only for tests weighted
    above ``1 / level`` (the library's few rows against the map's many cells): when a record is
    far from the model and nearly every hypothesis is rejected, weighted BH rejects those at any
    p, even 1 (``q <= (p / w) M / rank``); a test whose own p-value exceeds the level is never
    reported as a finding. Under the null (nothing else rejected) it changes nothing."""
    return bool(q < level and p < level)


def _bh_weights(n_map: int, n_library: int, library_share):
    """Weighted-BH weights: the library's tests share ``library_share`` of the total weight."""
    if library_share is None or n_map == 0 or n_library == 0:
        return None
    if not 0.0 < library_share < 1.0:
        raise ValueError(f"library_share={library_share}: give a share in (0, 1) of the "
                         "multiplicity weight for the library's tests, or None for plain BH")
    return np.concatenate([np.full(n_map, (1 - library_share) / n_map),
                           np.full(n_library, library_share / n_library)])


def _outside_pvalues(cells, noise_rows, n_map):
    """``(rng, b) -> (p_cells, p_noise)``: null p-values of the tests outside the map and the
    library, drawn independently of the residual: the cells past the map's ``n_map`` (a
    design-shift held-out cell: uniform) and the noise-model rows (Bonferroni minimum over the
    channels they tested: ``min(1, k min(U_1..U_k))``; 1 where not testable)."""
    n_extra = len(cells) - n_map
    ks = [len(x.get("fitted") or {}) if x.get("testable", True) else 0 for x in noise_rows]

    def draw(rng, b):
        p_cells = rng.uniform(size=(b, n_extra))
        p_noise = np.ones((b, len(ks)))
        for i, k in enumerate(ks):
            if k:
                p_noise[:, i] = np.minimum(1.0, k * rng.uniform(size=(b, k)).min(axis=1))
        return p_cells, p_noise
    return draw


def _calibrated_level(designs, mdesign, weights, alpha, n_draws, draw, *, seed, outside=None):
    """The BH level whose global false-alarm rate is ``alpha`` under the linearised null, and
    the draws' smallest q-values (see the module docstring).

    ``draw(rng, b)`` gives ``b`` whitened null residuals (``b x n x c``, or flat with a second
    block's entries after the rows': :meth:`~gyrojax.diagnose.AbstractGapProblem.null_sampler`);
    the map (:func:`map_statistics`) and the library (:func:`library_pvalues`) are evaluated
    on every draw; ``outside(rng, b)`` (:func:`_outside_pvalues`) adds the null p-values of
    the tests outside them. The level is the ``k``-th smallest of the draws' smallest q-values,
    ``k = floor(alpha (B + 1))``: rejecting when the data's smallest q is below it is the Monte
    Carlo test with p-value ``(1 + #{minq_b <= minq}) / (B + 1)``.
    """
    _, sig_designs = designs
    n, c = mdesign.n, mdesign.c
    k = int(np.floor(alpha * (n_draws + 1) + 1e-9))
    if k < 1:
        raise ValueError(f"null_draws={n_draws} is too few for alpha={alpha}: give at least "
                         f"{int(np.ceil(1 / alpha)) - 1} (e.g. 499)")
    rng = np.random.default_rng(seed)
    minq = []
    block = max(1, min(n_draws, 2_000_000 // max(n * c, 1)))  # bounds the memory (B x n x c)
    for start in range(0, n_draws, block):
        b = min(block, n_draws - start)
        z = draw(rng, b)
        _, p_map, _ = map_statistics(mdesign, z)
        p_lib = library_pvalues(sig_designs, z.reshape(b, -1).T).T
        p_cells, p_noise = outside(rng, b) if outside is not None else (
            np.zeros((b, 0)), np.zeros((b, 0)))
        p = np.concatenate([p_map, p_cells, p_lib, p_noise], axis=1)
        minq.append(bh_qvalues(p, weights).min(axis=1))
    minq = np.sort(np.concatenate(minq))
    return float(minq[k - 1]), minq

