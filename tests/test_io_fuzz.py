"""Record files as a hostile but realistic user writes them (hypothesis): any CSV (cells,
names, delimiters, encodings, sizes) and any NetCDF (channel types, attributes) either loads
as a record with finite samples, each column once, or is refused with a RecordFileError (one
message naming the file) -- never another exception."""

import numpy as np
import pytest
import xarray as xr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gyrojax.io import RecordFileError, load_record

CELL = st.one_of(st.floats(-1e3, 1e3).map(repr), st.floats().map(repr),
                 st.integers(-10**30, 10**30).map(str), st.text(max_size=5),
                 st.sampled_from(["", "1e300", "0,5", "nan", " 1.5 ", "1_0"]))
NAME = st.one_of(st.sampled_from(["alpha1", "alpha2", "wx", "t", "", " alpha1"]),
                 st.text(max_size=6))
SETTINGS = settings(max_examples=300, deadline=None, derandomize=True,
                    suppress_health_check=list(HealthCheck))


def _loads_or_refuses(path, n_channels=None):
    try:
        rec = load_record(path)
    except RecordFileError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc)
        return None
    assert np.all(np.isfinite(rec.t)) and np.all(np.isfinite(rec.y))
    assert len(set(rec.channels)) == len(rec.channels) > 0
    if n_channels is not None:  # no column dropped
        assert len(rec.channels) == n_channels
    return rec


@SETTINGS
@given(data=st.data(), names=st.lists(NAME, max_size=4), header_t=st.booleans(),
       sep=st.sampled_from([",", ";", "\t"]), n=st.integers(0, 8),
       encoding=st.sampled_from(["utf-8", "utf-8-sig", "latin-1", "utf-16"]))
def test_any_csv_loads_or_is_refused_by_name(tmp_path_factory, data, names, header_t, sep, n,
                                             encoding):
    head = (["t"] if header_t else []) + names
    rows = [[data.draw(CELL) for _ in head] for _ in range(n)]
    text = sep.join(head) + "\n" + "".join(sep.join(r) + "\n" for r in rows)
    path = tmp_path_factory.mktemp("csv") / "r.csv"
    try:
        path.write_bytes(text.encode(encoding))
    except UnicodeEncodeError:
        return
    _loads_or_refuses(path, len(head) - 1)


ATTR = st.one_of(st.floats(), st.text(max_size=8), st.integers(-10**6, 10**6),
                 st.lists(st.floats(-100, 100), min_size=1, max_size=3).map(np.array))
COLUMN = st.sampled_from(["float", "int", "text", "bool", "nan", "2d"])


@SETTINGS
@given(kinds=st.lists(COLUMN, max_size=3), n=st.integers(0, 6),
       attrs=st.dictionaries(st.sampled_from(["latitude_deg", "scheme", "g", "v10", "masked_s",
                                              "azimuth0_deg"]), ATTR, max_size=3),
       engine=st.sampled_from(["h5netcdf", "scipy"]))
def test_any_netcdf_loads_or_is_refused_by_name(tmp_path_factory, kinds, n, attrs, engine):
    t = np.arange(float(n))
    columns = {"float": np.linspace(0.0, 1e-3, n), "int": np.arange(n),
               "text": np.array([f"x{i}" for i in range(n)]),
               "bool": np.arange(n) % 2 == 0, "nan": np.full(n, np.nan)}
    data = {}
    for i, kind in enumerate(kinds):
        data[f"c{i}"] = ((("t", "k"), np.zeros((n, 2))) if kind == "2d"
                         else ("t", columns[kind]))
    ds = xr.Dataset(data, coords={"t": t}, attrs=attrs)
    path = tmp_path_factory.mktemp("nc") / "r.nc"
    try:
        ds.to_netcdf(path, engine=engine)
    except (TypeError, ValueError):  # a dataset the format itself cannot hold
        return
    _loads_or_refuses(path)


@pytest.mark.parametrize("text", ["t,a\n0,1\n1,1\n2,1\n", "t;a\n0;1\n1;1\n2;1\n"])
def test_the_fuzzed_reader_reads_a_plain_record(tmp_path, text):
    (tmp_path / "r.csv").write_text(text)
    rec = _loads_or_refuses(tmp_path / "r.csv", 1)
    assert rec is not None and rec.channels == ("a",)
