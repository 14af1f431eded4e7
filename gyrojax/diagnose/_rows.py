"""The report's candidate rows: each screened effect's figures in display units, its aliases
and confounded directions by name, and how its signature lies where the gap lies."""

from __future__ import annotations

import numpy as np

from ..analysis.observability import _pretty_basis, format_combination
from ._advice import _mde
from ._records import Candidate
from ._report import grid_located
from ._screening import Screen


def _consistency(row: Screen, prob, n, c, cells) -> float:
    """Cosine between the predicted and the observed excess over the finest time windows: does
    the effect's signature lie where the gap lies?"""
    tc = [x for x in cells if x["axis"] == "time"]
    if not tc or row.dof == 0:
        return float("nan")
    finest = max(x["level"] for x in tc)
    fine = [x for x in tc if x["level"] == finest]
    pred = (row.projected @ row.beta)[: n * c].reshape(n, c)  # the rows (no second block)
    chans = list(prob.channels)
    obs, pr = [], []
    for x in fine:
        i0 = int(np.searchsorted(prob.t[:n], x["t0"]))
        i1 = int(np.searchsorted(prob.t[:n], x["t1"])) + 1
        obs.append(max(0.0, x["excess"]))
        pr.append(float(np.sum(pred[i0:i1, chans.index(x["channel"])] ** 2)))
    obs, pr = np.array(obs), np.array(pr)
    if np.linalg.norm(obs) == 0 or np.linalg.norm(pr) == 0:
        return float("nan")
    return float(obs @ pr / np.linalg.norm(obs) / np.linalg.norm(pr))


def _onestep_display(r: Screen) -> dict:
    return {n: float(b * ps) for n, b, ps in zip(r.sig.names, r.beta, r.sig.prior_scale)}


def candidate_record(r: Screen, prob, excess, n, c, cells) -> Candidate:
    names = prob.nominal_names
    aliases = []  # coefficients in display units of the nominal per display unit of the effect
    for k, en in enumerate(r.sig.names):
        big = [(names[i], float(r.alias[i, k] * prob.nominal_display_scales[i]
                                / r.sig.prior_scale[k]),
                float(r.alias_std[i, k])) for i in range(len(names))
               if abs(r.alias_std[i, k]) > 1]
        if big:
            aliases.append({"effect_param": en, "absorbed_by": [
                {"name": a, "coefficient": x, "in_stderr": s} for a, x, s in big]})
    strength = {}
    for al in aliases:
        for a in al["absorbed_by"]:
            strength[a["name"]] = max(strength.get(a["name"], 0.0), abs(a["in_stderr"]))
    confounded_with = sorted(strength, key=lambda k: -strength[k])
    cons = _consistency(r, prob, n, c, cells)
    mde = _mde(r.projected)
    return Candidate(
        name=r.sig.name, family=r.sig.family, kind=r.sig.kind,
        params=list(r.sig.names), units=list(r.sig.units),
        prior_scale=[float(x) for x in r.sig.prior_scale],
        score=float(r.lm), dof=int(r.dof), p=float(r.p),
        q=None if r.q is None else float(r.q),
        # the score statistic and its dof at every grid value (one entry without a grid)
        score_grid=[float(x) for x in r.lm_grid], dof_grid=[int(x) for x in r.dof_grid],
        log_bf=float(r.log_bf), posterior=float(r.posterior),
        # the design prior's log Bayes factor at other expected noncentralities (prior sizes)
        log_bf_by_lambda={f"{k:g}": float(v) for k, v in r.log_bf_curve.items()},
        onestep=_onestep_display(r),
        onestep_se={nm: float(s * ps) for nm, s, ps in zip(r.sig.names, r.beta_se,
                                                           r.sig.prior_scale)},
        grid=({"name": r.sig.grid_name, "unit": r.sig.grid_unit,
               "values": [float(x) for x in r.sig.grid], "best": r.sig.grid[r.grid_index],
               # the posterior median of the visible fraction, where the flag is taken
               "flag_at": r.sig.grid[r.vis_index],
               # the posterior over the grid values given the effect (uniform prior)
               "posterior": ([float(x) for x in r.grid_weights]
                             if r.grid_weights is not None else [1.0]),
               # the value within one grid step of the most posterior mass (goal G8's
               # loss): the localisation to quote; "best" is what the refit uses
               **dict(zip(("located", "located_mass", "located_window"),
                          grid_located(r.sig.grid, r.grid_weights
                                       if r.grid_weights is not None else [1.0])))}
              if r.sig.grid else None),
        explained_gap_share=float(min(1.0, r.lm / excess)) if excess > 0 else 0.0,
        signature_consistency=cons,
        visible_fraction=float(r.visible_fraction), identifiable=r.flag in
        ("visible", "weakly identifiable", "partly no signature"),
        flag=r.flag,
        **_named_directions(r),
        confounded_with=confounded_with, aliases=aliases,
        mde_over_prior=float(mde),
    )


def _named_directions(r: Screen) -> dict:
    """The screened effect's directions without a signature and those the nominal parameters
    absorb, named in display units. The screening finds them per unit prior scale (its
    columns are the Jacobian times the prior scales), so a direction ``b`` there perturbs the
    coefficients by ``b * prior_scale``; the two agree only where an effect's coefficients share
    one prior scale."""
    return {key: _named_subspace([np.asarray(v) * r.sig.prior_scale for v in vectors], r.sig.names)
            for key, vectors in (("no_signature_directions", r.null_directions),
                                 ("confounded_directions", r.confounded_directions))}


def _named_subspace(vectors, names) -> list[str]:
    """A subspace spanned by coefficient ``vectors`` as named combinations, in reduced
    row-echelon form: the same text for the same subspace (a 2-3 dimensional one, e.g. the
    IMU's common rotation of both triads, has no preferred basis, and the eigenvectors that
    find it turn with rounding)."""
    if not vectors:
        return []
    return [format_combination(v, names) for v in _pretty_basis(np.array(vectors))]

