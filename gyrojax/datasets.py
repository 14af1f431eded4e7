"""Loaders for the real recorded data sets in ``../shared/data/real/`` (never copied into this
repository), into :class:`BenchRecord` in SI units with their conditions.

So far: ``ucalgary_ln100_adi`` — an LN-100 ring-laser-gyro INS (raw little-endian float64, 7 per
record: t [s], w [deg/s], f [m/s^2]) and an ADI MEMS IMU (7 whitespace columns; gyro unit
uncertain, see that folder's README), static with the x axis up, then down, at 51.0784 deg N.
Channels ``wx wy wz`` (rad/s) and ``ax ay az`` (m/s^2), per the DESIGN.md contract.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from . import units
from .record import BenchRecord, freeze

__all__ = ["DataFileError", "data_root", "read_float64_records", "read_text_columns",
           "load_ucalgary"]

IMU_CHANNELS = ("wx", "wy", "wz", "ax", "ay", "az")


class DataFileError(ValueError):
    """A data file that cannot be read as documented: names the file, the place and the fix."""


def data_root(path=None) -> Path:
    """``../shared/data/real`` beside the project root (or ``path``); a clear error if absent."""
    root = Path(path) if path is not None else Path(__file__).resolve().parents[2] / "shared" \
        / "data" / "real"
    if not root.is_dir():
        raise FileNotFoundError(f"real data not found at {root}: the data sets live in "
                                "../shared/data/real beside the project (not in this repository)")
    return root


def read_float64_records(path, n_columns: int, *, partial: str = "error") -> np.ndarray:
    """Raw little-endian float64 records of ``n_columns`` values. A size that is not a whole
    number of records is an error (truncated file) unless ``partial="warn"``, which drops the
    trailing bytes *with a warning* naming them."""
    path = Path(path)
    raw = path.read_bytes()
    rec = 8 * n_columns
    if len(raw) < rec:
        raise DataFileError(f"{path}: {len(raw)} bytes, less than one record of {n_columns} "
                            "float64 values; the file is truncated or not this format")
    extra = len(raw) % rec
    if extra:
        msg = (f"{path}: {len(raw)} bytes is {len(raw) // rec} whole records of {n_columns} "
               f"float64 plus {extra} trailing bytes")
        if partial != "warn":
            raise DataFileError(msg + "; the file is truncated (or has another column count). "
                                "If the trailing bytes are known padding, pass partial='warn'")
        warnings.warn(msg + "; dropping the trailing bytes", stacklevel=2)
    data = np.frombuffer(raw[: len(raw) - extra], dtype="<f8").reshape(-1, n_columns)
    if not np.all(np.isfinite(data)):
        bad = int(np.argwhere(~np.isfinite(data))[0][0])
        raise DataFileError(f"{path}: record {bad} holds non-finite values; wrong format?")
    return data


def read_text_columns(path, n_columns: int) -> np.ndarray:
    """Whitespace-separated numeric text with exactly ``n_columns`` per row; errors name the line."""
    path = Path(path)
    rows = []
    with path.open() as fh:
        for k, line in enumerate(fh, start=1):
            parts = line.split()
            if not parts:
                continue
            if len(parts) != n_columns:
                raise DataFileError(f"{path}, line {k}: {len(parts)} columns, expected "
                                    f"{n_columns}; fix or remove the line")
            try:
                rows.append([float(p) for p in parts])
            except ValueError:
                raise DataFileError(f"{path}, line {k}: non-numeric value in {line.strip()!r}; "
                                    "fix or remove the line") from None
    if not rows:
        raise DataFileError(f"{path}: no data rows")
    return np.asarray(rows)


def _imu_record(t, w, f, attrs):
    t = np.asarray(t, float)
    if np.any(np.diff(t) <= 0):
        k = int(np.argmax(np.diff(t) <= 0))
        raise DataFileError(f"time is not strictly increasing at sample {k + 1} "
                            f"({t[k]} -> {t[k + 1]} s)")
    y = np.concatenate([w, f], axis=1)
    return BenchRecord(np.asarray(t - t[0]), np.asarray(y), IMU_CHANNELS,
                       freeze(attrs | {"t0_s": float(t[0])}))


def load_ucalgary(sensor: str = "ln100", orientation: str = "up", *, root=None,
                  adi_gyro_unit: str = "rad/s") -> BenchRecord:
    """The UCalgary x-axis up/down static records. ``sensor``: ``"ln100"`` (64 Hz, gyro deg/s)
    or ``"adi"`` (100 Hz, gyro unit uncertain: ``adi_gyro_unit`` ``"rad/s"`` (default, see the
    README) or ``"deg/s"``). Conditions: latitude 51.0784 deg, the orientation, the sensor."""
    if sensor not in ("ln100", "adi") or orientation not in ("up", "down"):
        raise ValueError(f"sensor={sensor!r}, orientation={orientation!r}: use 'ln100' or 'adi', "
                         "and 'up' or 'down'")
    folder = data_root(root) / "ucalgary_ln100_adi"
    if sensor == "ln100":
        path = folder / f"x_LN100_{orientation}.ins"
        # the folder README mentions 8 spare bytes in x_LN100_up.ins; its 1,076,152 bytes are in
        # fact exactly 19,217 records of 56 bytes, so the strict reader applies
        data = read_float64_records(path, 7)
        w = data[:, 1:4] * units.DEG
    else:
        path = folder / f"x_adi_{orientation}.txt"
        data = read_text_columns(path, 7)
        if adi_gyro_unit not in ("rad/s", "deg/s"):
            raise ValueError(f"adi_gyro_unit={adi_gyro_unit!r}; use 'rad/s' or 'deg/s'")
        w = data[:, 1:4] * (units.DEG if adi_gyro_unit == "deg/s" else 1.0)
    return _imu_record(data[:, 0], w, data[:, 4:7],
                       {"latitude_deg": 51.0784, "orientation": f"x {orientation}",
                        "sensor": sensor, "source": str(path.name)})
