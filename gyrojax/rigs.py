"""The rig registry: every rig of gyrojax, by its ``--rig`` name, in one place.

A rig is one :class:`RigEntry`: its model and conditions classes, its diagnosis problem (an
:class:`~gyrojax.diagnose.AbstractGapProblem`, or none), and its command-line commands (an
:class:`~gyrojax.cli.AbstractRigCommands`). The command line (``gyrojax simulate|fit|
observability|diagnose|effects --rig NAME``) and :func:`gyrojax.diagnose.diagnose` dispatch
through :func:`get`; adding a rig is one :func:`register` call and edits no other file's
dispatch (``tests/toy_rig.py`` adds a sixth rig that way).

Entries name their classes as ``"module:attribute"`` strings, imported on first use, so the
registry itself imports nothing heavy.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any

__all__ = ["RigEntry", "get", "names", "register", "unregister"]


def _resolve(path: str) -> Any:
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


@dataclasses.dataclass(frozen=True)
class RigEntry:
    """One rig.

    - `name`: the ``--rig`` name; `summary`: one line for ``--help``.
    - `model`: its model class (an :class:`~gyrojax.models.AbstractRig`), ``"module:Class"``:
      its record channels (``channels``) with their SI units (``CHANNEL_UNITS``, read by
      :meth:`channel_units`) and bounds (``CHANNEL_BOUNDS``).
    - `conditions`: its test-conditions class (``create(...)`` from values, ``from_record``
      from a record's attributes).
    - `problem`: its diagnosis problem class, or ``None`` (no ``gyrojax diagnose --rig``).
    - `commands`: its command-line commands class (``simulate``, ``fit``, ``observability``,
      loading a record for ``diagnose``), or ``None``.
    """

    name: str
    summary: str
    model: str
    conditions: str
    problem: str | None = None
    commands: str | None = None

    @property
    def model_class(self):
        return _resolve(self.model)

    def channel_units(self, channels=None) -> dict:
        """Each record channel's SI unit in CF notation (the model's ``CHANNEL_UNITS``):
        ``{channel: unit}`` over ``channels`` (default: the model's own)."""
        table = self.model_class.CHANNEL_UNITS
        channels = self.model_class().channels if channels is None else channels
        from .io import by_channel

        return {c: by_channel(table, c, "SI") for c in channels}

    @property
    def conditions_class(self):
        return _resolve(self.conditions)

    @property
    def problem_class(self):
        """The diagnosis problem class; a clear error where the rig has none."""
        if self.problem is None:
            raise ValueError(f"--rig {self.name} has no diagnosis; rigs with one: "
                             f"{', '.join(n for n in names() if get(n).problem)}")
        return _resolve(self.problem)

    def commands_object(self):
        """The rig's command-line commands (an instance)."""
        if self.commands is None:
            raise ValueError(f"--rig {self.name} has no command-line commands")
        return _resolve(self.commands)()

    def check_options(self, options: dict) -> None:
        """A clear error for a diagnosis option the rig's problem does not take."""
        known = self.problem_class.OPTIONS
        bad = [k for k in options if k not in known]
        if bad:
            takes = (f"it takes {', '.join(known)}" if known else "it takes none")
            raise ValueError(f"option(s) {', '.join(bad)} are not for --rig {self.name} ({takes}); "
                             "leave them out")

    def catalogue(self, **options) -> dict:
        """The diagnosis catalogue under these options: ``{effect: family}``."""
        self.check_options(options)
        return self.problem_class.catalogue(**options)

    def problem_for(self, record, *, holdout: float = 0.25, noise_std=None, effects=None,
                    **options):
        """The rig's diagnosis problem of ``record`` (options checked here, validated by the
        problem's constructor)."""
        self.check_options(options)
        return self.problem_class(record, holdout=holdout, noise_std=noise_std,
                                  effects=effects, **options)


_REGISTRY: dict[str, RigEntry] = {}


def register(entry: RigEntry, *, replace: bool = False) -> RigEntry:
    """Add a rig (``replace``: over an entry of the same name)."""
    if entry.name in _REGISTRY and not replace:
        raise ValueError(f"rig {entry.name!r} is registered already; pass replace=True")
    _REGISTRY[entry.name] = entry
    return entry


def unregister(name: str) -> None:
    """Remove a rig (a test's)."""
    _REGISTRY.pop(name, None)


def names() -> tuple[str, ...]:
    """The registered rigs' names, in registration order."""
    return tuple(_REGISTRY)


def get(rig) -> RigEntry:
    """The registered rig ``rig``: its name (``"esg"``), or its model, as an object
    (``ESGRig()``, what :func:`gyrojax.fit` and :func:`gyrojax.simulate` take) or a class.

    **Raises:** `ValueError` naming the registered rigs when none is ``rig``."""
    if isinstance(rig, str):
        try:
            return _REGISTRY[rig]
        except KeyError:
            raise ValueError(f"unknown rig {rig!r}; rigs: {', '.join(_REGISTRY)}") from None
    cls = rig if isinstance(rig, type) else type(rig)
    for entry in _REGISTRY.values():
        if issubclass(cls, entry.model_class):
            return entry
    raise ValueError(f"no registered rig has the model {cls.__name__}; rigs: "
                     f"{', '.join(_REGISTRY)} (gyrojax.rigs.register adds one)")


register(RigEntry(
    "esg", "non-contact (electrostatic) gyro in a two-axis gyrostabilizer (default)",
    "gyrojax.models.esg:ESGRig", "gyrojax.models.esg:ESGConditions",
    "gyrojax.diagnose._esg:ESGProblem", "gyrojax._cli_esg:ESGCommands"))
register(RigEntry(
    "schuler", "platform INS in the Schuler test",
    "gyrojax.models.schuler:SchulerRig", "gyrojax.models.schuler:SchulerConditions",
    "gyrojax.diagnose._schuler:SchulerProblem", "gyrojax._cli_schuler:SchulerCommands"))
register(RigEntry(
    "platform", "three-gimbal platform under vibration",
    "gyrojax.models.platform:PlatformRig", "gyrojax.models.platform:PlatformConditions",
    "gyrojax.diagnose._platform:PlatformProblem", "gyrojax._cli_platform:PlatformCommands"))
register(RigEntry(
    "imu", "strapdown IMU on a stand (fit: multi-position calibration; diagnose)",
    "gyrojax.models.imu:IMURig", "gyrojax.models.imu:IMUConditions",
    "gyrojax.diagnose._imu:IMUProblem", "gyrojax._cli_imu:IMUCommands"))
register(RigEntry(
    "gyrotheodolite", "gyrotheodolite north-seeking run (simulate and diagnose)",
    "gyrojax.models.gyrotheodolite:GyrotheodoliteRig",
    "gyrojax.models.gyrotheodolite:GyrotheodoliteConditions",
    "gyrojax.diagnose._gyrotheodolite:GyrotheodoliteProblem",
    "gyrojax._cli_gyrotheodolite:GyrotheodoliteCommands"))
