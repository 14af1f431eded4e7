"""BenchRecord <-> NetCDF / CSV files, xarray data sets and pandas data frames, validated at the
boundary, written atomically.

Contract: time ``t`` in s, strictly increasing (first CSV column); one column or
variable per channel in SI units; test conditions as NetCDF attributes (CSV: command-line options).
Every problem raises :class:`RecordFileError` naming the file, the field or line, the value and the
fix. Files are written to a temporary file in the target folder and renamed, so a failed write never
leaves a half file.
"""

from __future__ import annotations

import csv
import json
import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .record import BenchRecord, freeze

if TYPE_CHECKING:
    import pandas as pd
    import xarray as xr

__all__ = ["RecordFileError", "load_record", "save_record", "validate_samples", "atomic_write",
           "write_json", "json_text", "check_times", "to_xarray", "from_xarray", "to_pandas",
           "from_pandas"]

MIN_SAMPLES = 3
MAX_SPAN_S = 1e9  # s (~32 years): no bench record spans more (epoch times are fine: t0 is free)


class RecordFileError(ValueError):
    """A record file or array failed validation; the message names the problem and the fix."""


def check_times(t, *, source: str = "record", min_samples: int = MIN_SAMPLES) -> np.ndarray:
    """Sample times as a record must have them: 1-D, at least ``min_samples``, finite, strictly
    increasing. Returns them as a float64 numpy array."""
    t = np.asarray(t, dtype=float)
    if t.ndim != 1:
        raise RecordFileError(f"{source}: t must be one-dimensional, got shape {t.shape}")
    if t.shape[0] < min_samples:
        raise RecordFileError(f"{source}: {t.shape[0]} samples is too few; a bench test needs at "
                              f"least {min_samples} samples (record longer or sample faster)")
    bad_t = np.where(~np.isfinite(t))[0]
    if bad_t.size:
        raise RecordFileError(f"{source}: t has non-finite value {t[bad_t[0]]} at sample "
                              f"{bad_t[0]}; remove or fill that sample")
    bad = np.where(np.diff(t) <= 0)[0]
    if bad.size:
        i = int(bad[0])
        raise RecordFileError(f"{source}: t must be strictly increasing but t[{i}]={t[i]} and "
                              f"t[{i + 1}]={t[i + 1]}; sort the samples and drop duplicates")
    span = float(t[-1] - t[0])
    if span > MAX_SPAN_S:
        i = int(np.argmax(np.diff(t)))
        raise RecordFileError(f"{source}: t spans {span:.3g} s ({span / 3.15576e7:.3g} years), "
                              f"the largest step from t[{i}]={t[i]:.6g} to t[{i + 1}]="
                              f"{t[i + 1]:.6g}: not a bench test's times in seconds; check t's "
                              "unit (s) and that no cell is corrupt")
    return t


def validate_samples(t, y, channels: Sequence[str], *, source: str = "record",
                     min_samples: int = MIN_SAMPLES):
    """Check time and channel arrays; returns them as float64 numpy arrays."""
    t = check_times(t, source=source, min_samples=min_samples)
    y = np.asarray(y, dtype=float)
    if y.ndim != 2 or y.shape != (t.shape[0], len(channels)):
        raise RecordFileError(f"{source}: channels have shape {y.shape}, expected "
                              f"({t.shape[0]}, {len(channels)}) for channels {list(channels)}")
    for j, name in enumerate(channels):
        badc = np.where(~np.isfinite(y[:, j]))[0]
        if badc.size:
            i = int(badc[0])
            raise RecordFileError(f"{source}: channel {name!r} has non-finite value {y[i, j]} at "
                                  f"sample {i} (t={t[i]}); gyrojax does not drop samples silently "
                                  "— remove or interpolate them before fitting")
    return t, y


def check_radians(y, channels: Sequence[str], limit: float, why: str, convert=None):
    """Refuse angle channels ``y`` ``(n, k)`` (named ``channels``) that reach ``limit`` rad, the
    edge of the model's range (``why``): such a record is in other units (deg, arcsec), and the
    fits read it as a trajectory far outside the model or as a scaled copy of one. The fix names
    the channels ``convert`` (default: ``channels``)."""
    peak = np.max(np.abs(np.asarray(y, float)), axis=0)
    over = [(c, float(v)) for c, v in zip(channels, np.atleast_1d(peak)) if v >= limit]
    if over:
        c, v = over[0]
        raise ValueError(f"the record's {c} reaches {v:.6g}, beyond {why} ({limit:.4g} rad), so "
                         f"it is not in radians; gyrojax records are SI: convert "
                         f"{' '.join(convert or channels)} to rad (from deg: x 0.0174533; from "
                         "arcsec: x 4.84814e-6)")


def by_channel(table, channel: str, default=None):
    """The entry of ``table`` (``{channel prefix: value}``, a rig's ``CHANNEL_BOUNDS``,
    ``CHANNEL_UNITS`` or ``NOISE_UNITS``) for ``channel``: the first prefix it starts with, or
    ``default``."""
    return next((v for prefix, v in table.items() if channel.startswith(prefix)), default)


def check_channel_bounds(record, bounds) -> None:
    """Refuse a record whose channels reach beyond ``bounds`` (a rig's ``CHANNEL_BOUNDS``:
    ``{channel prefix: (largest magnitude in SI, the fix)}``).

    **Raises:** `ValueError` naming the channel, the sample, its value, the bound and the fix."""
    y = np.asarray(record.y, float)
    for j, name in enumerate(record.channels):
        bound = by_channel(bounds, name)
        if bound is None or y.ndim != 2:
            continue
        limit, fix = bound
        i = int(np.argmax(np.abs(y[:, j])))
        if abs(y[i, j]) > limit:
            raise ValueError(f"the record's {name} reaches {y[i, j]:.4g} at sample {i} "
                             f"(t={float(np.asarray(record.t)[i]):.6g} s), beyond what a bench "
                             f"gives ({limit:g} in SI): {fix}, or remove the corrupt sample")


def _check_channels(channels, expected, source):
    if expected is None:
        return
    missing = [c for c in expected if c not in channels]
    if missing:
        raise RecordFileError(f"{source}: missing channel(s) {missing}; found {list(channels)}. "
                              f"This rig needs columns {list(expected)} (SI units)")


def load_record(source: str | os.PathLike | xr.Dataset | pd.DataFrame, *,
                channels: Sequence[str] | None = None,
                conditions: Mapping | None = None) -> BenchRecord:
    """Read a BenchRecord from a ``.nc`` or ``.csv`` file, an ``xarray.Dataset`` or a
    ``pandas.DataFrame`` (:func:`from_xarray`, :func:`from_pandas`).

    **Arguments:**
    - `source`: the file's path, or the data set / data frame.
    - `channels`: channel names the caller needs (e.g. ``rig.channels``); others are ignored,
      missing ones are an error. ``None`` keeps every column after ``t``.
    - `conditions`: test conditions to set or override (CSV files carry none).

    **Raises:** :class:`RecordFileError` with the file, the problem and the fix; ``TypeError``
    for a source of another kind.
    """
    kind = _in_memory_kind(source)
    if kind == "xarray":
        return from_xarray(source, channels=channels, conditions=conditions)
    if kind == "pandas":
        return from_pandas(source, channels=channels, conditions=conditions)
    if not isinstance(source, (str, os.PathLike)):
        raise TypeError(f"load_record: got a {type(source).__name__}; give a .nc or .csv file's "
                        "path, an xarray.Dataset or a pandas.DataFrame")
    path = Path(source)
    src = str(path)
    if not path.exists():
        raise RecordFileError(f"{src}: no such file; check the path (relative paths are taken from "
                              f"{os.getcwd()})")
    if path.is_dir():
        raise RecordFileError(f"{src} is a folder, not a record file; give the .nc or .csv file "
                              "in it")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        t, cols, names, attrs = _read_csv(path)
    elif suffix in (".nc", ".nc4", ".netcdf"):
        t, cols, names, attrs = _read_netcdf(path)
    else:
        raise RecordFileError(f"{src}: unknown file type {suffix!r}; use .nc (NetCDF) or .csv")
    return _record(t, cols, names, attrs, src, channels, conditions)


def _in_memory_kind(source) -> str | None:
    """``"xarray"`` or ``"pandas"`` for a data set or data frame (checked by module, so neither
    library is imported for a path)."""
    mod = type(source).__module__
    if mod.startswith("xarray") and type(source).__name__ == "Dataset":
        return "xarray"
    if mod.startswith("pandas") and type(source).__name__ == "DataFrame":
        return "pandas"
    return None


def _record(t, cols, names, attrs, src, channels, conditions) -> BenchRecord:
    """The record from a source's time, channel columns, names and attributes: every check a
    file gets, whatever it was read from."""
    if not names:
        raise RecordFileError(f"{src}: no channel after t; a record holds t and at least one "
                              "channel (e.g. t,alpha1,alpha2)")
    if "" in names:
        raise RecordFileError(f"{src}: column {names.index('') + 2} has no name; name every "
                              "channel in the header")
    twice = sorted({c for c in names if names.count(c) > 1})
    if twice:  # not one of them dropped unseen
        raise RecordFileError(f"{src}: channel(s) {twice} appear more than once; name each "
                              "column once")
    _check_channels(names, channels, src)
    keep = list(channels) if channels is not None else names
    y = np.stack([cols[names.index(c)] for c in keep], axis=-1)
    t, y = validate_samples(t, y, keep, source=src)
    attrs = _checked_conditions(dict(attrs), src) | dict(conditions or {})
    return BenchRecord(t, y, tuple(keep), freeze(attrs))


def _single(record: BenchRecord, what: str) -> None:
    if record.t.ndim != 1:
        raise ValueError(f"{what}: record is batched (t.shape={record.t.shape}); convert one "
                         "record at a time (record[i])")


def to_xarray(record: BenchRecord, *, units: Mapping[str, str] | None = None):
    """The (single) record as an ``xarray.Dataset``: one variable per channel over the time
    coordinate ``t`` (``units = "s"``), each channel's CF ``units`` from `units` (``{channel
    prefix: unit}``, a rig's ``CHANNEL_UNITS``; ``"SI"`` where it names none), the test
    conditions as attributes (a tuple as a JSON list). What :func:`save_record` writes."""
    import xarray as xr

    _single(record, "to_xarray")
    t, y = np.asarray(record.t), np.asarray(record.y)
    ds = xr.Dataset({c: ("t", y[:, j]) for j, c in enumerate(record.channels)},
                    coords={"t": ("t", t, {"units": "s"})})
    for c in record.channels:
        ds[c].attrs["units"] = by_channel(units or {}, c, "SI")
    ds.attrs.update({k: (v if isinstance(v, (int, float, str)) else json.dumps(v))
                     for k, v in record.conditions.items()})
    return ds


def from_xarray(ds, *, channels: Sequence[str] | None = None,
                conditions: Mapping | None = None) -> BenchRecord:
    """A record from an ``xarray.Dataset`` with a time coordinate ``t`` (s) and one variable per
    channel over it (SI units), its attributes the test conditions; checked as a NetCDF file is
    (:func:`load_record`'s arguments and errors)."""
    src = "xarray.Dataset"
    return _record(*_dataset_columns(ds, src), src, channels, conditions)


def to_pandas(record: BenchRecord):
    """The (single) record as a ``pandas.DataFrame``: index ``t`` (s), one column per channel
    (SI units), the test conditions in ``DataFrame.attrs``."""
    import pandas as pd

    _single(record, "to_pandas")
    df = pd.DataFrame(np.asarray(record.y), columns=list(record.channels),
                      index=pd.Index(np.asarray(record.t), name="t"))
    df.attrs.update(record.conditions)
    return df


def from_pandas(df, *, channels: Sequence[str] | None = None,
                conditions: Mapping | None = None) -> BenchRecord:
    """A record from a ``pandas.DataFrame``: the times (s) in a column ``t`` or an index named
    ``t``, one column per channel (SI units), the test conditions from ``DataFrame.attrs``;
    checked as a CSV file is (:func:`load_record`'s arguments and errors)."""
    src = "pandas.DataFrame"
    if "t" in df.columns:
        t, data = df["t"], df.drop(columns="t")
    elif df.index.name == "t":
        t, data = df.index, df
    else:
        raise RecordFileError(f"{src}: no time column or index 't'; name the times 't' (s), "
                              "e.g. df.rename_axis('t')")
    names = [str(c) for c in data.columns]
    cols = []
    for c in data.columns:
        try:
            cols.append(np.asarray(data[c], dtype=float))
        except (TypeError, ValueError):
            raise RecordFileError(f"{src}: channel {str(c)!r} holds {data[c].dtype} values, "
                                  "not numbers; give channels as floats in SI units") from None
    try:
        t = np.asarray(t, dtype=float)
    except (TypeError, ValueError):
        raise RecordFileError(f"{src}: t holds {t.dtype} values, not numbers; give the times "
                              "in s (from timestamps: (ts - ts[0]).total_seconds())") from None
    return _record(t, cols, names, dict(df.attrs), src, channels, conditions)


# test conditions a record file may carry that must be one finite number each (units in the
# name: deg, g; v10, v20 in m/s; g in m/s^2)
NUMERIC_CONDITIONS = ("latitude_deg", "azimuth0_deg", "a0_g", "g", "v10", "v20")


def _checked_conditions(attrs: dict, src: str) -> dict:
    """The numeric test conditions of a record file checked: one finite number each (a
    latitude within [-90, 90] deg). A :class:`RecordFileError` names the file, the attribute,
    its value and the fix."""
    for key in NUMERIC_CONDITIONS:
        if key not in attrs:
            continue
        v = attrs[key]
        arr = np.asarray(v)
        if arr.ndim != 0 or arr.dtype.kind not in "iuf":
            what = (f"{arr.size} values" if arr.ndim else f"{v!r}, not a number")
            raise RecordFileError(f"{src}: attribute {key} is {what}; set it to one number "
                                  f"({key} in the units its name gives, e.g. latitude_deg = "
                                  "55.75)")
        x = float(arr)
        if np.isinf(x):  # NaN is "not known" (an IMU record's latitude without --latitude)
            raise RecordFileError(f"{src}: attribute {key} is {x}; set it to a finite number "
                                  "(or leave it out where it is not known)")
        if key == "latitude_deg" and abs(x) > 90.0:
            raise RecordFileError(f"{src}: attribute latitude_deg = {x:g} is outside [-90, 90]; "
                                  "set the test site's latitude in deg")
        attrs[key] = x
    return attrs


def _read_csv(path: Path):
    try:
        return _read_csv_text(path)
    except UnicodeDecodeError as exc:
        raise RecordFileError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason}); save the "
                              "CSV as UTF-8 (plain ASCII numbers and names)") from None


def _read_csv_text(path: Path):
    # utf-8-sig: a spreadsheet's "CSV UTF-8" starts with a byte-order mark, which is not data
    with open(path, newline="", encoding="utf-8-sig") as fh:
        first = fh.readline()
        fh.seek(0)
        if first.startswith("\ufeff"):
            first = first[1:]
        # a spreadsheet in a locale with decimal commas writes ';'-separated files, and some
        # tools tab-separated ones: the header says which
        delimiter = next((d for d in (",", ";", "\t") if d in first), ",")
        reader = csv.reader(fh, delimiter=delimiter)
        try:
            header = next(reader)
        except StopIteration:
            raise RecordFileError(f"{path}: the file is empty; expected a header row "
                                  "'t,<channel>,...' and data rows") from None
        header = [h.strip().lstrip("\ufeff") for h in header]
        if not header or header[0] != "t":
            raise RecordFileError(f"{path}: line 1: the first column must be 't' (time in s), "
                                  f"got {header[:1]}; add a header row 't,<channel>,...'")
        data = _read_csv_fast(path, delimiter, len(header))
        if data is not None:
            names = header[1:]
            return data[:, 0], [data[:, j + 1] for j in range(len(names))], names, {}
        rows = []
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise RecordFileError(f"{path}: line {lineno}: {len(row)} columns but the header has "
                                      f"{len(header)} ({','.join(header)}); fix the row")
            try:
                rows.append([float(c) for c in row])
            except ValueError:
                bad = next(c for c in row if not _is_float(c))
                if _is_float(bad.replace(",", ".")):
                    raise RecordFileError(
                        f"{path}: line {lineno}: {bad!r} has a decimal comma; write numbers "
                        "with a decimal point (1.5, not 1,5)") from None
                raise RecordFileError(f"{path}: line {lineno}: non-numeric value {bad!r}; every "
                                      "data cell must be a number in SI units") from None
    if not rows:
        raise RecordFileError(f"{path}: no data rows after the header")
    data = np.asarray(rows, dtype=float)
    names = header[1:]
    return data[:, 0], [data[:, j + 1] for j in range(len(names))], names, {}


def _read_csv_fast(path: Path, delimiter: str, n_columns: int):
    """The data rows of a well-formed CSV as a float array ``(rows, n_columns)`` by pandas'
    C parser (its default precision reads numbers exactly as Python's ``float`` does;
    ``tests/test_io_ecosystem.py`` checks it bit for bit), or ``None`` when any row
    is not plain numbers in ``n_columns`` columns, for the row-by-row reader to name the line
    and the fix (blank-cell rows, missing or extra cells, words, decimal commas)."""
    import pandas as pd

    # pandas 3's default parser rounds correctly; pandas 2 needs it asked for
    exact = {} if int(pd.__version__.split(".")[0]) >= 3 else {"float_precision": "round_trip"}
    try:
        df = pd.read_csv(path, sep=delimiter, header=0, dtype=float, encoding="utf-8-sig",
                         engine="c", **exact)
    except (ValueError, pd.errors.ParserError, pd.errors.EmptyDataError):
        return None
    data = df.to_numpy(dtype=float)
    if data.ndim != 2 or data.shape[1] != n_columns or data.shape[0] == 0 or np.isnan(data).any():
        return None
    return data


def _is_float(s) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _read_netcdf(path: Path):
    import xarray as xr

    with open(path, "rb") as fh:
        magic = fh.read(4)
    # NetCDF-3 (classic, 64-bit offset) starts with b"CDF": scipy reads it; NetCDF-4 is HDF5
    engine = "scipy" if magic[:3] == b"CDF" else "h5netcdf"
    try:
        ds = xr.load_dataset(path, engine=engine)
    except Exception as exc:  # noqa: BLE001 - report any backend failure as a file error
        kind = "NetCDF-3" if engine == "scipy" else "NetCDF-4/HDF5"
        raise RecordFileError(f"{path}: cannot be read as {kind} ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else ''}); is the file "
                              "complete and written by xarray/netCDF4?") from None
    return _dataset_columns(ds, str(path))


def _dataset_columns(ds, src: str):
    """``(t, columns, names, attributes)`` of a data set holding one variable per channel over
    ``t``."""
    if "t" not in ds.coords and "t" not in ds.variables:
        raise RecordFileError(f"{src}: no time coordinate 't'; name the time axis 't' (seconds)")
    t = np.asarray(ds["t"].values, dtype=float)
    wide = {str(v): ds[v].dims for v in ds.data_vars if "t" in ds[v].dims and ds[v].dims != ("t",)}
    if wide:  # not dropped unseen: a record holds one variable per channel
        v, dims = next(iter(wide.items()))
        other = next(d for d in dims if d != "t")
        raise RecordFileError(f"{src}: variable(s) {sorted(wide)} have dims {dims}, not ('t',); "
                              f"a record holds one variable per channel over t: split each "
                              f"(xarray: ds[{v!r}].to_dataset(dim={other!r})) and name the "
                              "channels")
    names = [str(v) for v in ds.data_vars if ds[v].dims == ("t",)]
    cols = []
    for v in names:
        try:
            cols.append(np.asarray(ds[v].values, dtype=float))
        except (TypeError, ValueError):
            raise RecordFileError(f"{src}: channel {v!r} holds {ds[v].dtype} values, not "
                                  "numbers; store channels as floats in SI units") from None
    attrs = {k: _attr_value(v) for k, v in ds.attrs.items()}
    return t, cols, names, attrs


def _attr_value(v):
    """A NetCDF attribute as :func:`save_record` wrote it: a number, a string, or a list it
    stored as JSON (spans such as ``masked_s`` or ``table_rate_s``) back as a tuple. JSON
    objects (``schedule_json``) stay strings, for the code that parses them."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, str) and v.startswith("["):
        try:
            out = json.loads(v)
        except ValueError:
            return v
        return tuple(out) if isinstance(out, list) else v
    return v


def _umask() -> int:
    """The process's file-creation mask (Linux reads it without changing it; elsewhere it is
    set and restored at once)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path, write_fn):
    """Call ``write_fn(tmp_path)`` then rename over ``path``; the temp file is removed on error.

    The file gets the permissions a plain ``open(path, "w")`` would give it: an existing file's
    mode is kept, a new one gets ``0o666`` less the umask (``mkstemp``'s temp file is private,
    ``0o600``, and the rename would otherwise carry that over to a record others must read)."""
    write_together([(path, write_fn)])


def write_together(writes) -> None:
    """All of ``writes`` or none: ``(path, write_fn)`` pairs, each ``write_fn(tmp_path)``
    writing one output. Every output is written to a temp file beside its path first; only when
    all are written are they renamed into place. On an error the temp files are removed and no
    path is touched (a run that fails leaves no new output). Permissions as
    :func:`atomic_write`'s."""
    staged = []
    try:
        for path, write_fn in writes:
            path = Path(path)
            path.parent.mkdir(parents=True, exist_ok=True)
            try:
                mode = path.stat().st_mode & 0o7777
            except FileNotFoundError:
                mode = 0o666 & ~_umask()
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
            os.close(fd)
            staged.append((tmp, path))
            write_fn(tmp)
            os.chmod(tmp, mode)
        for tmp, path in staged:
            os.replace(tmp, path)
    except BaseException:
        for tmp, _ in staged:
            if os.path.exists(tmp):
                os.remove(tmp)
        raise


def check_writable(path, option: str) -> Path:
    """``path`` checked, before any work is done, to be a file this run can write: not a
    folder, in a folder that exists or can be made, and that takes a new file (a probe file is
    made there and removed).

    **Raises:** `ValueError` naming ``option``, the path, what is wrong and the fix."""
    out = Path(path)
    if out.is_dir():
        raise ValueError(f"{option} {str(path)!r} is a folder; give a file name (e.g. "
                         f"{str(out / ('out' + (out.suffix or '.json')))!r})")
    folder = out.parent
    while not os.path.lexists(folder) and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(f"{option} {str(path)!r}: {str(folder)!r} is a file, not a folder; "
                         "give a path in a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".probe", dir=folder)
    except OSError as exc:
        raise ValueError(f"{option} {str(path)!r}: cannot write in {str(folder)!r} "
                         f"({exc.strerror or exc}); give a path in a folder you can write to"
                         ) from None
    os.close(fd)
    os.remove(probe)
    return out


RECORD_SUFFIXES = (".nc", ".csv")


def record_path(path, option: str = "--out") -> Path:
    """``path`` as a Path, checked before any work is done to be one :func:`save_record` can
    write (``.nc`` or ``.csv``); a ValueError naming ``option`` otherwise."""
    out = Path(path)
    if out.suffix.lower() not in RECORD_SUFFIXES:
        raise ValueError(f"{option} {str(path)!r}: use a .nc or .csv file name")
    return out


def save_record(record: BenchRecord, path: str | os.PathLike, *,
                units: Mapping[str, str] | None = None) -> Path:
    """Write a (single, unbatched) record to ``.nc`` or ``.csv`` atomically.

    ``units``: each channel's unit in CF notation, ``{channel prefix: unit}`` (a rig's
    ``CHANNEL_UNITS``, e.g. ``{"w": "rad s-1", "a": "m s-2"}``), written as the NetCDF
    channels' ``units`` attribute; a channel it does not name is written ``"SI"``."""
    path = Path(path)
    if record.t.ndim != 1:
        raise ValueError(f"save_record: record is batched (t.shape={record.t.shape}); save one "
                         "record per file (record[i])")
    t = np.asarray(record.t)
    y = np.asarray(record.y)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        def write(tmp):
            with open(tmp, "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(["t", *record.channels])
                for i in range(t.shape[0]):
                    w.writerow([repr(float(t[i])), *(repr(float(v)) for v in y[i])])
    elif suffix in (".nc", ".nc4", ".netcdf"):
        ds = to_xarray(record, units=units)

        def write(tmp):
            ds.to_netcdf(tmp, engine="h5netcdf")
    else:
        raise ValueError(f"{path}: unknown file type {suffix!r}; use .nc or .csv")
    atomic_write(path, write)
    return path


def _plain(o):
    """``o`` as plain JSON values: NumPy/JAX scalars and arrays to numbers and lists, and a
    non-finite float to ``None`` (JSON has no NaN or Infinity; Python's ``json`` would write
    the bare words, which strict readers such as ``JSON.parse`` and many tools refuse)."""
    if isinstance(o, dict):
        return {k: _plain(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_plain(v) for v in o]
    if isinstance(o, str | bool | int) or o is None:
        return o
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    arr = np.asarray(o)
    if arr.dtype == object:
        raise TypeError(f"cannot write {type(o).__name__} to JSON")
    return _plain(arr.item() if arr.ndim == 0 else arr.tolist())


def json_text(obj) -> str:
    """Strict JSON text of ``obj`` (indented; NumPy/JAX values converted, NaN and infinities
    written as ``null``)."""
    return json.dumps(_plain(obj), indent=2, allow_nan=False)


def json_writer(obj):
    """A ``write_fn(tmp_path)`` for :func:`write_together` writing :func:`json_text` of
    ``obj`` (converted now: an object JSON cannot hold fails before any file is written)."""
    text = json_text(obj)

    def write(tmp):
        with open(tmp, "w") as fh:
            fh.write(text + "\n")

    return write


def write_json(obj, path) -> Path:
    """Write :func:`json_text` of ``obj`` atomically."""
    atomic_write(path, json_writer(obj))
    return Path(path)
