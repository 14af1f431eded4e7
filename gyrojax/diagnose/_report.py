"""GapReport: the diagnosis as data (JSON for programs, Markdown for people) and as Markdown."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._records import Candidate, Refit, Verdict, json_clean

__all__ = ["GapReport"]

ADVICE_SHOWN = 3  # design-advice rows per effect in the Markdown summary (the JSON has all)
# the summary asks for the record's units and conditions to be checked when the nominal fit's
# train residual is this many times the noise level (RMS): an ESG record in hours gives 153, a
# Schuler record's velocities in km/h 489 and its latitude in rad 151; of the 19 real records
# (`gyrojax.datasets`) the largest is 8.6 (Xsens, train gap 73.7), the next 4.6 (LN-100)
UNITS_CHECK_RATIO = 30.0


def verdict_lines(v) -> list[str]:
    """The report's first lines: the verdict's kind and effects with its reason, then its
    headline (each named effect's share of the gap and where the rest lies) unless the reason
    already says it."""
    eff = ", ".join(v.effects or []) or "-"
    head = v.headline()
    reason = v.reason if v.reason and v.reason != head else None
    lines = [f"**Verdict: {v.kind}** ({eff})" + (f" - {reason}" if reason else "")]
    if head and not (reason or "").startswith(head):
        lines.append(head)  # effect names as the catalogue spells them
    return lines


@dataclasses.dataclass
class GapReport:
    """Outcome of :func:`gyrojax.diagnose.diagnose`.

    - `nominal`: fitted nominal parameters (display units, see `nominal_units`); `noise`: the
      whitening level and where it came from.
    - `gap`: normalised gap ``G = mean(e^2) - 1`` of the whitened residual on train and held-out
      data (0 when model and data agree) with the held-out null band, and residual RMS (SI).
    - `where`: gap-map cells (axis, cell, channel, statistic, dof, p, q, significant); axes
      ``time``, ``frequency``, ``position`` and ``condition`` (with the signed Wald ``z`` of a
      1-dof cell), ``tau`` (AVAR ratio with ``tau_s`` and its 95 % EDF interval ``ci95``),
      ``heldout`` (a design-shift split), and ``lag`` (Ljung-Box; reported only: ``q`` None).
    - `ranking`: one row per catalogued effect (score, p, q, posterior, one-step estimate,
      visible fraction and flag, no-signature directions, aliases by name, MDE / prior scale).
    - `ambiguity`: the 90 %-posterior set and the canonical correlations of effect pairs.
    - `refits`: per refitted candidate: coefficients and standard errors (``inf`` where the
      rows do not determine a coefficient: no signature, or absorbed in part by the nominal
      parameters), the combinations of such coefficients the rows do determine (``estimable``:
      text, terms, value, standard error, unit), the nominal parameters refitted with them
      (``nominal_after``, display units), held-out gap before/after, reduction, closure,
      gap-map cells still significant.
    - `design_advice`: per flagged effect and candidate design, MDE / prior scale alone and with
      the closest rival effect fitted too (the ranking key: the advised design first), the
      largest correlation with another effect and whether that is <= 0.9 (separable).
    - `verdict`: kind (no-gap | attributed | partial | ambiguous | confounded | unexplained),
      effects and, for an attribution, each effect's share of the gap (:class:`Verdict`).
    - `conditional`: where the forward selection (several effects at once) ran, after its last
      refit: ``after`` (the effects refitted), ``stopped`` (why no further effect joined, in
      words), ``vetoed`` (the effects that passed their conditional score test after that
      refit but not the held-out part, in the order tried: ``effect``,
      ``heldout_gap_before``, ``heldout_gap_after``, ``band``; the rest were rescored with
      their signatures as a nuisance) and ``scores`` (each other effect's conditional score
      test after that refit: ``effect``, ``score``,
      ``dof``, ``p``, ``p_bonferroni`` over them, ``visibility``; largest score first); else
      ``None``.
    """

    rig: str
    channels: tuple
    n_train: int
    n_heldout: int
    nominal: dict
    nominal_units: dict
    noise: dict
    gap: dict
    where: list
    ranking: list[Candidate]
    ambiguity: dict
    second: str | None
    refits: list[Refit]
    design_advice: list
    verdict: Verdict
    alpha: float
    timings: dict
    residual_all: np.ndarray = dataclasses.field(repr=False)  # whitened, nominal fit, (n, c)
    t: np.ndarray = dataclasses.field(repr=False)
    residual_after: np.ndarray | None = dataclasses.field(default=None, repr=False)
    noise_effects: list = dataclasses.field(default_factory=list)
    split: str = "time-ordered (held-out = the record's end)"
    multiplicity: dict = dataclasses.field(default_factory=dict)
    prior: str = "design"  # the posteriors' Bayes-factor prior (diagnose's ``prior``)
    conditional: dict | None = None

    @property
    def kind(self) -> str:
        return self.verdict.kind

    def candidate(self, name: str) -> Candidate:
        for r in self.ranking:
            if r.name == name:
                return r
        raise KeyError(f"no effect {name!r} in the report; it has {[r.name for r in self.ranking]}")

    def candidates_json(self) -> list:
        out = []
        for r in self.ranking:
            rf = next((x for x in self.refits if x.effects == [r.name]), None)
            out.append({
                "name": r.name, "score": r.score, "dof": r.dof, "p_value": r.p,
                "q_value": r.q, "posterior": r.posterior,
                "identifiable": r.identifiable, "visibility": r.flag,
                "visible_fraction": r.visible_fraction,
                "confounded_with": r.confounded_with, "aliases": r.aliases,
                "no_signature_directions": r.no_signature_directions,
                "confounded_directions": r.confounded_directions,
                "onestep": r.onestep, "onestep_se": r.onestep_se, "units": r.units,
                "grid": r.grid, "score_grid": r.score_grid, "dof_grid": r.dof_grid,
                "signature_consistency": r.signature_consistency,
                "mde_over_prior": r.mde_over_prior,
                "heldout_gap_after": rf.heldout_gap_after if rf else None,
                "reduction": rf.reduction if rf else None,
            })
        return out

    def to_json(self) -> dict:
        return json_clean({
            "rig": self.rig, "channels": list(self.channels),
            "split": {"train_samples": self.n_train, "heldout_samples": self.n_heldout,
                      "kind": self.split},
            "nominal": {"parameters": {k: {"value": v, "unit": self.nominal_units[k]}
                                       for k, v in self.nominal.items()}},
            "noise": self.noise, "gap": self.gap,
            "where": [{k: v for k, v in x.items()} for x in self.where],
            "candidates": self.candidates_json(),
            "ambiguity": self.ambiguity, "second_effect": self.second,
            "conditional": self.conditional,
            "noise_effects": self.noise_effects,
            "refits": self.refits, "design_advice": self.design_advice,
            "verdict": self.verdict, "alpha": self.alpha, "multiplicity": self.multiplicity,
            "prior": self.prior,
            "timings": self.timings,
        })

    def _multiplicity_text(self) -> str:
        m = self.multiplicity or {"method": "weighted BH", "level": self.alpha}
        text = f"{m['method']}, significant at q < {m['level']:.3g}"
        if m.get("null_draws"):
            text += (f" (alpha {self.alpha} over {m['null_draws']} null draws; global p "
                     f"{m['global_p']:.3g})")
        return text

    def markdown(self) -> str:
        v = self.verdict
        lines = [f"# Gap diagnosis ({self.rig})", ""]
        lines += verdict_lines(v)
        g0, g1 = v.heldout_gap_before, v.heldout_gap_after
        band = self.gap.get("heldout_null_band") or [None, None]
        if g0 is not None and math.isfinite(g0):
            each = v.heldout_gap_after_by_effect
            no_refit = [e for e in (v.effects or []) if each and e not in each]
            after = (f"after {g1:.3g}" if g1 is not None else "after -") if not each else (
                ("after refitting each: " if len(each) > 1 else "after refitting ")
                + ", ".join(f"{k} {x:.3g}" for k, x in each.items())
                + (f"; {', '.join(no_refit)}: "
                   + ("a noise-model term" if len(no_refit) == 1 else "noise-model terms")
                   + ", no refit" if no_refit else ""))
            lines.append(f"Held-out gap G = mean(e^2) - 1: before {g0:.3g}, {after} "
                         f"(null band <= {band[1]:.3g})")
            lean = (v.heldout_leans or {}).get("lean")
            if lean:
                slow = ", ".join(v.heldout_leans["effects"])
                lines.append(
                    f"The held-out part leans to the random walk: the refit of {slow} fits the "
                    "train part only, as a drift fitted to one realisation of a random walk "
                    "does (repeat the run to decide: a drift repeats, a random walk does not)"
                    if lean == "stochastic" else
                    f"The held-out part leans to the drift: the refit of {slow} removes most of "
                    "the held-out gap, which a random walk's realisation would not repeat "
                    "(repeat the run to decide)")
            sep = v.heldout_separates
            if sep:
                lines.append(f"The held-out part tells them apart: refitted alone, "
                             f"{', '.join(sep['transfer'])} removes most of its gap, "
                             f"{', '.join(sep['do_not_transfer'])} fits the train part only "
                             "(the verdict stays ambiguous: the held-out gap checks an "
                             "attribution, it does not make one)")
        sig = ", ".join(f"{ch} {shown}" for ch, shown in zip(self.channels, self.noise["shown"]))
        lines.append(f"Noise level: {sig} ({self.noise['source']}); train gap {self.gap['train']:.3g}")
        turns = self.noise.get("turns")
        if turns:
            lines.append(f"Turns: {turns['count']} between still poses ({turns['train']} train), "
                         f"each a residual block entry pair at {turns['std_deg']:.3g} deg "
                         f"(median; {turns['source']})")
        ratio = math.sqrt(max(1.0 + self.gap["train"], 0.0))
        if ratio > UNITS_CHECK_RATIO:
            lines.append(f"Note: the nominal fit's residual is {ratio:.3g} times the noise level "
                         "(RMS), more than a physical effect on a bench usually leaves: check the "
                         "record's units (SI: s, rad, rad/s, m/s, m/s^2) and its conditions "
                         "(latitude, scheme, schedule) before reading the verdict")
        lines += [f"Multiplicity: {self._multiplicity_text()}", "", "## Where (significant cells)", ""]
        hits = [x for x in self.where if x.get("significant")]
        if hits:
            lines += ["| axis | cell | channel | statistic | expected | q |", "|---|---|---|---|---|---|"]
            for x in sorted(hits, key=lambda x: x["q"])[:12]:
                lines.append(f"| {x['axis']} | {x['cell']} | {x['channel']} | "
                             f"{x['statistic']:.4g} | {x['expected']:.4g} | {x['q']:.2g} |")
        else:
            lines.append("none")
        lines += ["", "## Which (efficient score tests at the nominal fit; posteriors under the "
                  f"{self.prior} prior)", "",
                  "| effect | score | dof | p | posterior | visible | flag | absorbed by |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in self.ranking:
            lines.append(f"| {r.name} | {r.score:.3g} | {r.dof} | {r.p:.2g} | "
                         f"{r.posterior:.2f} | {r.visible_fraction:.2g} | {r.flag} | "
                         f"{', '.join(r.confounded_with[:3]) or '-'} |")
        if self.noise_effects:
            lines += ["", "## Noise-model effects (full-rate static residual)", "",
                      "| effect | p (Bonferroni over channels) | q | channel | fitted per channel |",
                      "|---|---|---|---|---|"]
            for x in self.noise_effects:
                if not x.get("testable", True):  # no p-value: say why instead
                    lines.append(f"| {x['name']} | - | - | - | {x['statistic_kind']} |")
                    continue
                lines.append(f"| {x['name']} | {x['p']:.2g} | {x.get('q', float('nan')):.2g} | "
                             f"{x['channel']} | {_values_by_unit(x['fitted'], x['unit'])} |")
        full = [x for x in self.where if x["axis"] == "tau" and x.get("rate") == "full"]
        if full:
            best = {}
            for x in full:
                if x["p"] < best.get(x["channel"], {"p": 0.05})["p"]:
                    best[x["channel"]] = x
            lines += ["", "Where the noise departs from white (full-rate Allan variance over "
                      "its white value, smallest p per channel below 0.05; reported, not "
                      "decided on): " + ("; ".join(
                          f"{ch} at tau {x['tau_s']:.3g} s (ratio {x['statistic']:.3g}, "
                          f"p {x['p']:.2g})" for ch, x in best.items()) or "nowhere")]
        grids = [r for r in self.ranking if r.grid and r.posterior >= 0.05][:5]
        if grids:
            lines += ["", "Grid values (uniform prior over the grid; the posterior given the "
                      "effect): " + "; ".join(_grid_text(r) for r in grids)]
        classes = self.ambiguity.get("classes")
        if classes:
            lines += ["", "Cannot be told apart on this design (every direction of one effect "
                      "mimicked by the other: smallest projected canonical correlation >= 0.98; "
                      "the design advice says which test would): "
                      + "; ".join(" = ".join(c) for c in classes)]
        if self.verdict.notes:
            lines += [""] + [f"Note: {x}" for x in self.verdict.notes]
        nulls = [(r.name, d) for r in self.ranking for d in r.no_signature_directions]
        if nulls:
            lines += ["", "No signature on this bench (a change of the coefficients along these "
                      "directions, in their units, leaves the record as it was): "
                      + "; ".join(f"{d} ({n})" for n, d in nulls)]
        conf = [(r.name, d) for r in self.ranking for d in r.confounded_directions]
        if conf:
            lines += ["", "Absorbed by the nominal parameters (a change along these directions "
                      "is fitted away by them: visible fraction < 1e-6): "
                      + "; ".join(f"{d} ({n})" for n, d in conf)]
        if self.refits:
            lines += ["", "## How much (refit on train, gap on held-out)", "",
                      "| effects | estimate ± std. error | held-out gap before | after | "
                      "reduction | closure | cells left |", "|---|---|---|---|---|---|---|"]
            no_sig = {d for r in self.ranking for d in r.no_signature_directions}
            for rf in self.refits:
                red = f"{rf.reduction:.2f}" if rf.reduction is not None else "-"
                se, un = rf.std_errors, rf.units
                # a coefficient the rows do not determine (infinite standard error) is named
                # once, not printed as a value: without a signature on this bench, or one whose
                # other directions have none or are absorbed by the nominal parameters, when
                # only the combinations printed with the values are determined
                undetermined = [k for k in rf.coefficients
                                if not math.isfinite(se.get(k, 0.0))]
                blind = [k for k in undetermined if k in no_sig]
                partial = [k for k in undetermined if k not in no_sig]
                est = ", ".join(
                    [f"{k} {v:.4g}" + (f" ± {se[k]:.2g}" if k in se else "")
                     + _unit_suffix(un.get(k))
                     for k, v in rf.coefficients.items() if k not in undetermined]
                    + [f"{x['combination']} {x['value']:.4g} ± {x['std_error']:.2g}"
                       + _unit_suffix(x["unit"]) for x in rf.estimable])
                if blind:
                    est += f"; no signature, not estimated: {', '.join(blind)}"
                if partial:
                    est += ("; determined only in the combinations given (their other "
                            "directions have no signature or are absorbed by the nominal "
                            f"parameters, as listed above): {', '.join(partial)}")
                lines.append(f"| {' + '.join(rf.effects)} | {est} | "
                             f"{rf.heldout_gap_before:.3g} | "
                             f"{rf.heldout_gap_after:.3g} | {red} | {rf.closure} | "
                             f"{len(rf.remaining_cells)} |")
        if self.conditional:
            c = self.conditional
            lines += ["", f"After {' + '.join(c['after'])}, the forward selection stopped: "
                      f"{c['stopped']}. Conditional score tests of the other effects, the "
                      "refitted ones' signatures projected out:", ""]
            lines += ["| effect | score | dof | p | p (Bonferroni) |", "|---|---|---|---|---|"]
            lines += [f"| {x['effect']} | {x['score']:.4g} | {x['dof']} | {x['p']:.2g} | "
                      f"{x['p_bonferroni']:.2g} |" for x in c["scores"]]
        if self.design_advice:
            shown, count = [], {}  # the best ADVICE_SHOWN designs per effect
            for a in self.design_advice:
                count[a["effect"]] = count.get(a["effect"], 0) + 1
                if count[a["effect"]] <= ADVICE_SHOWN:
                    shown.append(a)
            lines += ["", "## Design advice (MDE in prior scales, alone and with the closest "
                      f"rival effect fitted too; per effect the advised design first, the best "
                      f"{ADVICE_SHOWN} shown)", "",
                      "| effect | design | MDE / prior | MDE / prior vs closest rival | "
                      "max corr. with other effects |", "|---|---|---|---|---|"]
            for a in shown:
                lines.append(f"| {a['effect']} | {a['design']} | {_mde_text(a)} | "
                             f"{a['mde_vs_closest_rival']:.3g} | "
                             f"{a['max_correlation_with_other_effects']:.3f} |")
            unseen = {a["effect"]: a.get("unseen_dims", 0) for a in self.design_advice
                      if a.get("unseen_dims", 0)}
            if unseen:
                lines.append("\nNo catalogued design sees " + "; ".join(
                    f"{n} of {e}'s directions" for e, n in unseen.items()) + " (no signature, "
                    "or absorbed by the nominal parameters on every design): the MDEs are over "
                    "the rest.")
            if any(math.isinf(a["mde_over_prior"]) and 0 < a.get("seen_dims", 0)
                   for a in self.design_advice):
                lines.append("\nA design that sees only some of an effect's directions has an "
                             "infinite MDE (the rest stay undetectable on it); the count says how "
                             "many it sees. The directions counted are those the record or some "
                             "design sees: between them, the tests see them all.")
            if len(shown) < len(self.design_advice):
                lines.append(f"\n{len(self.design_advice) - len(shown)} more designs in the "
                             "JSON report (`design_advice`).")
        return "\n".join(lines)


def grid_interval(values, weights, mass: float = 0.9) -> tuple[float, float, float]:
    """The shortest run of consecutive grid ``values`` whose posterior ``weights`` hold at least
    ``mass``: ``(first value, last value, mass held)`` (ties: the run holding more)."""
    w = np.asarray(weights, float)
    w = w / w.sum()
    best = (len(w) + 1, 0.0, 0, len(w) - 1)
    for i in range(len(w)):
        acc = np.cumsum(w[i:])
        j = int(np.searchsorted(acc, mass - 1e-12))
        if j < len(acc) and (j + 1, -acc[j]) < (best[0], -best[1]):
            best = (j + 1, float(acc[j]), i, i + j)
    return float(values[best[2]]), float(values[best[3]]), best[1]


def _unit_suffix(unit: str | None) -> str:
    """`` unit`` after a value; nothing for a dimensionless one (``"1"``, e.g. the IMU's Earth
    rate factor)."""
    return f" {unit}" if unit and unit != "1" else ""


def _mde_text(a: dict) -> str:
    """A design advice row's MDE; where infinite, how many of the effect's directions (those
    some design sees) this design sees."""
    mde = a["mde_over_prior"]
    if not math.isinf(mde) or "seen_dims" not in a:
        return f"{mde:.3g}"
    seen = a["seen_dims"]
    return f"inf (sees {seen} of {a['kept_dims']} directions)" if seen else "inf (sees none)"


def _values_by_unit(values: dict, units: dict) -> str:
    """``{channel: value}`` as text, the channels sharing a unit in one group followed by it,
    e.g. ``wx 0.1, wy 0.2 arcsec; ax 0.3 m/s`` (gyro and accelerometer terms differ)."""
    groups: dict = {}
    for ch, v in values.items():
        groups.setdefault(units.get(ch, ""), []).append(f"{ch} {v:.3g}")
    return "; ".join(", ".join(g) + (f" {u}" if u else "") for u, g in groups.items())


def grid_located(values, weights, points_per_step: int = 64):
    """Where the posterior over a grid places the effect, to within one grid step: the centre
    ``c`` whose window of one grid step either side holds the most posterior mass. Returns
    ``(c, mass held, (window low, window high))``, the window ``None`` on a one-value grid. On
    a geometric grid (decay times) step and window are taken on the log scale: ``c / r .. c r``
    with ``r`` the grid's ratio.

    This is the Bayes decision for a one-step loss (right when within one step of the truth),
    the loss goal G8 scores, and differs from the grid value of the largest score where the
    posterior has several modes: a broad mode can hold more mass than a taller narrow one. The
    posterior between grid values is their weights interpolated linearly (each weight spread as
    a hat over one step either side), so ``c`` can fall between two grid values; it is searched
    on ``points_per_step`` points per step over the grid's span."""
    v = np.asarray(values, float)
    w = np.asarray(weights, float)
    if v.size < 2:  # one value: nothing to place
        return float(v[0]), 1.0, None
    geometric = bool(v[0] > 0 and np.ptp(np.diff(np.log(v))) < 1e-6 * np.ptp(np.diff(v)))
    x = np.log(v) if geometric else v
    s = float(np.median(np.diff(x)))
    c = np.linspace(x[0], x[-1], (v.size - 1) * points_per_step + 1)
    # one hat of half-width s integrated over the window c -+ s, as a function of u = |c - x|/s:
    # 1 - u^2/2 for u <= 1, (2 - u)^2/2 for 1 <= u <= 2
    u = np.abs(c[:, None] - x[None, :]) / s
    held = np.where(u <= 1, 1 - 0.5 * u**2, 0.5 * np.clip(2 - u, 0, None) ** 2) @ w / w.sum()
    i = int(np.argmax(held))
    lo, mid, hi = c[i] - s, c[i], c[i] + s
    if geometric:
        lo, mid, hi = np.exp(lo), np.exp(mid), np.exp(hi)
    return float(mid), float(held[i]), (float(lo), float(hi))


def _grid_text(r) -> str:
    g = r.grid
    lo, hi, held = grid_interval(g["values"], g["posterior"])
    unit = f" {g['unit']}" if g["unit"] else ""
    mode = int(np.argmax(g["posterior"]))
    win = g.get("located_window")
    located = "" if win is None else (
        f"located at {g['located']:.3g}{unit} (one grid step either side, {win[0]:.3g}-"
        f"{win[1]:.3g}{unit}, holds {g['located_mass']:.2f}), ")
    return (f"{r.name} {g['name']} {located}{g['best']:.3g}{unit} at the largest score, "
            f"posterior {g['posterior'][mode]:.2f} at {g['values'][mode]:.3g}{unit}, 90 % within "
            f"{lo:.3g}-{hi:.3g}{unit} (mass {held:.2f}), flag taken at {g['flag_at']:.3g}{unit}")
