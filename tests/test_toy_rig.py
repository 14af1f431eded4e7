"""The extension path: a sixth rig defined in ``tests/toy_rig.py`` (a rate gyro on a turntable),
registered from the test, goes through ``gyrojax simulate``, ``fit``, ``observability``,
``diagnose`` and ``effects`` end to end. Nothing in ``gyrojax/`` names it."""

import json

import pytest
import toy_rig

from gyrojax import rigs
from gyrojax.cli import main


@pytest.fixture
def turntable():
    toy_rig.register()
    yield
    rigs.unregister("turntable")


def test_a_registered_sixth_rig_runs_every_command(turntable, tmp_path, capsys):
    """A bias of 2 deg/h and a scale error of 500 ppm over 1 h at 1 arcsec noise: the fit
    recovers both within 4 standard errors; observability says the three coefficients are
    observable on the turntable. With a bias ramp of 3 deg/h per h added, the diagnosis finds
    the gap, attributes it to bias_ramp, its refit measures the ramp within 4 standard errors
    of the truth and closes the held-out gap."""
    clean, rec = tmp_path / "clean.nc", tmp_path / "turntable.nc"
    for path, ramp in ((clean, "0"), (rec, "3")):
        assert main(["simulate", "--rig", "turntable", "--out", str(path), "--set", "b=2",
                     "--set", "k=500", "--set", f"r={ramp}", "--seed", "1"]) == 0
    import xarray as xr

    with xr.open_dataset(rec, engine="h5netcdf") as ds:  # the channel's unit, as CF writes it
        assert ds["angle"].attrs["units"] == "rad" and ds["t"].attrs["units"] == "s"
    out = tmp_path / "fit.json"
    assert main(["fit", str(clean), "--rig", "turntable", "--json", str(out)]) == 0
    fit = json.loads(out.read_text())["parameters"]
    for name, truth in (("b", 2.0), ("k", 500.0)):
        assert fit[name]["value"] == pytest.approx(truth, abs=4 * fit[name]["stderr"])
    assert main(["observability", "--rig", "turntable", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["unobservable"] == []
    assert main(["effects", "--rig", "turntable"]) == 0
    assert "bias_ramp (trend)" in capsys.readouterr().out
    assert main(["diagnose", str(rec), "--rig", "turntable", "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["verdict"]["kind"] == "attributed"
    assert rep["verdict"]["effects"] == ["bias_ramp"]
    refit = rep["refits"][0]
    assert refit["coefficients"]["r"] == pytest.approx(3.0, abs=4 * refit["std_errors"]["r"])
    assert refit["heldout_gap_after"] < refit["heldout_null_band_after"][1]
    # the library's entry takes the rig as fit and simulate do, a model object: the same report
    from gyrojax.diagnose import diagnose
    from gyrojax.io import load_record

    again = diagnose(load_record(rec), rig=toy_rig.TurntableRig())
    assert again.rig == "turntable" and again.verdict.effects == ["bias_ramp"]
    assert again.refits[0].coefficients["r"] == pytest.approx(refit["coefficients"]["r"],
                                                              rel=1e-9)
    # a rig option of another rig is refused by name
    assert main(["simulate", "--rig", "esg", "--omega0", "5", "--out", str(rec)]) == 2
    assert "--omega0 is for the turntable rig" in capsys.readouterr().err


def test_the_registry_names_the_rig_and_refuses_an_unknown_one(turntable):
    assert "turntable" in rigs.names()
    assert rigs.get("turntable").catalogue() == {"bias_ramp": "trend"}
    with pytest.raises(ValueError, match="unknown rig 'carousel'; rigs: esg, .*turntable"):
        rigs.get("carousel")
    with pytest.raises(ValueError, match="option.* order are not for --rig turntable"):
        rigs.get("turntable").catalogue(order="exact")
    # a rig's model object or class names its entry; one no entry has is refused by name
    from gyrojax import ESGRig
    from gyrojax.models import AbstractRig

    assert rigs.get(toy_rig.TurntableRig()) is rigs.get("turntable")
    # the record channels with their SI units, named by the rig (CF notation)
    assert rigs.get("turntable").channel_units() == {"angle": "rad"}
    assert rigs.get("imu").channel_units() == {"wx": "rad s-1", "wy": "rad s-1", "wz": "rad s-1",
                                                "ax": "m s-2", "ay": "m s-2", "az": "m s-2"}
    assert rigs.get("schuler").channel_units(("V1", "rot3", "temp")) == {
        "V1": "m s-1", "rot3": "rad", "temp": "SI"}
    assert rigs.get(ESGRig).name == "esg"

    class Carousel(AbstractRig):
        pass

    with pytest.raises(ValueError, match="no registered rig has the model Carousel; rigs: esg"):
        rigs.get(Carousel)
