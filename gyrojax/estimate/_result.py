"""Shared behaviour of estimator results: named values and standard errors."""

from __future__ import annotations

import equinox as eqx
import jax


class AbstractNamedEstimate(eqx.Module):
    """An estimate of named parameters: ``names`` (static), ``values`` and ``stderr`` with the
    parameter axis last (leading batch axes allowed)."""

    names: eqx.AbstractVar[tuple[str, ...]]
    values: eqx.AbstractVar[jax.Array]
    stderr: eqx.AbstractVar[jax.Array]

    def as_dict(self) -> dict:
        """``{name: value}`` (internal units)."""
        return {n: self.values[..., i] for i, n in enumerate(self.names)}

    def stderr_dict(self) -> dict:
        """``{name: standard error}`` (internal units)."""
        return {n: self.stderr[..., i] for i, n in enumerate(self.names)}
