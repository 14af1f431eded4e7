"""Stages 4 and 5 of the diagnosis: the held-out gap and its null band, the refits' standard
errors and the combinations they determine, what the held-out part says of each refit, and
the verdict (docs/diagnosis.md)."""

from __future__ import annotations

import math

import numpy as np

from ..analysis.observability import complement_basis, format_combination
from ._gapmap import _f_sf
from ._multiplicity import rejected
from ._signatures import (
    _orth,
    effect_family_name,
    nominal_basis,
    signature_directions,
    visible,
)

_CONFOUNDED_FLAGS = ("structurally confounded", "no signature")  # the nominal fit absorbs part or all


SLOW_MEAN = ("time_drift", "warmup_transient", "drift_ramp", "drift_transient")


STOCHASTIC_SLOW = ("rate_random_walk", "bias_instability")


def _with_noise(verdict, noise_rows, alpha, refits=()):
    """Noise-model effects join the verdict: listed under ``noise_effects`` (strongest first);
    when the mean model has no gap they are the attribution. A slow mean effect (drift,
    warm-up) named while a random walk or bias instability is significant on the *nominal*
    residual (and absorbed by the drift columns on the full one) cannot be told from it on this
    record: the verdict becomes ambiguous between them.

    There the held-out part still says which way it leans: a drift's refit on the train part
    predicts the held-out part when the drift is real, and fits the train part only when the
    slow residual is one realisation of a random walk (:func:`_does_not_transfer`). The verdict
    carries the slow members' held-out gaps (``heldout_gap_after_by_effect``) and
    ``heldout_leans`` (``lean``: "deterministic" / "stochastic"; ``effects``: the slow members
    refitted) and stays ambiguous: the held-out gap
    checks an attribution, it does not make one. The same is said of an ``unexplained`` verdict
    on a slow effect while a random walk is significant in the noise model (a long MEMS static:
    the drift's refit leaves the gap, the walk is the cause); its kind and effects stay."""
    if not noise_rows:
        return verdict
    sig = sorted([x for x in noise_rows if x.get("significant")], key=lambda x: -x["statistic"])
    verdict = dict(verdict, noise_effects=[x["name"] for x in sig])
    if sig and verdict["kind"] == "no-gap":
        verdict.update(kind="attributed", effects=[x["name"] for x in sig],
                       reason="the mean model fits; the noise model lacks "
                              + ", ".join(x["name"] for x in sig))
    slow = [e for e in (verdict.get("effects") or []) if effect_family_name(e) in SLOW_MEAN]
    rival = [x["name"] for x in noise_rows if x["name"] in STOCHASTIC_SLOW
             and not x.get("significant") and x.get("p_nominal", 1.0) < alpha]
    if slow and rival and verdict["kind"] in ("attributed", "partial", "ambiguous", "unexplained"):
        verdict.update(kind="ambiguous", effects=list(dict.fromkeys(
            (verdict.get("effects") or []) + rival)),
            reason=f"{', '.join(slow)} and {', '.join(rival)} both explain the slow residual of "
                   "the nominal model; one record cannot tell a deterministic drift from a "
                   "random walk (repeat the run: a drift repeats, a random walk does not)")
        verdict.update(_heldout_leans(slow, refits, verdict))
    walks = [x["name"] for x in sig if x["name"] in STOCHASTIC_SLOW]
    if slow and walks and verdict["kind"] in ("unexplained", "partial"):
        # the noise model's random walk is significant beside a slow mean effect that does not
        # explain the gap: say which way the held-out part leans (kind and effects unchanged)
        verdict.update(_heldout_leans(slow, refits, verdict))
        verdict["reason"] += f"; the noise model lacks {', '.join(walks)} (significant)"
    return verdict


def _heldout_leans(slow, refits, verdict) -> dict:
    """The held-out evidence between the slow mean effects ``slow`` and a random walk: their
    refits' held-out gaps and which way they lean (see :func:`_with_noise`); {} without a
    held-out part or a refit of each. A lean needs a held-out gap outside the nominal model's
    null band (:func:`_heldout_has_gap`): with none there is nothing for a refit to predict."""
    single = {rf["effects"][0]: rf for rf in refits if len(rf["effects"]) == 1}
    if not all(e in single and single[e].get("closure") is not None for e in slow):
        return {}
    out = {"heldout_gap_after_by_effect": (verdict.get("heldout_gap_after_by_effect") or {})
           | {e: single[e]["heldout_gap_after"] for e in slow}}
    fail = [e for e in slow if _does_not_transfer(single[e])]
    lean = "stochastic" if len(fail) == len(slow) else "deterministic" if not fail else None
    if lean is not None and _heldout_has_gap(verdict):
        out["heldout_leans"] = {"lean": lean, "effects": list(slow)}
    return out


def _heldout_has_gap(verdict) -> bool:
    """The held-out gap before any refit lies above the nominal model's null band."""
    g0, band = verdict.get("heldout_gap_before"), verdict.get("heldout_null_band")
    return bool(g0 is not None and band is not None and np.isfinite(g0) and g0 > band[1])


def _null_band(jn_all, m_train, m_ho, extra: float = 0.0, noise_dof: float = np.inf):
    """Expected held-out gap under the nominal model (parameter-extrapolation leverage, plus
    ``extra`` from nuisance terms outside the Jacobian) and its upper 95 % limit.

    The limit counts the held-out samples' scatter (``2 / m_ho``) and, when the noise level was
    estimated, the scatter of that estimate (``2 / noise_dof``, ``noise_dof`` pooled over the
    channels): the held-out gap is a ratio of the two."""
    if m_ho == 0:
        return (float("nan"), float("nan"))
    jt, jh = jn_all[:m_train], jn_all[m_train:]
    u, s, vt = np.linalg.svd(jt, full_matrices=False)
    keep = s > 1e-10 * s[0]
    a = jh @ (vt[keep].T / s[keep])
    mean = float(np.sum(a * a) / m_ho) + extra
    return (mean, mean + 1.96 * np.sqrt(2.0 / m_ho + 2.0 / noise_dof) * (1 + mean))


def _does_not_transfer(refit) -> bool:
    """An attribution fails its held-out check when the refit leaves the held-out gap outside
    its null band *and* removes less than half of it (or adds to it): the effect mimics the
    train residual but does not predict new data (an out-of-library term it happens to fit, goal
    G9). A right effect whose gap is merely not fully closed still removes most of it."""
    g0, g1 = refit["heldout_gap_before"], refit["heldout_gap_after"]
    if refit.get("closure") is not False or g1 is None or not np.isfinite(g0):
        return False
    return bool(g1 > 0.5 * g0)


def _heldout_by_member(names, single, base) -> dict:
    """For an ambiguous verdict: each member's held-out gap after its own refit
    (``heldout_gap_after_by_effect``) and, where the held-out part tells the members apart (the
    refits of some predict it, those of others fit the train part only: :func:`_does_not_transfer`),
    which do and which do not (``heldout_separates``). The train design cannot separate them,
    which is why the verdict is ambiguous; a held-out part on another design can (docs/diagnosis.md,
    Stage 4: confounded alternatives separate on the design-shift split). The verdict stays
    ambiguous: the held-out gap is the check of an attribution, not its input. ``base``: the
    verdict's held-out gap and null band; separation needs a gap above the band."""
    refit = {rf["effects"][0]: rf for rf in single if rf["effects"][0] in names}
    if not any(rf.get("closure") is not None for rf in refit.values()):  # no held-out part
        return {}
    out = {"heldout_gap_after_by_effect": {n: refit[n]["heldout_gap_after"]
                                           for n in names if n in refit}}
    fail = [n for n in names if n in refit and _does_not_transfer(refit[n])]
    keep = [n for n in names if n in refit and n not in fail]
    if fail and keep and _heldout_has_gap(base):
        out["heldout_separates"] = {"transfer": keep, "do_not_transfer": fail}
    return out


def _shift_hidden(rows, cells, jn_all, s_full):
    """Effects with no signature on the train design that have one on the whole record (train
    plus the design-shifted held-out rows): the candidates for a gap seen only held out."""
    if not any(x["axis"] == "heldout" and x.get("significant") for x in cells):
        return []
    u = nominal_basis(jn_all)
    out = []
    for r in rows:
        if r.flag in _CONFOUNDED_FLAGS:
            if visible(u, s_full[r.sig.name].jac[r.vis_index]):
                out.append(r.sig.name)
    return out


def _heldout_cell(g, band, m, noise_dof, kind) -> dict:
    """The held-out gap of a design-shift split as one cell of the map: a model that fits the
    train design but not the shifted one (an effect without signature on the train design) shows
    only here. F reference: held-out sum of squares over its null expectation (leverage
    included), against the noise estimate's dof."""
    ratio = (1 + g) / (1 + band[0])
    return dict(axis="heldout", cell=kind, channel="all", statistic=float(m * (1 + g)),
                dof=float(m), expected=float(m * (1 + band[0])),
                excess=float(m * (g - band[0])), p=_f_sf(ratio, m, noise_dof))


def _refit_uncertainty(combo, coefficients: dict) -> tuple[dict, list]:
    """Standard errors (display units) of a refit's effect coefficients, linearised at the
    nominal fit with the nominal parameters fitted too: the effect block of the inverse
    information, ``(J~^T J~)^+`` of the projected columns, times the prior scales; and the
    combinations the rows determine of the coefficients they do not.

    The undetermined directions are the screening's (:func:`~._signatures.signature_directions` on the
    combination's raw and projected signatures): those without a signature and those whose
    visible fraction after the nominal projection is below ``VISIBLE_MIN`` (absorbed by the
    nominal parameters, e.g. the IMU's common rotation of both triads, which the poses take;
    what little of such a direction survives the projection is second-order physics or
    round-off, so its variance, finite but huge, would make any error look small). A
    coefficient such a direction involves gets ``inf``. The determined combinations of those
    coefficients are the complement of the undetermined directions among them (reduced
    row-echelon form, display units, the largest term's coefficient 1), each with its value from
    ``coefficients``, standard error and unit (its largest term's), e.g. ``maxy + mayx`` where
    the poses absorb ``maxy - mayx``."""
    jt = np.concatenate([r.projected for r in combo], axis=1)
    j = np.concatenate([r.sig.jac[r.grid_index] for r in combo], axis=1)
    scale = np.concatenate([r.sig.prior_scale for r in combo])
    names = [n for r in combo for n in r.sig.names]
    units = [u for r in combo for u in r.sig.units]
    w, v = np.linalg.eigh(jt.T @ jt)
    ok = w > 1e-12 * max(float(w.max()), 1e-300)
    cov = (v[:, ok] / w[ok]) @ v[:, ok].T  # prior-scale units
    var = np.diag(cov).copy()
    _, _, _, null, absorbed = signature_directions(j, jt)
    hidden = np.array(null + absorbed + [v[:, i] for i in np.flatnonzero(~ok)]).reshape(
        -1, len(names)).T
    if hidden.size:
        hidden = _orth(hidden)[0]
    involved = np.flatnonzero(np.any(np.abs(hidden) > 1e-6, axis=1))
    var[involved] = np.inf
    std_errors = {n: float(np.sqrt(x) * ps) for n, x, ps in zip(names, var, scale)}
    estimable = []
    for row in (complement_basis((hidden[involved] * scale[involved, None]).T)
                if involved.size else ()):
        c = np.zeros(len(names))
        c[involved] = row / np.max(np.abs(row))
        c[np.abs(c) < 1e-3] = 0.0  # as format_combination prints it
        terms = {names[i]: float(c[i]) for i in np.flatnonzero(c)}
        cp = c * scale
        estimable.append({
            "combination": format_combination(c, names), "terms": terms,
            "value": float(sum(x * coefficients[k] for k, x in terms.items())),
            "std_error": float(np.sqrt(max(cp @ cov @ cp, 0.0))),
            "unit": units[int(np.argmax(np.abs(c)))]})
    return std_errors, estimable


def _pair_also(pair, chosen, g_nom) -> str:
    """What the largest refit of the effects that earned their place did where the verdict
    stays with one effect's (the set leaves significant cells and explains too little of the
    gap to be named with a remainder): said when it predicts more of the held-out part, which
    the user would otherwise read only in the refit table."""
    if pair is None or pair is chosen:
        return ""
    after, before = pair["heldout_gap_after"], chosen["heldout_gap_after"]
    if after is None or before is None or not after < before:
        return ""
    band = "inside" if pair["closure"] else "above"
    return (f"; refitted with {' + '.join(pair['effects'])}, the held-out gap goes {g_nom:.3g} "
            f"-> {after:.3g} ({band} its null band) and {len(pair['remaining_cells'])} cells "
            "stay significant")


def _fmt_gap(g) -> str:
    return "n/a" if g is None or not np.isfinite(g) else f"{g:.3g}"


def _cell_names(cells) -> list[str]:
    """Gap-map cells as the verdict lists them: ``"<axis> <cell> <channel>"``."""
    return [f"{x['axis']} {x['cell']} {x['channel']}" for x in cells]


PARTIAL_SHARE = 0.9  # the share of the gap the named set must explain to be named with a remainder


def earns_place(before, after) -> bool:
    """Whether an effect that passed its conditional score test (after the effects before it
    were refitted: ``before``) also earns its place on the held-out part, where the held-out
    part can show it: where the held-out gap of ``before`` lies above its null band, the refit
    with the effect added (``after``) must lower it; where it lies inside, the added effect must
    keep it inside (a mimic of the train residual that spoils the prediction is out). Without a
    held-out part the score test decides."""
    if before["closure"] is None:
        return True
    if before["closure"] is False:
        return bool(after["heldout_gap_after"] < before["heldout_gap_after"])
    return after["closure"] is True


def explained_shares(chain, g_nom, band, g_train) -> dict | None:
    """How much of the gap each effect of the nested refits ``chain`` explains, each after the
    ones before it: ``{"of": "held-out" | "train", "shares": {effect: share}, "total": share}``
    (shares of the nominal model's gap; they add up to ``total``, at most 1: a gap after below
    0, the noise's expectation, counts as 0). The held-out gap where it
    lies above the nominal model's null band (there it measures what the refits predict); the
    train gap otherwise (no held-out part, or a held-out gap the noise can make). ``None``
    without a refit or a positive gap to share."""
    if not chain:
        return None
    heldout = g_nom is not None and np.isfinite(g_nom) and g_nom > band[1]
    g0, key = (g_nom, "heldout_gap_after") if heldout else (g_train, "gap_train_after")
    if g0 is None or not g0 > 0:
        return None
    gaps = [g0] + [max(rf[key], 0.0) for rf in chain]  # below 0 is noise: nothing left
    return {"of": "held-out" if heldout else "train",
            "shares": {rf["effects"][-1]: float((a - b) / g0)
                       for rf, a, b in zip(chain, gaps, gaps[1:])},
            "total": float(1 - gaps[-1] / g0)}


def remainder_text(cells, limit: int = 3) -> str:
    """Where the significant cells ``cells`` left after a refit lie, in a few words: per axis
    (largest excess first), the channels and then the cells (largest first, at most ``limit``),
    e.g. ``"time (ay; 0.00-0.01 h, 0.09-0.10 h), tau (ay; tau 26 s)"``."""
    if not cells:
        return "no significant cell"
    by_axis: dict = {}
    for x in cells:
        a = by_axis.setdefault(x["axis"], {"excess": 0.0, "ch": {}, "win": {}})
        ex = max(float(x.get("excess") or 0.0), 0.0)
        a["excess"] += ex
        a["ch"][x["channel"]] = a["ch"].get(x["channel"], 0.0) + ex
        a["win"][x["cell"]] = a["win"].get(x["cell"], 0.0) + ex
    parts = []
    for axis, a in sorted(by_axis.items(), key=lambda kv: -kv[1]["excess"]):
        chans = sorted(a["ch"], key=lambda k: -a["ch"][k])
        wins = sorted(a["win"], key=lambda k: -a["win"][k])
        text = (", ".join(chans) + "; " + ", ".join(wins[:limit])
                + (", ..." if len(wins) > limit else ""))
        parts.append(f"{axis} ({text})")
    return ", ".join(parts)


def headline(verdict) -> str | None:
    """The verdict in one line where it names effects with their shares of the gap: "earth_rate
    explains 99.8 % of the held-out gap, time_drift 0.1 %; remainder: frequency (wx, ...)";
    ``None`` elsewhere."""
    ex = verdict.get("explained")
    if not ex or verdict.get("kind") not in ("attributed", "partial"):
        return None
    items = list(ex["shares"].items())
    text = ", ".join(f"{e} {100 * x:.1f} %" for e, x in items[1:])
    first = f"{items[0][0]} explains {100 * items[0][1]:.1f} % of the {ex['of']} gap"
    if len(items) > 1:
        first = (f"{' + '.join(e for e, _ in items)} explain {100 * ex['total']:.1f} % of the "
                 f"{ex['of']} gap ({items[0][0]} {100 * items[0][1]:.1f} %, {text})")
    return f"{first}; remainder: {verdict.get('remainder') or 'no significant cell'}"


def _verdict(detected, rows, amb, refits, chain, top, alpha, cells, g_nom, band,
             shift_hidden=(), g_train=None):
    """Stage 5 (docs/diagnosis.md "Verdicts"). ``chain``: the nested refits of the effects that
    earned their place, the top effect's alone first (:func:`earns_place`); ``refits``: every
    refit (the ambiguity set's singles among them); ``g_nom``, ``band``: the nominal model's
    held-out gap and null band; ``g_train``: its train gap. Returns the verdict's fields."""
    base = {"heldout_gap_before": g_nom, "heldout_null_band": list(band)}
    if not detected:
        return {"kind": "no-gap", "effects": [], "heldout_gap_after": None, **base,
                "reason": f"no gap-map cell or library test significant at q < {alpha:.3g}"}
    sig_rows = [r for r in rows if rejected(r.p, 1.0 if r.q is None else r.q, alpha)]
    shifted = [x for x in cells if x["axis"] == "heldout" and x.get("significant")]
    if not sig_rows and shifted and shift_hidden and not any(
            x.get("significant") for x in cells if x["axis"] != "heldout"):
        return {"kind": "confounded", "effects": list(shift_hidden),
                "heldout_gap_after": None, **base,
                "reason": "the model fits the train design but not the held-out one "
                          f"({shifted[0]['cell']}, G = {g_nom:.3g} above its null band "
                          f"{band[1]:.3g}); candidates: the effects without a signature on "
                          f"the train design that have one on the whole record: "
                          f"{', '.join(shift_hidden)}"}
    if not sig_rows:
        where = _cell_names(x for x in cells if x.get("significant"))
        return {"kind": "unexplained", "effects": [], "heldout_gap_after": None, **base,
                "cells": where[:10],
                "reason": "the gap map is significant but no catalogued effect's score test is"}
    # an effect without a signature cannot make a detected gap (its Bayes factor is 1 whatever
    # the record) and holds no posterior; when every effect with one fits worse than none
    # (Bayes factor < 1), as for an effect outside the catalogue, none is the cause
    if top.log_bf < 0.0:
        return {"kind": "unexplained", "effects": [], "heldout_gap_after": None, **base,
                "posterior": {r.sig.name: r.posterior for r in amb},
                "reason": f"every catalogued effect with a signature fits worse than none (the "
                          f"largest Bayes factor, {top.sig.name}'s, is {math.exp(top.log_bf):.2g})"}
    # `confounded` names one effect as the likely cause, so its own score test must be
    # significant and it must hold most of the posterior mass.
    share = top.posterior / (sum(r.posterior for r in rows) or 1.0)  # as the ambiguity set's
    top_confounded = top.flag in _CONFOUNDED_FLAGS
    if top_confounded and top in sig_rows and share >= 0.5:
        return {"kind": "confounded", "effects": [top.sig.name], "heldout_gap_after": None,
                **base, "posterior": {r.sig.name: r.posterior for r in amb},
                "reason": f"{top.sig.name} is {top.flag} on this design"}
    names = [r.sig.name for r in amb]
    if len(amb) == 1 and top_confounded:
        return {"kind": "unexplained", "effects": [], "heldout_gap_after": None, **base,
                "posterior": {top.sig.name: top.posterior},
                "reason": f"the posterior's top effect, {top.sig.name}, is {top.flag} on this "
                          "design and its score test is not significant: no catalogued "
                          "effect's visible signature explains the gap"}
    single = [rf for rf in refits if len(rf["effects"]) == 1]
    best = min(single, key=lambda rf: rf["gap_train_after"]) if single else None
    if len(amb) > 1:
        # the effects that earned their place beside the set, after the refit of the member
        # the forward selection started from (decision 0030: the one that best predicts the
        # held-out part)
        also = [rf["effects"][-1] for rf in (chain or [])[1:] if rf["effects"][-1] not in names]
        more = ""
        if also:
            more = (f"; beside the set, {' and '.join(also)} "
                    f"{'earns its' if len(also) == 1 else 'earn their'} place after "
                    f"{chain[0]['effects'][0]}'s refit (held-out gap "
                    f"{_fmt_gap(chain[0]['heldout_gap_after'])} -> "
                    f"{_fmt_gap(chain[-1]['heldout_gap_after'])})")
        head = chain[0] if chain else best
        return {"kind": "ambiguous", "effects": names + also, "also": also,
                "heldout_gap_after": head["heldout_gap_after"] if head else None, **base,
                "posterior": {r.sig.name: r.posterior for r in amb},
                "reason": "no single effect holds 90 % of the posterior; see design_advice"
                          + more,
                **_heldout_by_member(names, single, base)}
    if not chain:
        return {"kind": "unexplained", "effects": [], "heldout_gap_after": None, **base,
                "reason": "no refit available"}
    # the first nested refit that leaves no significant cell, else the top effect's alone
    chosen = next((rf for rf in chain if not rf["remaining_cells"]), chain[0])
    if chosen["remaining_cells"]:
        last = chain[-1]
        ex = explained_shares(chain, g_nom, band, g_train)
        if ex is not None and ex["total"] >= PARTIAL_SHARE and not _does_not_transfer(last):
            v = {"kind": "partial", "effects": last["effects"],
                 "heldout_gap_after": last["heldout_gap_after"], **base,
                 "posterior": {r.sig.name: r.posterior for r in amb},
                 "cells": _cell_names(last["remaining_cells"])[:10],
                 "explained": ex, "remainder": remainder_text(last["remaining_cells"])}
            return dict(v, reason=headline(v))
        cells_left = _cell_names(chosen["remaining_cells"])
        return {"kind": "unexplained", "effects": chosen["effects"],
                "heldout_gap_after": chosen["heldout_gap_after"], **base, "cells": cells_left[:10],
                "reason": "after refitting the best catalogued effect(s) the localised gap map "
                          "still has significant cells" + _pair_also(last, chosen, g_nom)}
    if _does_not_transfer(chosen):
        return {"kind": "unexplained", "effects": chosen["effects"],
                "heldout_gap_after": chosen["heldout_gap_after"], **base,
                "reason": f"the refit with {' + '.join(chosen['effects'])} fits the train part "
                          f"but not the held-out part (held-out gap {g_nom:.3g} -> "
                          f"{chosen['heldout_gap_after']:.3g}, null band <= "
                          f"{chosen['heldout_null_band_after'][1]:.3g}): it mimics the gap "
                          "without explaining it"}
    return {"kind": "attributed", "effects": chosen["effects"],
            "heldout_gap_after": chosen["heldout_gap_after"], **base,
            "posterior": {r.sig.name: r.posterior for r in amb},
            "p": {r.sig.name: r.p for r in amb},
            "explained": explained_shares(chain[:chain.index(chosen) + 1], g_nom, band, g_train),
            "remainder": remainder_text([])}
