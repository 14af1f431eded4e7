"""Records meet xarray and pandas: conversions both ways, load_record on in-memory data, the CF
units written, and the vectorised CSV reader against Python's own float parsing."""

import csv

import numpy as np
import pytest

from gyrojax import BenchRecord
from gyrojax.io import RecordFileError, load_record, save_record


def _imu_record(n=50, seed=0):
    rng = np.random.default_rng(seed)
    names = ("wx", "wy", "wz", "ax", "ay", "az")
    t = 0.01 * np.arange(n) + 3.0
    return BenchRecord.create(t, {c: rng.normal(size=n) for c in names},
                              {"latitude_deg": 45.0, "rig": "imu", "masked_s": (1.0, 2.5)})


def test_xarray_round_trip_keeps_samples_conditions_and_cf_units(tmp_path):
    rec = _imu_record()
    ds = rec.to_xarray(units={"w": "rad s-1", "a": "m s-2"})
    assert ds["wx"].attrs["units"] == "rad s-1" and ds["az"].attrs["units"] == "m s-2"
    assert ds["t"].attrs["units"] == "s"
    back = BenchRecord.from_xarray(ds)
    assert back.channels == rec.channels
    np.testing.assert_array_equal(np.asarray(back.y), np.asarray(rec.y))
    np.testing.assert_array_equal(np.asarray(back.t), np.asarray(rec.t))
    assert back.conditions == rec.conditions
    assert load_record(ds, channels=("wz", "ax")).channels == ("wz", "ax")
    # the file is the same data set; an old file's units="SI" reads the same
    path = save_record(rec, tmp_path / "r.nc", units={"w": "rad s-1", "a": "m s-2"})
    import xarray as xr

    on_disk = xr.load_dataset(path)
    assert on_disk["wy"].attrs["units"] == "rad s-1"
    on_disk["wy"].attrs["units"] = "SI"
    np.testing.assert_array_equal(np.asarray(load_record(on_disk).y), np.asarray(rec.y))


def test_pandas_round_trip_with_t_as_index_or_column():
    rec = _imu_record()
    df = rec.to_pandas()
    assert df.index.name == "t" and list(df.columns) == list(rec.channels)
    assert df.attrs["latitude_deg"] == 45.0
    for frame in (df, df.reset_index()):
        back = BenchRecord.from_pandas(frame)
        np.testing.assert_array_equal(np.asarray(back.y), np.asarray(rec.y))
        np.testing.assert_array_equal(np.asarray(back.t), np.asarray(rec.t))
        assert back.conditions == rec.conditions
    assert load_record(df, conditions={"latitude_deg": 10.0}).conditions["latitude_deg"] == 10.0


def test_in_memory_sources_get_the_file_checks():
    rec = _imu_record()
    df = rec.to_pandas()
    with pytest.raises(RecordFileError, match="no time column or index 't'"):
        load_record(df.reset_index(drop=True))
    bad = df.copy()
    bad.index = bad.index[::-1].rename("t")
    with pytest.raises(ValueError, match="strictly increasing|increasing"):
        load_record(bad)
    with pytest.raises(RecordFileError, match="missing channel"):
        load_record(rec.to_xarray(), channels=("alpha1",))
    ds = rec.to_xarray()
    ds.attrs["latitude_deg"] = 95.0
    with pytest.raises(RecordFileError, match=r"latitude_deg = 95 is outside \[-90, 90\]"):
        load_record(ds)
    with pytest.raises(TypeError, match="give a .nc or .csv file's path, an xarray.Dataset or "
                                        "a pandas.DataFrame"):
        load_record([1.0, 2.0])
    words = df.astype(object)
    words.iloc[3, 0] = "spike"
    with pytest.raises(RecordFileError, match="channel 'wx' holds object values"):
        load_record(words)


def test_csv_reader_reads_every_number_as_python_float_does(tmp_path):
    """The vectorised reader (pandas' C parser, round-trip precision) against Python's float
    on each cell: bit-identical, on repr-written values, short decimals and exponents; a file
    it cannot read whole (a row of blank cells) goes row by row, with the same values."""
    rng = np.random.default_rng(3)
    n = 400
    cells = np.column_stack([np.arange(n) * 0.01,
                             rng.normal(size=n) * 10.0 ** rng.integers(-12, 12, size=n),
                             np.round(rng.normal(size=n), 3), rng.normal(size=n) * 1e-300])
    text = [[repr(float(v)) for v in row] for row in cells]
    text[5][2] = "1.5e-3"
    text[6][3] = "  -0.25 "

    def write(path, rows):
        with open(path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t", "a", "b", "c"])
            w.writerows(rows)

    write(tmp_path / "x.csv", text)
    truth = np.array([[float(c) for c in row] for row in text])
    rec = load_record(tmp_path / "x.csv")
    np.testing.assert_array_equal(np.asarray(rec.y), truth[:, 1:])
    np.testing.assert_array_equal(np.asarray(rec.t), truth[:, 0])
    write(tmp_path / "blank.csv", text[:10] + [["", "", "", ""]] + text[10:])
    slow = load_record(tmp_path / "blank.csv")
    np.testing.assert_array_equal(np.asarray(slow.y), truth[:, 1:])
