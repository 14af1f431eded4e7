"""Loaders of the real data sets: bad files give errors naming file and line; the UCalgary
LN-100 up/down statics reproduce the Earth rate and gravity (skipped when the data are absent)."""

import numpy as np
import pytest

from gyrojax import units
from gyrojax.analysis.spectral import allan_deviation
from gyrojax.datasets import (
    DataFileError,
    data_root,
    load_ucalgary,
    read_float64_records,
    read_text_columns,
)
from gyrojax.earth import normal_gravity


def test_bad_files(tmp_path):
    good = np.arange(14.0).reshape(2, 7)
    f = tmp_path / "x.ins"
    f.write_bytes(good.astype("<f8").tobytes() + b"\0" * 8)
    with pytest.raises(DataFileError, match=r"x.ins: 120 bytes .* 8 trailing bytes.*truncated"):
        read_float64_records(f, 7)
    with pytest.warns(UserWarning, match="dropping the trailing bytes"):
        np.testing.assert_array_equal(read_float64_records(f, 7, partial="warn"), good)
    f.write_bytes(b"\0" * 20)
    with pytest.raises(DataFileError, match="less than one record"):
        read_float64_records(f, 7)
    t = tmp_path / "x.txt"
    t.write_text("0 1 2 3 4 5 6\n1 1 2 3 4 5\n")
    with pytest.raises(DataFileError, match=r"x.txt, line 2: 6 columns, expected 7"):
        read_text_columns(t, 7)
    t.write_text("0 1 2 3 4 5 6\n1 1 2 x 4 5 6\n")
    with pytest.raises(DataFileError, match=r"line 2: non-numeric"):
        read_text_columns(t, 7)


def _root():
    try:
        return data_root()
    except FileNotFoundError as exc:
        pytest.skip(str(exc))


def test_ln100_up_down_static_gives_earth_rate_and_gravity():
    """x up then down: (mean_up - mean_down)/2 of wx is the vertical Earth rate,
    Omega sin(51.0784 deg) = 11.70 deg/h (bias cancels), to 1 %; of ax it is gravity, to 0.1 %."""
    _root()
    up = load_ucalgary("ln100", "up")  # 19,217 whole records (the README's "8 spare bytes" aside)
    down = load_ucalgary("ln100", "down")
    for rec in (up, down):
        dt = np.median(np.diff(np.asarray(rec.t)))
        assert 1 / dt == pytest.approx(64.07, rel=1e-3) and rec.channels[0] == "wx"
    wu, wd = (np.asarray(r.channel("wx")).mean() for r in (up, down))
    earth_v = units.EARTH_RATE * np.sin(np.radians(51.0784))
    assert (wu - wd) / 2 == pytest.approx(earth_v, rel=0.01)
    au, ad = (np.asarray(r.channel("ax")).mean() for r in (up, down))
    assert (au - ad) / 2 == pytest.approx(float(normal_gravity(np.radians(51.0784))), rel=1e-3)
    adev = allan_deviation(np.asarray(up.channel("wx")), 64.07)
    assert np.all(np.isfinite(adev.adev)) and adev.adev[4] < adev.adev[0]
