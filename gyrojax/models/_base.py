"""The rig interface shared by every instrument model."""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx

from ..params import ParameterSpace


class AbstractRig(eqx.Module):
    """A bench-test rig: equations of motion and measurement of one instrument on its stand.

    A rig is configuration only (static fields); numbers live in the parameter dict (see
    `gyrojax.params`) and in the rig's conditions module (latitude, mounting, schedule...),
    built on every rig by ``Conditions.create(...)`` from values and
    ``Conditions.from_record(record)`` from a record's attributes.

    Time inside a rig may be normalized: ``internal_time = t_seconds * rig.time_scale``.
    """

    # the largest magnitude a channel reaches on any bench this rig models, in SI, and the fix
    # for a record beyond it: {channel prefix: (limit, "fix")}; beyond it a record is in other
    # units or holds a corrupt cell (gyrojax.io.check_channel_bounds, before any fit)
    CHANNEL_BOUNDS: ClassVar[dict[str, tuple[float, str]]] = {}
    # each record channel's SI unit in CF notation ({channel prefix: unit}, e.g. "rad s-1"),
    # written into a NetCDF record's channel attributes
    CHANNEL_UNITS: ClassVar[dict[str, str]] = {}

    @property
    @abc.abstractmethod
    def param_space(self) -> ParameterSpace:
        """Every parameter the rig knows, nominal ones and effect groups with null values."""

    @property
    @abc.abstractmethod
    def channels(self) -> tuple[str, ...]:
        """Names of the measured channels (the BenchRecord columns)."""

    @property
    @abc.abstractmethod
    def time_scale(self) -> float:
        """Internal time units per second."""

    @abc.abstractmethod
    def initial_state(self, params, conditions):
        """State at the first sample time."""

    @abc.abstractmethod
    def vector_field(self, t, state, params, conditions):
        """d state / d internal time."""

    @abc.abstractmethod
    def observe(self, t, state, params, conditions):
        """Measured channels (noise-free) at internal time ``t``."""

    def jump_times(self, params, conditions):
        """Internal times where the vector field jumps (an array), or ``None``: the adaptive
        solver then steps to just before and just after each (``diffrax``'s ``jump_ts``). A jump
        whose amplitude is 0 still needs it: forward sensitivities see the jump in their own
        equations, which the step-size controller (primal error only) does not."""
        return None

    def step_times(self, params, conditions):
        """Internal times the adaptive solver must step to (an array), or ``None``
        (``diffrax``'s ``step_ts``): for a fast but smooth feature of the vector field, e.g. a
        rise over a minute in a record of hours, which forward sensitivities at zero amplitude
        see and the step-size controller (primal error only) does not."""
        return None
