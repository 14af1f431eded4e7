"""``gyrojax simulate|fit|observability --rig platform`` with schedule files."""

import json

import pytest

from gyrojax.cli import main
from gyrojax.models.platform import TRUE_TABLE2


@pytest.mark.slow  # moved out of the default suite (compile-heavy; CI runs it)
def test_simulate_fit_observability(tmp_path, capsys):
    sched = tmp_path / "s.json"
    sched.write_text(json.dumps({"dwell_s": 20, "table_amplitudes_g": [9, 7]}))
    rec, out = tmp_path / "p.nc", tmp_path / "fit.json"
    assert main(["simulate", "--rig", "platform", "--schedule", str(sched), "--out", str(rec)]) == 0
    assert main(["fit", str(rec), "--rig", "platform", "--json", str(out)]) == 0
    res = json.loads(out.read_text())["parameters"]
    for name, truth in TRUE_TABLE2.items():  # schedule read back from the record's attributes
        assert abs(res[name]["value"] - truth) < 5 * res[name]["stderr"], name
    assert main(["observability", "--rig", "platform", "--schedule",
                 '{"table_amplitudes_g": [9]}']) == 0
    text = capsys.readouterr().out
    assert "D_f_x - 0.0526 D_ii_x - 0.0526 D_oo_x - 0.0526 D_ss_x" in text  # kappa = 19


def test_bad_schedules_exit_2(tmp_path, capsys):
    cases = [('{"dwel": 3}', "unknown field"), ('{"sample_s": 0.05}', "Nyquist"),
             ('{"table_amplitudes_g": [7, 7]}', "repeats an amplitude")]
    for text, msg in cases:
        assert main(["observability", "--rig", "platform", "--schedule", text]) == 2
        assert msg in capsys.readouterr().err
    sched = tmp_path / "s.json"
    sched.write_text(json.dumps({"dwell_s": 5, "table_amplitudes_g": [0, 2]}))
    rec = tmp_path / "p.nc"
    assert main(["simulate", "--rig", "platform", "--schedule", str(sched), "--out", str(rec)]) == 0
    assert main(["fit", str(rec), "--rig", "platform", "--method", "s21"]) == 2
    assert "0 g amplitude" in capsys.readouterr().err


@pytest.mark.slow  # moved out of the default suite (compile-heavy; CI runs it)
def test_fit_methods_agree_and_unknown_method_refused(tmp_path, capsys):
    sched = tmp_path / "s.json"
    sched.write_text(json.dumps({"dwell_s": 10, "table_amplitudes_g": [9, 7]}))
    rec = tmp_path / "p.nc"
    assert main(["simulate", "--rig", "platform", "--schedule", str(sched), "--out", str(rec)]) == 0
    out, info = {}, {}
    for m in ("joint", "kalman", "gauss-newton"):
        assert main(["fit", str(rec), "--rig", "platform", "--method", m, "--json",
                     str(tmp_path / f"{m}.json")]) == 0
        info[m] = json.loads((tmp_path / f"{m}.json").read_text())
        out[m] = info[m]["parameters"]
    # the EKF and the batch Gauss-Newton end on the regression (the model is linear in D)
    for m in ("kalman", "gauss-newton"):
        for name in TRUE_TABLE2:
            assert abs(out[m][name]["value"] - out["joint"][name]["value"]) < \
                0.05 * out["joint"][name]["stderr"], (m, name)
    gn = info["gauss-newton"]  # started from the regression: converged, nothing left to step
    assert gn["converged"] is True and gn["num_steps"] < 20 and gn["remaining_step_se"] < 1e-2
    assert "converged: True (" in capsys.readouterr().out
    assert main(["fit", str(rec), "--rig", "platform", "--method", "levenberg-marquardt"]) == 2
    assert "not a platform method" in capsys.readouterr().err
