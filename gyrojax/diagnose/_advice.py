"""Stage 3's design advice: for each flagged or ambiguous effect, every candidate design's
minimum detectable effect alone and with its closest rival fitted too, over the directions
some design sees (docs/diagnosis.md)."""

from __future__ import annotations

import numpy as np

from ._signatures import (
    LAMBDA_80,
    SEPARABLE,
    _orth,
    _visibility,
    canonical_correlation,
    nominal_basis,
    project_out,
)


def _hidden_directions(j, u) -> list:
    """An effect's directions a design does not see (raw signature ``j``, nominal basis ``u``):
    those without a signature and those the nominal parameters absorb."""
    _, null, conf = _visibility(j, u)
    return null + conf


def _seen_somewhere(row, designs_hidden):
    """Orthonormal basis (coefficients x kept) of the screened effect's directions that the
    record's design (``row``'s no-signature and confounded directions) or at least one
    candidate design (its :func:`_hidden_directions`, one list per design) sees: the complement
    of the intersection of their hidden subspaces."""
    k = row.sig.jac.shape[2]
    hidden = [row.null_directions + row.confounded_directions, *designs_hidden]
    if any(not h for h in hidden):
        return np.eye(k)
    acc = np.zeros((k, k))
    for h in hidden:
        q, _ = _orth(np.array(h).T)
        acc += q @ q.T
    w, v = np.linalg.eigh(acc)
    return v[:, w < len(hidden) - 1e-6]


def _mde(jt):
    """Minimum detectable effect in prior-scale units (80 % power, alpha 0.05, 1 dof) along the
    least visible direction of the projected signature."""
    _, s = _orth(jt, 1e-12)
    if s.size == 0 or s[-1] == 0:
        return float("inf")
    if s.size < jt.shape[1]:
        return float("inf")
    return float(np.sqrt(LAMBDA_80) / s[-1])


def _design_advice(prob, params0, sigma, flagged):
    rows = []
    grid = {r.sig.name: r.vis_index for r in flagged}  # the grid value each flag was taken at
    names = set(grid)
    # problems that can evaluate one grid value per effect are told which (the flag's)
    only = {"grid": grid} if prob.design_grid_choice else {}
    designs = []
    for label, cond, t in prob.designs():
        jn, sigs = prob.jacobians(params0, sigma, conditions=cond, t=t, **only)
        u = nominal_basis(jn)
        raw = {s.name: s.jac[min(grid.get(s.name, 0), s.jac.shape[0] - 1)] for s in sigs}
        designs.append((label, sigs, {k: project_out(u, v) for k, v in raw.items()},
                        {k: _hidden_directions(v, u) for k, v in raw.items() if k in names}))
    # an effect's directions that neither the record's design nor any candidate sees (no
    # signature, or absorbed by the nominal: e.g. the accelerometer triad's rotation, which the
    # poses absorb on any stand) are reported, and each design's MDE is over the rest
    keep = {r.sig.name: _seen_somewhere(r, [h[r.sig.name] for *_, h in designs
                                           if r.sig.name in h]) for r in flagged}
    for label, sigs, proj, hidden in designs:
        span = {k: _orth(v)[0] for k, v in proj.items()}  # each rival's span, once per design
        for s in sigs:
            if s.name not in names:
                continue
            basis = keep[s.name]
            mine = proj[s.name] @ basis
            others = [o.name for o in sigs if o.name != s.name]
            corr = float(max((canonical_correlation(proj[s.name], proj[o]) for o in others),
                             default=0.0))
            mde = _mde(mine)
            rows.append({"effect": s.name, "design": label, "mde_over_prior": mde,
                         # how many of those directions this design sees: all but its own hidden
                         # ones (they hold the ones no design sees); short of all, its MDE is
                         # infinite, and the count says another design sees the rest
                         "seen_dims": int(basis.shape[0] - len(hidden[s.name])),
                         "kept_dims": int(basis.shape[1]),
                         "mde_vs_closest_rival": max(
                             (_mde(project_out(span[o], mine)) for o in others), default=mde),
                         "max_correlation_with_other_effects": corr,
                         "separable": corr <= SEPARABLE,
                         "unseen_dims": int(basis.shape[0] - basis.shape[1])})
    # ranked by the MDE with the closest rival effect in the model too, then by the MDE: a
    # design that makes an effect visible but leaves it aliased with a rival (the platform's
    # D_oo on a 9 g + 0 g test, where D_oo and rectification both add a bias to the vibrated
    # run only) buys a detection without an attribution (G6's closed loop found this: ranked
    # by the MDE alone, 0 of 2 re-simulated D_oo cases were attributed); where no design sees
    # all of an effect's directions (every MDE infinite), the one that sees the most first
    out = []
    for nm in sorted(names):
        out.extend(sorted([r for r in rows if r["effect"] == nm],
                          key=lambda r: (r["mde_vs_closest_rival"], r["mde_over_prior"],
                                         -r["seen_dims"])))
    return out

