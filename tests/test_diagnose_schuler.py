"""Gap diagnosis of the Schuler test (``--rig schuler``): a hidden gyro drift ramp found, named,
measured and closed on the held-out part; the accelerometer vertical-axis tilt reported as
absorbed by the bias with the analytic alias ``g`` per radian; a null record left alone."""

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

from gyrojax import units
from gyrojax.cli import main
from gyrojax.diagnose import diagnose
from gyrojax.io import load_record
from gyrojax.models.schuler import SchulerConditions
from gyrojax.record import BenchRecord

RAMP = 0.05  # deg/h/h, the catalogue's prior scale


def _simulate(tmp_path, name, sets, seed):
    rec = tmp_path / f"{name}.nc"
    args = [a for s in sets for a in ("--set", s)]
    assert main(["simulate", "--rig", "schuler", "--periods", "2", "--sample", "10", "--seed",
                 str(seed), "--set", "nu1=0.1", "--set", "D22=5000", "--set", "df2=0.005",
                 *args, "--out", str(rec)]) == 0
    return rec


def _run(tmp_path, name, sets, seed):
    rec = _simulate(tmp_path, name, sets, seed)
    out = tmp_path / f"{name}.json"
    assert main(["diagnose", str(rec), "--rig", "schuler", "--json", str(out)]) == 0
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def ramp_report(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("schuler_gap"), "ramp", [f"nudot2={RAMP}"], seed=5)


@pytest.mark.slow  # ~50 s: the first Schuler diagnosis compiles every refit
def test_hidden_drift_ramp_is_attributed_measured_and_closed(ramp_report):
    r = ramp_report
    v = r["verdict"]
    assert v["kind"] == "attributed" and v["effects"] == ["drift_ramp"]
    row = next(x for x in r["candidates"] if x["name"] == "drift_ramp")
    assert row["posterior"] > 0.99 and row["p_value"] < 1e-10
    # the one-step estimate against the generating value, in its standard errors
    for k, truth in (("nudot1", 0.0), ("nudot2", RAMP), ("nudot3", 0.0)):
        assert abs(row["onestep"][k] - truth) < 4 * row["onestep_se"][k], (k, row["onestep"])
    refit = next(x for x in r["refits"] if x["effects"] == ["drift_ramp"])
    assert refit["coefficients"]["nudot2"] == pytest.approx(RAMP, rel=0.1)
    # held out: a gap of tens of noise variances before, inside the null band after
    assert v["heldout_gap_before"] > 10 * v["heldout_null_band"][1]
    assert refit["reduction"] > 0.99 and refit["closure"]


@pytest.mark.slow  # ~50 s: the first Schuler diagnosis compiles every refit
def test_accelerometer_tilt_is_absorbed_by_the_bias_with_the_analytic_alias(ramp_report):
    """An input axis tilted by mu towards the vertical senses mu * f3 = mu * g cos(a1) cos(a2):
    a bias of g per radian up to the tilts' squares (~3e-4 here)."""
    row = next(x for x in ramp_report["candidates"] if x["name"] == "accelerometer_tilt")
    assert row["visible_fraction"] < 1e-6 and "confounded" in row["visibility"]
    g = float(SchulerConditions.create().g)
    alias = {a["effect_param"]: a["absorbed_by"][0] for a in row["aliases"]}
    for mu, bias in (("mu13", "df1"), ("mu23", "df2")):
        assert alias[mu]["name"] == bias
        assert alias[mu]["coefficient"] == pytest.approx(g * units.ARCMIN, rel=3e-3)
    assert set(row["confounded_with"]) == {"df1", "df2"}


def test_null_record_has_no_gap(tmp_path):
    # through the API without the design advisor: its longer-record design compiles the
    # Jacobian a second time (~15 s); the CLI's whole run is the slow ramp tests'
    rep = diagnose(load_record(_simulate(tmp_path, "null", [], seed=6)), rig="schuler",
                   design_advice=False)
    r = rep.to_json()
    assert r["verdict"]["kind"] == "no-gap", rep.markdown()
    assert r["gap"]["heldout"] < r["gap"]["heldout_null_band"][1]


def test_bad_schuler_record(tmp_path):
    rec = tmp_path / "short.nc"
    assert main(["simulate", "--rig", "schuler", "--periods", "0.4", "--sample", "10",
                 "--out", str(rec)]) == 0
    assert main(["diagnose", str(rec), "--rig", "schuler"]) == 2  # train part < half a period
    assert main(["diagnose", str(rec), "--rig", "schuler", "--effects", "rotor_tilt"]) == 2


@pytest.mark.slow
def test_schuler_blind_harness(tmp_path):
    """Four sealed D5 cases diagnosed with the manifest out of reach: a null, a strong drift
    ramp, an out-of-library velocity line, a strong drift step (onset localised, goal G8)."""
    import shutil

    from gyrojax.validation import schuler as bs

    bs.generate(tmp_path, 1, seed=3, null_fraction=1.0)
    bs.generate(tmp_path / "b", 3, seed=4, null_fraction=0.0, lambdas=(400.0,),
                families=("drift_ramp", "velocity_line", "drift_step"))
    hidden = tmp_path.parent / f"{tmp_path.name}_sealed"
    shutil.move(tmp_path / "sealed", hidden)
    shutil.move(tmp_path / "b" / "sealed", tmp_path / "b_sealed")
    null, = bs.run(tmp_path)
    ramp, line, step = bs.run(tmp_path / "b")
    shutil.move(hidden, tmp_path / "sealed")
    shutil.move(tmp_path / "b_sealed", tmp_path / "b" / "sealed")
    assert null["verdict"] == "no-gap"
    assert "drift_ramp" in ramp["effects"] + ramp["ambiguity"]
    # goal G9: unexplained or ambiguous, not attributed. Under the design prior the line's top
    # posterior is accelerometer_tilt, which the bias absorbs whole (Bayes factor 1): without a
    # significant score test of its own it is not named `confounded` either (5d1933e)
    assert line["verdict"] in ("unexplained", "ambiguous", "no-gap"), line
    s = bs.score(tmp_path / "b", [ramp, line, step])
    assert s["by_lambda"]["400"]["power"]["rate"] == 1.0
    assert s["ool_confident_misattribution"]["rate"] == 0.0
    # goal G8: the strong step's onset at its largest score within 5 % of the record
    # (a drift step and a warm-up transient are hard to tell apart over two Schuler periods: the
    # verdict may be ambiguous between them, the step's own onset is still scored)
    assert "drift_step" in step["effects"] + step["ambiguity"], step
    g8 = bs.localisation_scores(tmp_path / "b", [ramp, line, step])
    assert g8["g8_step_onset"] == {"rate": 1.0, "se": pytest.approx(1e-6), "n": 1}
    assert g8["g8_step_onset_crb"]["n"] == 1 and g8["g8_step_onset_crb"]["rate"] > 0.99
    assert g8["g8_transient_decay"] is None


def test_schuler_blind_design_is_the_specs_four_hours():
    """Design D5 (docs/goals.md) records 4 h (1441 samples at 10 s, ~2.84 Schuler periods);
    ``of_periods`` and ``with_periods`` give a record of whole periods on the same sample grid."""
    from gyrojax.validation import schuler as bs

    d = bs.SchulerDesign()
    period = float(SchulerConditions.create(d.latitude_deg).schuler_period)
    assert d.ts[0] == 0.0 and d.ts[-1] == 4 * 3600.0 and len(d.ts) == 1441
    assert d.periods == pytest.approx(4 * 3600.0 / period, rel=1e-12)
    assert 2.8 < d.periods < 2.9
    two = bs.SchulerDesign.of_periods(2.0)
    np.testing.assert_array_equal(two.ts, np.arange(0.0, 2 * period + 5.0, 10.0))
    assert two.periods == pytest.approx(2.0, rel=1e-12) and two.n_train == 760
    other = bs.SchulerDesign(sample_s=20.0, latitude_deg=40.0, holdout=0.5).with_periods(3.0)
    assert (other.sample_s, other.latitude_deg, other.holdout) == (20.0, 40.0, 0.5)
    assert other.periods == pytest.approx(3.0, rel=1e-12)
    assert other.hours * 3600.0 == pytest.approx(3 * float(other.conditions.schuler_period), rel=1e-12)


def test_schuler_localisation_scores_by_hand(tmp_path):
    """goal G8 on a 2-period record (~169 min, tolerance ~8.4 min): the truth in minutes (the
    parameters' display unit) against grids in hours; decay grid step ratio 12^(1/7)."""
    from gyrojax.validation import schuler as bs

    cases = {"a": {"family": "drift_step", "lambda": 32.0, "t_step": 60.0, "onset_crb_min": 6.0},
             "b": {"family": "drift_step", "lambda": 64.0, "t_step": 60.0, "onset_crb_min": 3.0},
             "c": {"family": "drift_step", "lambda": 8.0, "t_step": 60.0},  # below 32
             "d": {"family": "drift_transient", "lambda": 32.0, "tau_tr": 60.0},
             "e": {"family": "drift_transient", "lambda": 32.0, "tau_tr": 60.0}}
    (tmp_path / "sealed").mkdir()
    (tmp_path / "sealed" / "manifest.json").write_text(json.dumps({"cases": cases}))
    record_s = 2 * 5064.0
    tol_h = 0.05 * record_s / 3600  # 0.1407 h
    # a: 1 h + 0.95 tol (in), b: 1 h - 1.05 tol (out), c: far off but below lambda 32;
    # d: 1.4 h (1.4 < 12^(1/7) = 1.426, in), e: 0.68 h (1 / 0.68 = 1.47, out)
    best = {"a": 1 + 0.95 * tol_h, "b": 1 - 1.05 * tol_h, "c": 2.5, "d": 1.4, "e": 0.68}
    res = [{"sha": k, "record_s": record_s, "grid_best": {cases[k]["family"]: v}}
           for k, v in best.items()]
    g8 = bs.localisation_scores(tmp_path, res)
    assert g8["g8_step_onset"]["rate"] == 0.5 and g8["g8_step_onset"]["n"] == 2
    assert g8["g8_transient_decay"]["rate"] == 0.5 and g8["g8_transient_decay"]["n"] == 2
    # an efficient estimator's rate: normal errors of the Cramér-Rao deviations (min -> h)
    tol_min = 60 * tol_h
    expected = [math.erf(tol_min / (math.sqrt(2) * s)) for s in (6.0, 3.0)]
    assert g8["g8_step_onset_crb"] == {"rate": pytest.approx(np.mean(expected), rel=1e-12),
                                       "n": 2}


def test_schuler_problem_lines_designs_and_jacobians_by_hand(tmp_path):
    """The Schuler diagnosis' pieces against independent arithmetic, without a fit: the gap map's
    lines at ``2 pi sqrt(a_R / g)`` and half of it; the advisor's four designs as labelled (twice
    the record on the same step, V2' negated, the start azimuth + 90 deg, both V' doubled); the
    screening's whitened columns (a drift ramp's, and a drift step's at its 4th onset) equal to
    central differences of ``predict`` (the model in the test's residual coordinates, docs/rigs/schuler.md)
    per unit ``Param.scale``, divided by the channel noise (the prior scale in display units);
    and a record too short refused with the numbers."""
    from gyrojax.diagnose._schuler import DEFAULT_NOISE, SchulerProblem
    from gyrojax.models.schuler import EARTH_RADIUS

    rec = load_record(_simulate(tmp_path, "pieces", [], seed=7))
    prob = SchulerProblem(rec)
    c = prob.conditions
    period = 2 * math.pi * math.sqrt(EARTH_RADIUS / float(c.g))
    assert 5000 < period < 5100
    assert prob.lines == pytest.approx({"Schuler period": period, "half Schuler period": period / 2},
                                       rel=1e-12)
    t = prob.t
    (l1, c1, t1), (l2, c2, t2), (l3, c3, t3), (l4, c4, t4) = prob.designs()
    assert t1[0] == t[0] and t1[-1] - t1[0] == pytest.approx(2 * (t[-1] - t[0]), rel=1e-12)
    np.testing.assert_allclose(np.diff(t1), t[1] - t[0], rtol=1e-12)
    assert c1 is c and l1 == f"{2 * (t[-1] - t[0]) / 60:.0f} min record"
    v1, v2, az = float(c.v10), float(c.v20), float(c.a0)
    for cond, want in ((c2, (v1, -v2, az)), (c3, (v1, v2, az + math.radians(90))),
                       (c4, (2 * v1, 2 * v2, az))):
        assert (float(cond.v10), float(cond.v20), float(cond.a0)) == pytest.approx(want, abs=1e-12)
        assert float(cond.g) == float(c.g) and float(cond.latitude) == float(c.latitude)
    assert l2 == f"initial velocities ({v1:g}, {-v2:g}) m/s" and "start azimuth 90 deg" == l3
    assert all(x is t for x in (t2, t3, t4))

    sp = prob.space
    params = sp.make({"nu1": 0.1, "D22": 5000.0, "df2": 0.005}, display=True)
    sigma = np.asarray(DEFAULT_NOISE)
    _, sigs = prob.jacobians(params, sigma)
    sig = {s.name: s for s in sigs}
    np.testing.assert_allclose(sig["drift_ramp"].prior_scale, RAMP, rtol=1e-12)  # display units
    g = 3
    for name, grid in (("drift_ramp", {}), ("drift_step", {"t_step": prob.step_grid_s[g]})):
        s = sig[name]
        at = params | {k: jnp.asarray(v) for k, v in grid.items()}
        for i, k in enumerate(s.names):
            h = 1e-2 * float(sp[k].scale)
            fd = (prob.predict(at | {k: at[k] + h}) - prob.predict(at | {k: at[k] - h})) / (2 * h)
            col = (fd * float(sp[k].scale) / sigma).reshape(-1)
            got = s.jac[g if grid else 0][:, i]
            assert np.max(np.abs(got - col)) < 1e-3 * np.max(np.abs(col)), (name, k)

    with pytest.raises(ValueError, match=r"the train part spans \d+ s, less than half a Schuler "
                                         r"period \(2531 s\)"):
        SchulerProblem(load_record(_simulate(tmp_path, "short", ["nu1=0"], seed=1)), holdout=0.8)
    y = np.asarray(prob.record.y).copy()
    y[:, 2:] = np.degrees(y[:, 2:]) + 200.0  # attitude in deg, 200 deg off: no rotation vector
    with pytest.raises(ValueError, match=r"\|rot1 rot2 rot3\| reaches .*, beyond a rotation "
                       r"vector's largest angle"):
        SchulerProblem(BenchRecord(prob.record.t, y, prob.record.channels, prob.record.attrs))


@pytest.mark.slow  # ~60 s: the Schuler refit's compilation
def test_a_refit_holds_the_screened_step_onset(tmp_path):
    """A drift step of 0.1 and of 0.5 deg/h (2x and 10x the catalogue's prior scale) on axis 2 at the
    onset grid's 6th value: the refit with the drift_step effect at that grid index holds that
    onset, measures the step to 5 % (the other axes' steps under 0.01 deg/h), converges (no
    note) and leaves every effect it was not given at its null. Without damping the 0.5 deg/h
    refit's undamped Gauss-Newton returned -203 deg/h."""
    from gyrojax.diagnose._schuler import DEFAULT_NOISE, SchulerProblem

    g = 5
    onset = SchulerProblem(load_record(_simulate(tmp_path, "grid", [], seed=8))).step_grid_s[g]
    for amp in (0.1, 0.5):
        rec = load_record(_simulate(tmp_path, "step", [f"nustep2={amp}",
                                                        f"t_step={onset / 60!r}"], seed=8))
        prob = SchulerProblem(rec)
        assert prob.step_grid_s[g] == pytest.approx(onset, rel=1e-12)
        p0 = prob.fit_nominal()
        sigma = np.asarray(DEFAULT_NOISE)
        _, sigs = prob.jacobians(p0, sigma)
        step = next(s for s in sigs if s.name == "drift_step")
        _, coeffs, p = prob.refit(p0, [(step, g)], sigma)
        assert float(p["t_step"]) == pytest.approx(onset, rel=1e-12)
        assert coeffs["nustep2"] == pytest.approx(amp, rel=0.05), coeffs
        assert abs(coeffs["nustep1"]) < 0.01 and abs(coeffs["nustep3"]) < 0.01
        assert not any("refit" in n for n in prob.notes), prob.notes
        others = [k for e, names in prob.effect_names.items() if e != "drift_step"
                  for k in names]
        assert len(others) > 10 and all(float(p[k]) == 0.0 for k in others)
