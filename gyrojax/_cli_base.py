"""What every rig's command-line commands share: the interface the ``gyrojax`` command dispatches
through (:class:`AbstractRigCommands`), bad input as one line (:class:`UsageError`), and the edge
helpers (``--set`` in display units, ``--json``, record files)."""

from __future__ import annotations

import abc
import argparse
import sys
from pathlib import Path
from typing import ClassVar

import numpy as np

EXIT_USAGE = 2
# `fit` notes a residual RMS beyond this many times the record's sample-to-sample noise: a
# record in other units (hours for seconds) or a wrong scheme gives thousands, an unmodelled
# effect anything from 1 up (11 for a 300-arcsec base misalignment on a day's record)
MISFIT_RATIO = 10.0
SUB_STAGES = ("library_scores",)  # a part of the screening, timed apart for goal G10


class UsageError(Exception):
    """Bad user input: printed as one line, exit status 2."""


class AbstractRigCommands(abc.ABC):
    """A rig's side of the ``gyrojax`` command: the options it adds and the commands it serves.

    `COMMANDS` names the commands the rig serves (of ``simulate``, ``fit``, ``observability``,
    ``diagnose`` and the rig's own ``montecarlo``, ``demo``, ``observer``); any other with
    ``--rig NAME`` is refused with `ELSEWHERE`, where to go instead. :meth:`add_arguments`
    adds the rig's own options to a command's parser through :meth:`option` (they are refused
    with another ``--rig``); the command methods do the work and print. A command the rig does
    not serve is never called (the ``gyrojax`` command checks `COMMANDS` first)."""

    name: ClassVar[str]
    COMMANDS: ClassVar[tuple[str, ...]] = ()
    ELSEWHERE: ClassVar[str] = ""

    def add_arguments(self, command: str, group) -> None:
        """Add this rig's options of ``command`` to ``group`` (an argparse group), each by
        :meth:`option`. Default: none."""

    @staticmethod
    def option(group, *flags, **kwargs) -> None:
        """One rig option: ``group.add_argument`` with its default ``None`` unless given (a
        value differing from the default is how the ``gyrojax`` command tells it was set)."""
        group.add_argument(*flags, **kwargs)

    def refuse(self, command: str) -> UsageError:
        """The error for a command this rig does not serve: which rigs do, and where to go."""
        from . import rigs

        served = [n for n in rigs.names()
                  if rigs.get(n).commands and command in rigs.get(n).commands_object().COMMANDS]
        return UsageError(f"--rig {self.name!r}: gyrojax {command} serves --rig "
                          f"{', '.join(served)}"
                          + (f"; for {self.name} use {self.ELSEWHERE}" if self.ELSEWHERE else ""))

    def simulate(self, args) -> None:
        raise self.refuse("simulate")

    def fit(self, args) -> None:
        raise self.refuse("fit")

    def observability(self, args) -> None:
        raise self.refuse("observability")

    def load(self, args):
        """The record ``gyrojax diagnose`` reads (``args.record``) with the conditions its
        options give."""
        raise self.refuse("diagnose")

    def diagnose_options(self, args) -> dict:
        """The rig's diagnosis options (:attr:`gyrojax.diagnose.AbstractGapProblem.OPTIONS`)
        from its command-line options. Default: none."""
        return {}

    def noise_std(self, args):
        """The diagnosis' ``noise_std`` from ``--noise-arcsec`` (SI), or ``None``. Default: an
        angle in arcsec for every channel."""
        if args.noise_arcsec is None:
            return None
        from . import units

        return positive("--noise-arcsec", args.noise_arcsec) * units.ARCSEC


def misfit_note(ratio: float, noise: str, checks: str, record, rig: str) -> str | None:
    """``fit``'s note when its residual RMS is more than :data:`MISFIT_RATIO` times the record's
    sample-to-sample noise (``ratio``; ``noise`` the level as shown, from
    :func:`gyrojax.record.sample_noise`), naming what to ``check`` and the diagnosis to run."""
    if not ratio > MISFIT_RATIO:
        return None
    return (f"note: the residual RMS is {ratio:.3g} times the record's sample-to-sample noise "
            f"({noise}, from third differences): the model does not describe this record; check "
            f"{checks}, or see where it departs with: gyrojax diagnose {record} --rig {rig}")


def parse_sets(items, space) -> dict:
    """``--set NAME=VALUE`` options in display units (deg/h, arcsec, deg) -> SI values."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise UsageError(f"--set {item!r}: expected NAME=VALUE, e.g. --set m11=0.15")
        name, val = item.split("=", 1)
        name = name.strip()
        if name not in space:
            raise UsageError(f"--set: unknown parameter {name!r}; valid: {', '.join(space.names)}")
        try:
            out[name] = space[name].from_display(float(val))
        except ValueError:
            raise UsageError(f"--set {name}={val!r}: value must be a number in "
                             f"{space[name].display_unit}") from None
    return out


def emit_json(obj, dest) -> None:
    """``--json FILE`` (written atomically) or ``--json -`` (printed)."""
    from .io import json_text, write_json

    if dest == "-":
        print(json_text(obj))
    elif dest:
        write_json(obj, dest)
        print(f"wrote {dest}", file=sys.stderr)


def write_outputs(outputs) -> None:
    """``outputs`` (``(path, write_fn)`` pairs; ``path`` ``None``: not asked for) written all
    or none (:func:`gyrojax.io.write_together`), each named on stderr once written."""
    from .io import write_together

    outputs = [(path, fn) for path, fn in outputs if path]
    write_together(outputs)
    for path, _ in outputs:
        print(f"wrote {path}", file=sys.stderr)


OUTPUT_OPTIONS = ("out", "json", "plot", "netcdf")  # the options that name a file a command writes


def check_outputs(args, extra=()) -> None:
    """Every output file the command line names (``--out``, ``--json`` but ``-``, ``--plot``,
    and ``extra``: ``(option, path)`` pairs a command derives), checked before any work: a
    usage error naming the option and the fix where one cannot be written."""
    from .io import check_writable

    named = [(f"--{o}", getattr(args, o, None)) for o in OUTPUT_OPTIONS]
    for option, path in [*named, *extra]:
        if path and path != "-":
            try:
                check_writable(path, option)
            except ValueError as exc:
                raise UsageError(str(exc)) from None


def load(args, channels):
    """The record ``args.record`` with ``channels`` (``None``: any); a usage error names what is
    wrong with the file."""
    from .io import RecordFileError, load_record

    if args.record.startswith("dataset:") and not Path(args.record).exists():
        raise UsageError(f"{args.record}: the built-in real data sets are strapdown IMU records; "
                         f"use --rig imu, or give a record file (.nc or .csv) of the "
                         f"{args.rig} rig")
    from . import rigs
    from .io import check_channel_bounds

    try:
        record = load_record(args.record, channels=channels)
    except RecordFileError as exc:
        raise UsageError(str(exc) + _rig_hint(args, channels)) from None
    check_channel_bounds(record, rigs.get(args.rig).model_class.CHANNEL_BOUNDS)
    return record


def _rig_hint(args, channels) -> str:
    """Where a record lacks this rig's channels but has all of another registered rig's: a
    hint to give that ``--rig`` (an IMU's wx..az read as an ESG record)."""
    from . import rigs
    from .io import load_record

    if channels is None:
        return ""
    try:
        found = set(load_record(args.record).channels)
    except Exception:  # noqa: BLE001 - the first error is the one to report
        return ""
    for name in rigs.names():
        try:
            theirs = rigs.get(name).model_class().channels
        except Exception:  # noqa: BLE001 - a rig that needs arguments to build gives no hint
            continue
        if name != args.rig and set(theirs) <= found:
            article = "an" if name[0] in "aeiou" else "a"
            return f" (the columns are {article} {name} record's: add --rig {name})"
    return ""


def with_latitude(args, record):
    """``record`` with ``--latitude`` as its ``latitude_deg`` condition, where given."""
    if args.latitude is None:
        return record
    return record.with_conditions(latitude_deg=float(args.latitude))


def stage_printer(command):
    """Progress of a long command on stderr, one line per finished stage (a first call in a
    process spends most of its time compiling)."""
    def show(stage, seconds):
        if stage in SUB_STAGES:
            return
        what = "done in" if stage == "total" else stage.replace("_", " ")
        print(f"gyrojax {command}: {what} {seconds:.1f} s", file=sys.stderr, flush=True)
    return show


def positive(name, value):
    """``value`` if a positive finite number, else a usage error naming ``name``."""
    if value is None or not np.isfinite(value) or value <= 0:
        raise UsageError(f"{name} {value} must be a positive number")
    return value


def alpha0(text):
    """``--alpha0 A1,A2`` in deg."""
    try:
        a = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected two numbers 'A1,A2' in deg") from None
    if len(a) != 2:
        raise argparse.ArgumentTypeError(f"{text!r}: expected two numbers 'A1,A2' in deg")
    return a
