"""Named parameter sets: names, units, scales, null values, effects, free/frozen masks.

A rig's parameters are a plain ``dict[str, Array]`` (a pytree, so it batches with ``vmap`` and
differentiates with ``jax.jacfwd``), values in the rig's internal units (SI or normalized). The
static :class:`ParameterSpace` describes them: each :class:`Param` has a unit, a display unit for
reports, a typical scale (for column scaling of Jacobians and the optimiser), a null value (the value
that switches its effect off) and the effect group it belongs to (``None`` for the nominal model).

``flatten(params, free)`` gives the vector of the free parameters divided by their scales;
``unflatten(vector, base, free)`` puts such a vector back into a copy of ``base``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping, Sequence

import jax.numpy as jnp
import numpy as np

from . import units


@dataclasses.dataclass(frozen=True)
class Param:
    """One named parameter.

    **Arguments:**
    - `name`: the paper's symbol (``m11``, ``theta1``, ``eps2``...).
    - `unit`: internal unit of the stored value (``"1"`` normalized, ``"rad"``, ``"rad/s"``, ...).
    - `display_unit`: unit used in reports (``"deg/h"``, ``"arcsec"``...); see `gyrojax.units`.
    - `display_factor`: internal value = display value * display_factor.
    - `scale`: typical magnitude in the internal unit (used for scaling, priors and Monte Carlo).
    - `null`: value at which the parameter has no effect.
    - `effect`: name of the effect group, or ``None`` for nominal parameters.
    - `description`: one line for ``--help`` and reports.
    """

    name: str
    unit: str
    display_unit: str
    display_factor: float
    scale: float
    null: float = 0.0
    effect: str | None = None
    description: str = ""

    def to_display(self, value):
        return value / self.display_factor

    def from_display(self, value):
        return value * self.display_factor


@dataclasses.dataclass(frozen=True)
class ParameterSpace:
    """An ordered, hashable collection of :class:`Param` (safe as a static field under jit)."""

    params: tuple[Param, ...]

    def __post_init__(self):
        names = [p.name for p in self.params]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"duplicate parameter names {sorted(dup)}")

    # -- lookup -----------------------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def __getitem__(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(f"unknown parameter {name!r}; this rig has: {', '.join(self.names)}")

    def __contains__(self, name: str) -> bool:
        return name in self.names

    def __len__(self) -> int:
        return len(self.params)

    @property
    def effects(self) -> tuple[str, ...]:
        """Effect group names in order of first appearance."""
        seen: list[str] = []
        for p in self.params:
            if p.effect is not None and p.effect not in seen:
                seen.append(p.effect)
        return tuple(seen)

    def effect_names(self, effect: str) -> tuple[str, ...]:
        if effect not in self.effects:
            raise ValueError(
                f"unknown effect {effect!r}; this rig's effects are: {', '.join(self.effects)}")
        return tuple(p.name for p in self.params if p.effect == effect)

    def nominal_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params if p.effect is None)

    def check_names(self, names: Iterable[str], what: str = "parameter") -> tuple[str, ...]:
        names = tuple(names)
        bad = [n for n in names if n not in self.names]
        if bad:
            raise ValueError(f"unknown {what} name(s) {bad}; valid names: {', '.join(self.names)}")
        return names

    def free_names(self, effects: Sequence[str] = (), *, nominal: bool | Sequence[str] = True,
                   exclude: Sequence[str] = ()) -> tuple[str, ...]:
        """Names of the free parameters: the nominal ones plus those of ``effects``, in space order."""
        chosen = set()
        if nominal is True:
            chosen |= set(self.nominal_names())
        elif nominal:
            chosen |= set(self.check_names(nominal))
        for e in effects:
            chosen |= set(self.effect_names(e))
        self.check_names(exclude)
        return tuple(n for n in self.names if n in chosen and n not in exclude)

    # -- values -----------------------------------------------------------------------------
    def null_values(self) -> dict:
        """All parameters at their null values (jnp float64 scalars)."""
        return {p.name: jnp.asarray(p.null, dtype=float) for p in self.params}

    def make(self, values: Mapping[str, float] | None = None, *, display: bool = False,
             **kwargs) -> dict:
        """A full parameter dict: null values overridden by ``values`` / keyword arguments.

        With ``display=True`` the given values are in display units (deg/h, arcsec...).
        """
        given = dict(values or {}) | kwargs
        self.check_names(given)
        out = self.null_values()
        for k, v in given.items():
            v = jnp.asarray(v, dtype=float)
            out[k] = self[k].from_display(v) if display else v
        return out

    def scales(self, names: Sequence[str]) -> np.ndarray:
        return np.array([self[n].scale for n in names])

    def flatten(self, params: Mapping, free: Sequence[str]):
        """Vector of ``params[free] / scale`` (stacked along the last axis)."""
        sc = self.scales(free)
        return jnp.stack([jnp.asarray(params[n]) / s for n, s in zip(free, sc)], axis=-1)

    def unflatten(self, vector, base: Mapping, free: Sequence[str]) -> dict:
        """Inverse of :meth:`flatten`: a copy of ``base`` with the free entries from ``vector``."""
        sc = self.scales(free)
        out = dict(base)
        for i, (n, s) in enumerate(zip(free, sc)):
            out[n] = vector[..., i] * s
        return out

    def to_display(self, params: Mapping) -> dict:
        return {k: np.asarray(self[k].to_display(v)) for k, v in params.items() if k in self}

    def display_json(self, params: Mapping, names: Iterable[str]) -> dict:
        """``{name: {"value": v, "unit": u}}`` in display units: the parameters of a written
        record, as the CLI's ``--json`` reports them."""
        return {k: {"value": float(self[k].to_display(params[k])), "unit": self[k].display_unit}
                for k in names}

    def table(self, params: Mapping, stderr: Mapping | None = None, names=None) -> str:
        """Human-readable table in display units."""
        names = names or [n for n in self.names if n in params]
        rows = [f"{'parameter':<12} {'value':>14} {'stderr':>12}  unit"]
        for n in names:
            p = self[n]
            v = float(np.asarray(p.to_display(params[n])).reshape(-1)[0])
            s = "" if stderr is None or n not in stderr else \
                f"{float(np.asarray(p.to_display(stderr[n])).reshape(-1)[0]):12.4g}"
            rows.append(f"{n:<12} {v:14.6g} {s:>12}  {p.display_unit}")
        return "\n".join(rows)


def param(name, unit, display_unit, scale, *, null=0.0, effect=None, description=""):
    """Shorthand constructor taking the display unit's factor from `gyrojax.units`."""
    return Param(name=name, unit=unit, display_unit=display_unit,
                 display_factor=float(units.from_unit(1.0, display_unit)), scale=float(scale),
                 null=float(null), effect=effect, description=description)
