import json
import os

import jax
import numpy as np
import pytest
from helpers import TS_24H, design

import gyrojax as gj
from gyrojax import units
from gyrojax.cli import main
from gyrojax.io import RecordFileError, load_record, save_record


@pytest.fixture(scope="module")
def record():
    rig, cond, p = design("equatorial", alpha0_deg=(0, 30))
    return gj.simulate(rig, p, cond, TS_24H[:121], key=jax.random.key(0),
                       noise_std=units.ARCSEC, attrs={"scheme": "equatorial", "latitude_deg": 55.75,
                                                      "masked_s": (60.0, 120.5)})


@pytest.mark.parametrize("suffix", [".nc", ".csv"])
def test_roundtrip(tmp_path, record, suffix):
    path = save_record(record, tmp_path / f"rec{suffix}")
    back = load_record(path, channels=("alpha1", "alpha2"))
    np.testing.assert_array_equal(back.t, record.t)
    np.testing.assert_array_equal(back.y, record.y)  # repr() floats and NetCDF are lossless
    if suffix == ".nc":
        assert back.conditions["scheme"] == "equatorial"
        assert back.conditions["latitude_deg"] == 55.75
        assert back.conditions["masked_s"] == (60.0, 120.5)  # a span list comes back a tuple
    assert [p.name for p in tmp_path.iterdir()] == [f"rec{suffix}"]  # no temp files left


def test_written_files_get_the_umask_mode_and_keep_an_existing_mode(tmp_path, record):
    """The atomic write's temp file is private (0o600); the record must come out as a plain
    open() would make it, and a replaced file keeps its mode."""
    import os
    import stat

    old = os.umask(0o027)
    try:
        path = save_record(record, tmp_path / "rec.nc")
        assert stat.S_IMODE(path.stat().st_mode) == 0o640  # 0o666 less the umask
        os.chmod(path, 0o604)
        save_record(record, path)
        assert stat.S_IMODE(path.stat().st_mode) == 0o604
    finally:
        os.umask(old)


def test_a_failed_write_leaves_the_old_file_and_no_temp_file(tmp_path, record):
    """Nothing is lost and no half file is left: a writer that fails part-way (here after
    writing some bytes) leaves the existing record as it was and removes its temp file."""
    from gyrojax.io import atomic_write

    path = save_record(record, tmp_path / "rec.csv")
    before = path.read_bytes()

    def half(tmp):
        with open(tmp, "w") as f:
            f.write("t,alpha1\n0,")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(path, half)
    assert path.read_bytes() == before
    assert [x.name for x in tmp_path.iterdir()] == ["rec.csv"]
    with pytest.raises(OSError, match="disk full"):
        atomic_write(tmp_path / "new.csv", half)
    assert [x.name for x in tmp_path.iterdir()] == ["rec.csv"]


def test_json_is_strict_nan_and_infinity_become_null(tmp_path):
    import jax.numpy as jnp

    from gyrojax.io import write_json

    def refuse(word):  # a strict reader: JSON has no NaN or Infinity
        raise ValueError(f"non-JSON constant {word}")

    obj = {"a": float("nan"), "b": np.array([1.5, np.inf, -np.inf]), "c": np.float64(2.0),
           "d": jnp.arange(3.0), "e": (np.int64(4), True, None, "x"), "f": np.bool_(False)}
    back = json.loads(write_json(obj, tmp_path / "o.json").read_text(), parse_constant=refuse)
    assert back == {"a": None, "b": [1.5, None, None], "c": 2.0, "d": [0.0, 1.0, 2.0],
                    "e": [4, True, None, "x"], "f": False}
    x = 0.1 + 0.2  # floats round-trip to the last bit
    assert json.loads(write_json({"x": np.float64(x)}, tmp_path / "x.json").read_text())["x"] == x


def _write(tmp_path, text, name="bad.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("text,match", [
    ("t,alpha1,alpha2\n0,0,0\n60,nan,0\n120,0,0\n", "non-finite value nan at sample 1"),
    ("t,alpha1,alpha2\n0,0,0\n60,0,0\n30,0,0\n", "strictly increasing but t\\[1\\]=60.0"),
    ("t,alpha1,alpha2\n0,0,0\n60,0,0\n60,1,0\n120,0,0\n",
     "strictly increasing but t\\[1\\]=60.0 and t\\[2\\]=60.0"),  # a duplicated time stamp
    ("t,alpha1,alpha2\n0,0,0\n60,0,0\n", "2 samples is too few"),
    ("t,alpha1,alpha2\n0,0,0\n60,0\n120,0,0\n", "line 3: 2 columns but the header has 3"),
    ("t,alpha1,alpha2\n0,0,0\n60,0,x\n120,0,0\n", "line 3: non-numeric value 'x'"),
    ("time,alpha1\n0,0\n", "first column must be 't'"),
    ("t,alpha1\n0,0\n60,0\n120,0\n", "missing channel\\(s\\) \\['alpha2'\\]"),
])
def test_bad_files_give_clear_errors(tmp_path, text, match):
    p = _write(tmp_path, text)
    with pytest.raises(RecordFileError, match=match) as info:
        load_record(p, channels=("alpha1", "alpha2"))
    assert str(p) in str(info.value)


def test_spreadsheet_csv_with_byte_order_mark_and_crlf_reads(tmp_path, record):
    text = "t,alpha1,alpha2\r\n" + "".join(
        f"{t!r},{a!r},{b!r}\r\n" for t, (a, b) in zip(np.asarray(record.t).tolist()[:5],
                                                       np.asarray(record.y).tolist()[:5]))
    p = tmp_path / "excel.csv"
    p.write_bytes(b"\xef\xbb\xbf" + text.encode())
    back = load_record(p, channels=("alpha1", "alpha2"))
    np.testing.assert_array_equal(back.y, np.asarray(record.y)[:5])
    p.write_bytes("t,alpha1,alpha2\n0,0,0\n60,0,0\n120,0,0\n".replace("alpha1", "\u00e9alpha1")
                  .encode("latin-1"))
    with pytest.raises(RecordFileError, match="not UTF-8 text .*save the CSV as UTF-8"):
        load_record(p)


def test_netcdf_channels_not_over_t_alone_are_refused_not_dropped(tmp_path):
    import xarray as xr

    t = np.arange(4.0)
    xr.Dataset({"alpha1": ("t", t), "gyro": (("t", "axis"), np.zeros((4, 3))),
                "gain": ((), 2.0)}, coords={"t": t}).to_netcdf(tmp_path / "w.nc",
                                                               engine="h5netcdf")
    with pytest.raises(RecordFileError, match=r"\['gyro'\] have dims \('t', 'axis'\).*"
                       r"to_dataset\(dim='axis'\)"):
        load_record(tmp_path / "w.nc")
    xr.Dataset({"alpha1": ("t", t), "label": ("t", np.array(list("abcd")))},
               coords={"t": t}).to_netcdf(tmp_path / "s.nc", engine="h5netcdf")
    with pytest.raises(RecordFileError, match="channel 'label' holds <U1 values, not numbers"):
        load_record(tmp_path / "s.nc")


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(RecordFileError, match="no such file"):
        load_record(tmp_path / "nope.csv")
    with pytest.raises(RecordFileError, match="unknown file type '.txt'"):
        load_record(_write(tmp_path, "x", "a.txt"))
    with pytest.raises(RecordFileError, match="cannot be read as NetCDF"):
        load_record(_write(tmp_path, "not netcdf", "a.nc"))


def test_failed_write_leaves_nothing(tmp_path, record):
    batched = jax.tree.map(lambda x: np.stack([x, x]), record)
    with pytest.raises(ValueError, match="batched"):
        save_record(batched, tmp_path / "x.nc")
    assert list(tmp_path.iterdir()) == []


def test_cli_simulate_fit_observability_effects(tmp_path, capsys):
    rec = tmp_path / "sim.nc"
    assert main(["simulate", "--scheme", "vertical", "--latitude", "55.75", "--hours", "12",
                 "--noise-arcsec", "1", "--set", "m11=0.3", "--set", "theta1=300",
                 "--out", str(rec)]) == 0
    out = tmp_path / "fit.json"
    assert main(["fit", str(rec), "--effects", "rotor_tilt", "--json", str(out)]) == 0
    fit = json.loads(out.read_text())
    assert fit["converged"] is True
    assert fit["remaining_step_se"] < 1e-2  # Gauss-Newton's step left, in standard errors
    assert fit["parameters"]["m11"]["unit"] == "deg/h"
    assert fit["parameters"]["m11"]["value"] == pytest.approx(0.3, abs=5 * fit["parameters"]["m11"]["stderr"])
    assert fit["parameters"]["theta1"]["unit"] == "arcsec"
    assert fit["residual_rms_arcsec"] == pytest.approx(1.0, rel=0.1)
    # the record's own noise from third differences, read against the residual: 1 arcsec
    assert fit["sample_noise_arcsec"] == pytest.approx(1.0, rel=0.1)
    assert "note: the residual RMS" not in capsys.readouterr().out
    # the same record with its times in hours: its gimbals would turn at hundreds of Earth
    # rates, which no bench gives; refused before the fit, naming t's unit
    from gyrojax._cli_base import misfit_note
    from gyrojax.io import load_record, save_record
    from gyrojax.record import BenchRecord

    r = load_record(rec)
    save_record(BenchRecord(r.t / 3600, r.y, r.channels, r.attrs), tmp_path / "hours.nc")
    assert main(["fit", str(tmp_path / "hours.nc")]) == 2
    err = capsys.readouterr().err
    assert "times the Earth rate" in err and "check t's unit (s: a record in hours" in err
    # a fit the model does not describe (beyond 10x the record's own noise) says what to check
    note = misfit_note(489.0, "1.01 arcsec", "its units (SI: s, rad), --scheme and --latitude",
                       "r.nc", "esg")
    assert note.startswith("note: the residual RMS is 489 times the record's sample-to-sample "
                           "noise (1.01 arcsec") and "gyrojax diagnose r.nc --rig esg" in note
    assert misfit_note(9.9, "1 arcsec", "-", "r.nc", "esg") is None
    # a known noise sets Gauss-Newton's standard errors: sigma (J^T J)^-1/2 at 2 arcsec is the
    # residual estimate's times 2 / sigma_hat, and the estimates are the same fit's
    gout = tmp_path / "fit2.json"
    assert main(["fit", str(rec), "--effects", "rotor_tilt", "--noise-arcsec", "2",
                 "--json", str(gout)]) == 0
    fit2 = json.loads(gout.read_text())
    assert fit2["noise_std_arcsec"] == 2.0
    assert fit2["residual_noise_arcsec"] == pytest.approx(fit["residual_noise_arcsec"], rel=1e-9)
    assert fit["residual_noise_arcsec"] == pytest.approx(1.0, rel=0.1)
    ratio = 2.0 / fit["residual_noise_arcsec"]
    for k in ("m11", "mc2", "theta1"):
        assert fit2["parameters"][k]["value"] == pytest.approx(fit["parameters"][k]["value"], rel=1e-9)
        assert fit2["parameters"][k]["stderr"] == pytest.approx(ratio * fit["parameters"][k]["stderr"],
                                                                rel=1e-9)
    assert main(["fit", str(rec), "--method", "regression", "--noise-arcsec", "2"]) == 2
    assert "not used by method='regression'" in capsys.readouterr().err
    kout = tmp_path / "kf.json"
    assert main(["fit", str(rec), "--method", "kalman", "--effects", "rotor_tilt",
                 "--noise-arcsec", "1", "--json", str(kout)]) == 0
    kf = json.loads(kout.read_text())
    assert kf["noise_std_arcsec"] == pytest.approx(1.0, rel=1e-12)  # the given level, in arcsec
    assert kf["parameters"]["m11"]["value"] == pytest.approx(0.3, abs=5 * kf["parameters"]["m11"]["stderr"])
    assert kf["residual_rms_arcsec"] < 1.3
    assert main(["observability", "--scheme", "equatorial", "--latitude", "55.75",
                 "--json", str(tmp_path / "obs.json")]) == 0
    obs = json.loads((tmp_path / "obs.json").read_text())
    assert obs["unobservable"] == ["theta1", "theta2"]
    assert main(["effects", "--rig", "esg"]) == 0
    assert "drift_transient" in capsys.readouterr().out


@pytest.mark.parametrize("argv,match", [
    (["fit", "missing.csv", "--scheme", "polar", "--latitude", "50"], "no such file"),
    (["simulate", "--scheme", "diagonal", "--latitude", "50", "--out", "x.nc"],
     "--scheme 'diagonal' is unknown"),
    (["simulate", "--scheme", "polar", "--latitude", "50", "--out", "x.nc", "--set", "m13=1"],
     "unknown parameter 'm13'"),
    (["simulate", "--scheme", "polar", "--latitude", "95", "--out", "x.nc"], "--latitude 95"),
    (["simulate", "--scheme", "polar", "--latitude", "50", "--out", "x.txt"], "use a .nc or .csv"),
    (["observability", "--scheme", "polar", "--latitude", "50", "--effects", "wobble"],
     "unknown effect 'wobble'"),
    (["diagnose", "r.nc", "--rig", "imu", "--flicker-arcsec", "0.1", "--json", "x.json"],
     "--flicker-arcsec is for the esg rig"),
    (["diagnose", "r.nc", "--noise-model", "white", "--flicker-arcsec", "0.1", "--json",
      "x.json"], "drop --noise-model white"),
    (["diagnose", "r.nc", "--table-run", "0:60:10", "--json", "x.json"],
     "--table-run is for the imu rig"),
    (["diagnose", "r.nc", "--rig", "imu", "--table-run", "0:60", "--json", "x.json"],
     "--table-run '0:60': give T0:T1:RATE"),
    (["montecarlo", "--study", "budget", "--processes", "0", "--json", "x.json"],
     "--processes '0': give a number of worker processes >= 1 or 'all'"),
    (["montecarlo", "--study", "budget", "--processes", "2", "--scheduler", "local", "--json",
      "x.json"], "--processes and --scheduler: give one"),
    (["montecarlo", "--study", "budget", "--plot", "b.txt", "--json", "x.json"],
     "--plot 'b.txt': use a .png, .pdf or .svg"),
    (["diagnose", "r.nc", "--plot", "gap.txt"], "--plot 'gap.txt': use a .png, .pdf or .svg"),
    (["fit", "dataset:xsens", "--rig", "schuler"],
     "dataset:xsens: the built-in real data sets are strapdown IMU records; use --rig imu"),
    (["montecarlo", "--study", "budget", "--chunk-size", "0", "--json", "x.json"],
     "--chunk-size 0 must be >= 1"),
    (["montecarlo", "--study", "budget", "--noise-arcsec", "-1", "--json", "x.json"],
     "--noise-arcsec -1.0 must be >= 0"),
    # a test the machine could not hold: refused before any array is made
    (["simulate", "--scheme", "polar", "--latitude", "50", "--hours", "1e9", "--out", "x.nc"],
     "--hours 1e+09 with --sample 60 s gives 6e+10 samples"),
    (["observability", "--scheme", "polar", "--latitude", "50", "--hours", "-2"],
     "--hours -2 and --sample 60 must be positive numbers"),
    (["simulate", "--rig", "schuler", "--periods", "1e9", "--out", "x.nc"],
     "--periods 1e+09 with --sample 1 s gives 5.06e+12 samples"),
    (["simulate", "--rig", "gyrotheodolite", "--hours", "1e9", "--out", "x.nc"],
     "--hours 1e+09 with --sample 1 s gives 3.6e+12 samples"),
    (["simulate", "--rig", "platform", "--schedule", '{"dwell_s": 1e9}', "--out", "x.nc"],
     "dwell_s 1e+09 at sample_s 0.025 over 14 positions and 2 amplitude(s) gives 1.12e+12"),
    (["simulate", "--rig", "platform", "--schedule", '{"frequency_hz": 0}', "--out", "x.nc"],
     "vibration frequency 0.0 Hz must be positive"),
    (["simulate", "--rig", "imu", "--out", "x.nc", "--hours", "1"],
     "an IMU record lasts --poses x (--dwell + 2 s of turn)"),
    (["simulate", "--rig", "imu", "--out", "x.nc", "--poses", "0"], "--poses 0 must be >= 1"),
    (["simulate", "--rig", "imu", "--out", "x.nc", "--arw", "-1"], "--arw -1 must be >= 0"),
    (["simulate", "--rig", "imu", "--out", "x.nc", "--sample", "5"],
     "--sample 5 s is longer than the 2-s turns between poses: sample at 2 s or faster"),
    (["simulate", "--rig", "imu", "--out", "x.nc", "--poses", "100000", "--dwell", "1000"],
     "gives 1e+10 samples; a simulated record holds at most 10,000,000"),
    (["simulate", "--rig", "imu", "--out", "x.nc", "--latitude", "95"],
     "latitude 95 deg is outside [-90, 90]; give the test site's latitude (--latitude)"),
    (["diagnose", "r.nc", "--rig", "imu", "--latitude", "-91", "--json", "x.json"],
     "latitude -91 deg is outside [-90, 90]"),
    (["simulate", "--rig", "imu", "--out", "x.nc", "--set", "sa_x=1"], "unknown parameter 'sa_x'"),
    (["diagnose", "r.nc", "--effects", "rotor_tilt,rotor_tilt"],
     "effects: rotor_tilt named more than once; name each effect once"),
    # every rig checks the output's type before it simulates (one helper, io.record_path)
    *[(["simulate", "--rig", rig, "--out", "x.txt"], "--out 'x.txt': use a .nc or .csv file name")
      for rig in ("imu", "platform", "schuler", "gyrotheodolite")],
])
def test_cli_bad_input_exit_2_one_line_nothing_written(tmp_path, capsys, monkeypatch, argv,
                                                      match):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert match.replace("\\", "") in err
    assert list(tmp_path.iterdir()) == []


def test_cli_unknown_option_is_named_by_its_command(capsys):
    with pytest.raises(SystemExit) as info:
        main(["fit", "r.nc", "--window", "3"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: gyrojax fit ")
    assert err.strip().splitlines()[-1] == ("gyrojax fit: error: unrecognized arguments: "
                                            "--window 3 (see gyrojax fit --help)")


def test_cli_help_explains_every_option(capsys):
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    text = capsys.readouterr().out
    for opt in ("--effects", "--method", "--latitude", "--scheme", "--json"):
        assert opt in text


def test_cli_version_is_the_installed_distribution(capsys):
    """``gyrojax --version`` prints the package's version, the one pyproject.toml installed."""
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"gyrojax {version('gyrojax')}"


def test_the_version_is_pyprojects_with_its_changelog_entry():
    import tomllib
    from pathlib import Path

    import gyrojax

    meta = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert gyrojax.__version__ == meta["project"]["version"]
    assert (Path(gyrojax.__file__).parent / "py.typed").exists()
    assert f"## {gyrojax.__version__}" in (Path(__file__).parents[1] / "CHANGELOG.md").read_text()


def test_outputs_that_cannot_be_written_are_refused_before_the_work(tmp_path, capsys,
                                                                   monkeypatch):
    """An output path that is a folder, lies under a file, or in a folder that takes no new
    file is refused with one line naming the option and the fix, exit 2, before any record is
    read or simulated (the record named here does not even exist), and nothing is written."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "outdir").mkdir()
    (tmp_path / "existing_dir.nc").mkdir()
    (tmp_path / "afile").write_text("x")
    cases = [
        (["simulate", "--scheme", "polar", "--latitude", "50", "--out", "existing_dir.nc"],
         "--out 'existing_dir.nc' is a folder; give a file name"),
        (["fit", "missing.nc", "--json", "outdir"], "--json 'outdir' is a folder"),
        (["diagnose", "missing.nc", "--json", "outdir"], "--json 'outdir' is a folder"),
        (["diagnose", "missing.nc", "--json", "dj.json", "--plot", "afile/gap.png"],
         "--plot 'afile/gap.png': 'afile' is a file, not a folder"),
        (["demo", "--plot", "outdir/demo.png", "--json", "afile/sub/x.json"],
         "--json 'afile/sub/x.json': 'afile' is a file, not a folder"),
    ]
    (tmp_path / "outdir" / "demo_gap.png").mkdir()  # where the demo's second figure goes
    cases.append((["demo", "--plot", "outdir/demo.png"],
                  "--plot 'outdir/demo_gap.png' is a folder"))
    if os.path.isdir("/proc/self"):  # Linux: a folder no file can be made in
        cases.append((["diagnose", "missing.nc", "--plot", "/proc/gap.png", "--json", "dj.json"],
                      "--plot '/proc/gap.png': cannot write in '/proc'"))
    before = sorted(p.name for p in tmp_path.rglob("*"))
    for argv, match in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and match in err, (argv, err)
        assert sorted(p.name for p in tmp_path.rglob("*")) == before, argv


def test_a_diagnosis_whose_figure_fails_writes_no_report(tmp_path, monkeypatch):
    """``diagnose --json --plot`` writes both or neither: the figure failing after the report
    is ready leaves no JSON behind (and no temp file)."""
    import types

    import gyrojax.diagnose
    import gyrojax.plots

    monkeypatch.chdir(tmp_path)
    csv = tmp_path / "r.csv"
    csv.write_text("t,alpha1,alpha2\n" + "".join(f"{60.0 * i},0.0,0.0\n" for i in range(30)))
    report = types.SimpleNamespace(markdown=lambda: "# report", to_json=lambda: {"verdict": 1})
    monkeypatch.setattr(gyrojax.diagnose, "diagnose", lambda record, **kw: report)

    def broken(report, path=None):
        raise RuntimeError("the figure failed")

    monkeypatch.setattr(gyrojax.plots, "plot_gap_report", broken)
    with pytest.raises(RuntimeError, match="the figure failed"):
        main(["diagnose", "r.csv", "--scheme", "polar", "--latitude", "50",
              "--json", "dj.json", "--plot", "gap.png"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv"]
    # and a figure that cannot be saved (write_together's second output) leaves no JSON either
    from gyrojax.io import json_writer, write_together

    def failing(tmp):
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        write_together([(tmp_path / "a.json", json_writer({"a": 1})), (tmp_path / "b.png",
                                                                       failing)])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv"]


def test_records_in_other_layouts_are_read_or_refused_by_name(tmp_path, record):
    """A ';'- or tab-separated CSV reads as the comma-separated one (a decimal comma is named);
    a NetCDF-3 file (xarray's scipy engine) reads; a folder named like a record, and numeric
    conditions that are not one number, are refused naming the file, the attribute and the
    fix."""
    import xarray as xr

    save_record(record, tmp_path / "r.csv")
    text = (tmp_path / "r.csv").read_text()
    for name, sep in (("semi.csv", ";"), ("tab.csv", "\t")):
        (tmp_path / name).write_text(text.replace(",", sep))
        got = load_record(tmp_path / name)
        np.testing.assert_array_equal(got.y, load_record(tmp_path / "r.csv").y)
    (tmp_path / "comma.csv").write_text("t;alpha1;alpha2\n0;0,5;1\n1;0,5;1\n2;0,5;1\n")
    with pytest.raises(RecordFileError, match=r"line 2: '0,5' has a decimal comma; write "
                                              r"numbers with a decimal point"):
        load_record(tmp_path / "comma.csv")
    save_record(record, tmp_path / "r.nc")
    ds = xr.load_dataset(tmp_path / "r.nc")
    ds.to_netcdf(tmp_path / "classic.nc", engine="scipy")
    assert (tmp_path / "classic.nc").read_bytes()[:3] == b"CDF"
    got = load_record(tmp_path / "classic.nc")
    np.testing.assert_array_equal(got.y, load_record(tmp_path / "r.nc").y)
    assert got.conditions["latitude_deg"] == 55.75
    (tmp_path / "adir.nc").mkdir()
    with pytest.raises(RecordFileError, match=r"adir.nc is a folder, not a record file"):
        load_record(tmp_path / "adir.nc")
    for value, match in (("fifty-five", r"attribute latitude_deg is 'fifty-five', not a number"),
                         (np.array([55.0, 56.0]), r"attribute latitude_deg is 2 values"),
                         (95.0, r"attribute latitude_deg = 95 is outside \[-90, 90\]")):
        bad = ds.copy()
        bad.attrs["latitude_deg"] = value
        bad.to_netcdf(tmp_path / "bad.nc", engine="h5netcdf")
        with pytest.raises(RecordFileError, match=r"bad.nc: " + match):
            load_record(tmp_path / "bad.nc")


def test_bad_record_files_exit_2_on_the_command_line(tmp_path, capsys, monkeypatch):
    """The same refusals on the command line, one line, exit 2; an IMU's columns read as the
    default (ESG) rig's are named, with the --rig to give."""
    import xarray as xr

    monkeypatch.chdir(tmp_path)
    (tmp_path / "adir.nc").mkdir()
    xr.Dataset({"alpha1": ("t", np.zeros(5)), "alpha2": ("t", np.zeros(5))},
               coords={"t": np.arange(5.0)}, attrs={"latitude_deg": "fifty-five",
                                                    "scheme": "polar"}).to_netcdf(
        "words.nc", engine="h5netcdf")
    (tmp_path / "imu.csv").write_text("t,wx,wy,wz,ax,ay,az\n"
                                      + "".join(f"{i},0,0,0,0,0,9.8\n" for i in range(5)))
    for argv, match in ((["fit", "adir.nc"], "adir.nc is a folder, not a record file"),
                        (["diagnose", "imu.csv"], "the columns are an imu record's: add --rig imu"),
                        (["fit", "words.nc"], "words.nc: attribute latitude_deg is 'fifty-five'")):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and match in err, err


def test_records_no_bench_could_give_are_refused_on_the_physics(tmp_path, record, capsys):
    """A 24-h polar record with t in hours (the gimbals then move at 36 Earth rates), a cell of
    1e300 rad, and a time cell of 1e300 s: ``fit`` and ``diagnose`` refuse each with one line
    naming the channel and the unit to check, exit 2 (they gave m11 = -67,095 deg/h, or NaN
    estimates marked converged)."""
    rig, cond, p = design("polar", alpha0_deg=(0, 30))
    polar = gj.simulate(rig, p, cond, TS_24H, key=jax.random.key(0), noise_std=units.ARCSEC,
                        attrs={"scheme": "polar", "latitude_deg": 55.75})
    save_record(polar, tmp_path / "polar.csv")
    lines = (tmp_path / "polar.csv").read_text().splitlines()
    hours = [lines[0]] + [",".join([repr(float(r.split(",")[0]) / 3600)] + r.split(",")[1:])
                          for r in lines[1:]]
    (tmp_path / "hours.csv").write_text("\n".join(hours) + "\n")
    cell = lines[:]
    cell[100] = ",".join([cell[100].split(",")[0], "1e300", cell[100].split(",")[2]])
    (tmp_path / "cell.csv").write_text("\n".join(cell) + "\n")
    tcell = lines[:]
    tcell[-1] = ",".join(["1e300", *tcell[-1].split(",")[1:]])
    (tmp_path / "tcell.csv").write_text("\n".join(tcell) + "\n")
    cases = [("hours.csv", "rad in 24 s, 5"),
             ("cell.csv", "alpha1 moves 1e+300 rad"),
             ("tcell.csv", "t spans 1e+300 s")]
    for name, match in cases:
        for command in ("fit", "diagnose"):
            assert main([command, str(tmp_path / name), "--scheme", "polar", "--latitude",
                         "55.75"]) == 2
            err = capsys.readouterr().err.strip()
            assert len(err.splitlines()) == 1 and match in err, (name, command, err)


@pytest.mark.parametrize("rig, channels, value, match", [
    ("imu", ("wx", "wy", "wz", "ax", "ay", "az"), 1e300, "the record's wx reaches 1e+300 at "
     "sample 4 (t=4 s), beyond what a bench gives (100 in SI): gyro rates are in rad/s"),
    ("imu", ("wx", "wy", "wz", "ax", "ay", "az"), 57.3 * 20, "gyro rates are in rad/s (from "
     "deg/s: x 0.0174533)"),
    ("schuler", ("V1", "V2", "rot1", "rot2", "rot3"), -1e300, "the record's V1 reaches -1e+300"),
])
def test_channels_beyond_any_bench_are_refused_before_the_work(tmp_path, capsys, rig, channels,
                                                              value, match):
    """A cell no bench gives (a corrupt 1e300, a rate table at 1146 "rad/s" that is deg/s) is
    refused by the diagnosis and by the command line, naming the channel, the sample and the
    fix, before any fit (they ran to NaN estimates or 'SVD did not converge')."""
    from gyrojax import rigs
    from gyrojax.diagnose import diagnose
    from gyrojax.record import BenchRecord

    t = np.arange(40.0)
    y = 1e-3 * np.random.default_rng(0).standard_normal((40, len(channels)))
    y[4, 0] = value
    rec = BenchRecord(t, y, channels, {"latitude_deg": 45.0})
    # an auxiliary channel (a supply in mV) is not bounded as the specific forces are
    from gyrojax.io import check_channel_bounds

    check_channel_bounds(BenchRecord(t, np.full((40, 1), 5000.0), ("aux1",), {}),
                         rigs.get(rig).model_class.CHANNEL_BOUNDS)
    with pytest.raises(ValueError, match=match.replace("(", r"\(").replace(")", r"\)")
                       .replace("+", r"\+")):
        diagnose(rec, rig=rig)
    save_record(rec, tmp_path / "r.csv")
    assert main(["diagnose", str(tmp_path / "r.csv"), "--rig", rig, "--latitude", "45"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and match in err, err


def test_a_plot_keeps_the_sessions_matplotlib_backend(tmp_path):
    """A notebook's backend (here svg) is the same after gyrojax draws and saves a figure (it
    was switched to Agg, and later inline figures stopped showing), and a saved figure is
    closed in pyplot (none left open)."""
    import subprocess
    import sys

    code = ("import matplotlib, numpy as np\n"
            "import gyrojax.plots as P\n"
            "plt = P._plt()\n"
            "fig, ax = plt.subplots()\n"
            "ax.plot(np.arange(3.0))\n"
            f"P._save(fig, {str(tmp_path / 'f.png')!r})\n"
            "print(matplotlib.get_backend(), plt.get_fignums())\n")
    env = dict(os.environ, MPLBACKEND="svg")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["svg", "[]"]
    assert (tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"
