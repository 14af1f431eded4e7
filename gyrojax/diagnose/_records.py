"""The report's typed records: a screened effect (:class:`Candidate`), a refit (:class:`Refit`)
and the verdict (:class:`Verdict`).

Each is a frozen dataclass with typed fields; its JSON (``to_json``) is written from the fields.
Each is also a read-only mapping from its field names to their values (``row["posterior"]``,
``row.get("grid")``), the names the report's JSON uses, so that code written against the JSON
reads a live report unchanged. Display units throughout (the units the fields name).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ._verdict import headline

__all__ = ["Candidate", "Refit", "Verdict", "json_clean"]

VERDICT_KINDS = ("no-gap", "attributed", "partial", "ambiguous", "confounded", "unexplained")


def json_clean(x):
    """JSON-safe: records -> dicts, numpy -> Python, non-finite -> None."""
    if isinstance(x, _Record):
        return x.to_json()
    if isinstance(x, dict):
        return {str(k): json_clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.ndarray):
        return json_clean(x.tolist())
    return x


class _Record(Mapping):
    """A frozen dataclass read as a mapping of its fields (no item assignment: the record is
    immutable; :func:`dataclasses.replace` makes a changed copy)."""

    def __getitem__(self, key: str) -> Any:
        if key not in self._names():
            raise KeyError(f"{type(self).__name__} has no field {key!r}; it has {self._names()}")
        return getattr(self, key)

    def __iter__(self):
        return iter(self._names())

    def __len__(self) -> int:
        return len(self._names())

    @classmethod
    def _names(cls) -> tuple:
        return tuple(f.name for f in dataclasses.fields(cls))

    def to_json(self) -> dict:
        """The record as JSON-safe data: every field, non-finite numbers as null."""
        return {k: json_clean(getattr(self, k)) for k in self._names()}


@dataclasses.dataclass(frozen=True, kw_only=True, eq=True)
class Candidate(_Record):
    """One catalogued effect as screened at the nominal fit.

    - ``name``, ``family``, ``kind`` (``"bias"``, ``"noise"``, ...), ``params`` and their
      ``units`` and ``prior_scale`` (display units).
    - ``score``, ``dof``, ``p``, ``q``: the efficient score test at the best grid value and its
      multiplicity-adjusted q-value (``None``: reported only); ``score_grid``, ``dof_grid`` at
      every grid value (one entry without a grid).
    - ``log_bf``, ``posterior``: the Bayes factor against no effect and the posterior share;
      ``log_bf_by_lambda``: the design prior's log Bayes factor at other expected
      noncentralities (keys ``f"{lambda:g}"``).
    - ``onestep``, ``onestep_se``: the one-step estimate of each coefficient and its standard
      error (display units).
    - ``grid``: ``None``, or the effect's grid (``name``, ``unit``, ``values``, ``best``,
      ``flag_at``, ``posterior``, ``located``, ``located_mass``, ``located_window``).
    - ``explained_gap_share`` (0-1), ``signature_consistency`` (cosine, NaN without time cells).
    - ``visible_fraction`` (0-1), ``identifiable``, ``flag`` (``"visible"``, ``"weakly
      identifiable"``, ``"partly no signature"``, ``"confounded"``, ``"no signature"`` ...),
      ``no_signature_directions`` and ``confounded_directions`` (named combinations),
      ``confounded_with`` (nominal parameters, strongest first) and ``aliases`` (per effect
      coefficient, the nominal coefficients that absorb it).
    - ``mde_over_prior``: the minimum detectable effect over its prior scale.
    """

    name: str
    family: str
    kind: str
    params: list[str]
    units: list[str]
    prior_scale: list[float]
    score: float
    dof: int
    p: float
    q: float | None
    score_grid: list[float]
    dof_grid: list[int]
    log_bf: float
    posterior: float
    log_bf_by_lambda: dict[str, float]
    onestep: dict[str, float]
    onestep_se: dict[str, float]
    grid: dict | None
    explained_gap_share: float
    signature_consistency: float
    visible_fraction: float
    identifiable: bool
    flag: str
    no_signature_directions: list[str]
    confounded_directions: list[str]
    confounded_with: list[str]
    aliases: list[dict]
    mde_over_prior: float


@dataclasses.dataclass(frozen=True, kw_only=True, eq=True)
class Refit(_Record):
    """The nominal model refitted with ``effects`` (each at its best grid value).

    - ``coefficients``, ``std_errors`` (``inf`` where the rows do not determine one),
      ``units``: per effect coefficient, display units; ``estimable``: the combinations of the
      undetermined coefficients that the rows do determine (``combination``, ``terms``,
      ``value``, ``std_error``, ``unit``); ``onestep``: each effect's one-step estimate.
    - ``nominal_after``: the nominal parameters refitted with them (display units).
    - ``gap_train_after``, ``heldout_gap_before``, ``heldout_gap_after`` (``None``/NaN without a
      held-out part), ``reduction`` (``None`` unless the held-out gap before lay above its null
      band), ``heldout_null_band_after`` (mean, upper 95 %), ``closure`` (the held-out gap
      after inside that band; ``None`` without a held-out part).
    - ``remaining_cells``: gap-map cells still significant after the refit.
    - ``screened``: False for the refits of ``refit_all`` beyond the screened candidates.
    - ``reading``: the rig's physical reading of the refit, where it has one (the IMU's
      Earth rate: size and heading per chain of poses, :meth:`IMUProblem.earth_reading`).
    """

    effects: list[str]
    coefficients: dict[str, float]
    std_errors: dict[str, float]
    estimable: list[dict]
    units: dict[str, str]
    nominal_after: dict[str, float]
    onestep: dict[str, dict[str, float]]
    gap_train_after: float
    heldout_gap_before: float
    heldout_gap_after: float | None
    reduction: float | None
    heldout_null_band_after: list[float]
    closure: bool | None
    remaining_cells: list[dict]
    screened: bool = True
    reading: dict | None = None


@dataclasses.dataclass(frozen=True, kw_only=True, eq=True)
class Verdict(_Record):
    """What the diagnosis concludes.

    - ``kind``: one of ``no-gap``, ``attributed``, ``partial``, ``ambiguous``, ``confounded``,
      ``unexplained``; ``effects``: the effects named (attributed: the cause, one effect or a
      set each of which earned its place after the others were fitted; partial: a set that
      explains most of the gap and leaves significant cells; ambiguous: the set it cannot tell
      apart, then the effects in ``also``; confounded: the effect the nominal parameters
      absorb; unexplained: the nearest effect, if any); ``reason``: why, in words (``None``
      for an attribution).
    - ``heldout_gap_before``, ``heldout_null_band`` and ``heldout_gap_after`` (the named
      effects' refit; ``None`` where none applies).
    - ``posterior`` and ``p`` over the ambiguity set (``None`` where not part of the verdict),
      ``cells``: the significant cells left (``unexplained``).
    - ``noise_effects``: significant noise-model effects, strongest first.
    - ``heldout_gap_after_by_effect``, ``heldout_separates``, ``heldout_leans``: what the
      held-out part says between the members of an ambiguous verdict (``None`` when nothing).
    - ``explained``: attributed and partial: the share of the gap each named effect explains,
      each after the ones before it (``of``: ``"held-out"`` where the held-out gap lies above
      its null band, else ``"train"``; ``shares``: effect -> share of the nominal model's gap,
      in the order they joined; ``total``); ``remainder``: where the significant cells left
      lie (axis, channels, time windows). :meth:`headline` says both in one line.
    - ``also``: ambiguous: the effects outside the set that earned their place after the
      refit of the set's top member (a conditional score test and, where the held-out part
      can show it, a lower held-out gap), as for an attribution's set.
    - ``notes``: the rig's notes on the record (units, noise model ...).
    """

    kind: str
    effects: list[str]
    heldout_gap_before: float | None
    heldout_null_band: list[float]
    heldout_gap_after: float | None = None
    reason: str | None = None
    posterior: dict[str, float] | None = None
    p: dict[str, float] | None = None
    cells: list[str] | None = None
    noise_effects: list[str] = dataclasses.field(default_factory=list)
    heldout_gap_after_by_effect: dict[str, float] | None = None
    heldout_separates: dict | None = None
    heldout_leans: dict | None = None
    notes: list[str] = dataclasses.field(default_factory=list)
    explained: dict | None = None
    remainder: str | None = None
    also: list[str] = dataclasses.field(default_factory=list)

    def headline(self) -> str | None:
        """"earth_rate explains 99.8 % of the held-out gap; remainder: ..." for an attributed
        or partial verdict that measured its shares; ``None`` otherwise."""
        return headline(self)

    def __post_init__(self):
        if self.kind not in VERDICT_KINDS:
            raise ValueError(f"verdict kind {self.kind!r} is none of {VERDICT_KINDS}")
