"""``gyrojax simulate|fit|observability --rig schuler`` end to end, and bad input -> exit 2."""

import json

import numpy as np
import pytest

from gyrojax import units
from gyrojax.cli import main
from gyrojax.io import load_record, save_record
from gyrojax.record import BenchRecord


@pytest.mark.slow  # moved out of the default suite (compile-heavy; CI runs it)
def test_simulate_fit_observability(tmp_path, capsys):
    rec = tmp_path / "schuler.nc"
    truth = {"nu1": 0.1, "D22": 5000.0, "K11": -3000.0, "dA0": 20.0}
    sets = [a for k, v in truth.items() for a in ("--set", f"{k}={v}")]
    assert main(["simulate", "--rig", "schuler", "--periods", "1", "--sample", "2", "--seed", "4",
                 "--out", str(rec), *sets]) == 0
    r = load_record(rec, channels=("V1", "V2", "rot1", "rot2", "rot3"))
    assert r.conditions["rig"] == "schuler" and r.n_samples == 2532
    out = tmp_path / "fit.json"
    assert main(["fit", str(rec), "--rig", "schuler", "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["converged"] is True and rep["iterations"] < 10
    assert 0.0 <= rep["last_step_se"] < 1e3  # the last step taken (converged by tol)
    for name, value in truth.items():  # within 4 standard errors of the truth
        p = rep["parameters"][name]
        assert abs(p["value"] - value) < 4 * p["stderr"], (name, p)
    assert abs(rep["parameters"]["nu2"]["value"]) < 4 * rep["parameters"]["nu2"]["stderr"]
    # the scale errors raise the V1 channel's Schuler frequency by about (K11 + D22) / 2 = 1e-3:
    # the period shortens by ~0.1 % (one noisy period, other errors present: 0.06-0.16 %)
    assert -1.6e-3 < rep["period_min"][0] / rep["theoretical_period_min"] - 1 < -0.6e-3
    # the residual at the estimate and the record's own noise: the simulated 0.05 m/s, 1 arcmin
    sim = np.array([0.05, 0.05] + [units.ARCMIN] * 3)
    for key in ("residual_rms", "sample_noise"):
        np.testing.assert_allclose(list(rep[key].values()), sim, rtol=0.1)
    assert "note:" not in capsys.readouterr().out
    # the same record with its velocities in km/h: Gauss-Newton does not converge, and the
    # note names the misfit against the noise with the units to check
    save_record(BenchRecord(r.t, r.y * np.array([3.6, 3.6, 1, 1, 1]), r.channels, r.attrs),
                tmp_path / "kmh.nc")
    assert main(["fit", str(tmp_path / "kmh.nc"), "--rig", "schuler"]) == 0
    note = capsys.readouterr().out.splitlines()[-1]
    assert float(note.split("RMS is ")[1].split(" times")[0]) > 100
    assert "V1 V2 in m/s" in note and "diagnose" in note
    obs = tmp_path / "obs.json"
    assert main(["observability", "--rig", "schuler", "--periods", "0.5", "--sample", "5",
                 "--json", str(obs)]) == 0
    o = json.loads(obs.read_text())
    assert o["rank"] == 12
    pairs = {frozenset(p[:2]): p[2] for p in o["weak_pairs"]}
    assert pairs[frozenset(("alpha10", "df2"))] == pytest.approx(-1.0, abs=1e-2)
    assert o["crlb"]["dA0"]["unit"] == "arcmin"
    assert o["crlb"]["dA0"]["value"] > 1.0  # azimuth unresolved below one period


def test_bad_input_exits_2(tmp_path, capsys):
    assert main(["simulate", "--rig", "schuler", "--periods", "-1", "--out",
                 str(tmp_path / "x.nc")]) == 2
    assert "--periods -1.0 must be > 0" in capsys.readouterr().err
    short = tmp_path / "short.csv"
    t = np.arange(0.0, 600.0, 1.0)
    np.savetxt(short, np.column_stack([t, 200 * np.cos(t / 806), np.zeros((t.size, 4))]),
               delimiter=",", header="t,V1,V2,rot1,rot2,rot3", comments="")
    assert main(["fit", str(short), "--rig", "schuler"]) == 2
    assert "less than half a Schuler period" in capsys.readouterr().err
    nogimbal = tmp_path / "v.csv"
    np.savetxt(nogimbal, np.column_stack([t, t, t]), delimiter=",", header="t,V1,V2", comments="")
    assert main(["fit", str(nogimbal), "--rig", "schuler"]) == 2
    assert "rot1" in capsys.readouterr().err
    assert main(["fit", str(short), "--rig", "schuler", "--sigma-v", "0"]) == 2
