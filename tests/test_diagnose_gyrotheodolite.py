"""Gap diagnosis of a gyrotheodolite north-seeking run (``--rig gyrotheodolite``): a hidden torque
ramp found, measured and closed on the held-out part; a suspension-tape torque hidden in the
index offset with the analytic alias ``1/(H omega3 cos phi)`` and the design that separates it;
bad input refused with the fix named."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from gyrojax import units
from gyrojax.cli import main
from gyrojax.diagnose import diagnose
from gyrojax.estimate import STATIONARY_SE
from gyrojax.models.gyrotheodolite import DEFAULTS
from gyrojax.record import BenchRecord

RAMP = 0.3  # nN m/h: the equilibrium walks ~14 arcsec/h
TAPE = 1.0  # nN m: ~45 arcsec of equilibrium shift
OFFSET = 40.0  # arcsec, the index offset the instrument measures
LAT = 50.45
K0 = DEFAULTS["H"] * units.EARTH_RATE * np.cos(np.radians(LAT))  # N m per rad


def _run(tmp_path, name, sets, seed):
    rec = tmp_path / f"{name}.nc"
    args = [a for s in sets for a in ("--set", s)]
    assert main(["simulate", "--rig", "gyrotheodolite", "--seed", str(seed), "--set",
                 f"index_offset={OFFSET}", "--set", "alpha0=5", *args, "--out", str(rec)]) == 0
    out = tmp_path / f"{name}.json"
    assert main(["diagnose", str(rec), "--rig", "gyrotheodolite", "--json", str(out)]) == 0
    return json.loads(out.read_text())


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("gyrotheodolite_gap")
    return {"ramp": _run(tmp, "ramp", [f"M_ramp={RAMP}"], seed=3),
            "tape": _run(tmp, "tape", [f"M_tape={TAPE}"], seed=4)}


def test_hidden_torque_ramp_is_attributed_measured_and_closed(reports):
    r = reports["ramp"]
    v = r["verdict"]
    assert v["kind"] == "attributed" and v["effects"] == ["torque_ramp"]
    row = next(x for x in r["candidates"] if x["name"] == "torque_ramp")
    assert row["posterior"] > 0.99 and row["p_value"] < 1e-10
    assert abs(row["onestep"]["M_ramp"] - RAMP) < 4 * row["onestep_se"]["M_ramp"]
    refit = next(x for x in r["refits"] if x["effects"] == ["torque_ramp"])
    assert refit["coefficients"]["M_ramp"] == pytest.approx(RAMP, rel=0.05)
    assert v["heldout_gap_before"] > 10 * v["heldout_null_band"][1]
    assert refit["reduction"] > 0.99 and refit["closure"]


def test_tape_torque_hides_in_the_index_offset_with_the_analytic_alias(reports):
    """A constant torque M shifts the equilibrium by M/k0 like an index offset, and its release
    transient is the release state's: no gap, the measured offset biased by exactly M/k0, the
    alias named (index_offset +1/k0, alpha0 -1/k0 per N m), and only the run at another rotor
    momentum resolving it (a second compensation gain does not: the forcing stays M + k0 A)."""
    r = reports["tape"]
    assert r["verdict"]["kind"] == "no-gap"
    bias = TAPE * 1e-9 / K0 / units.ARCSEC
    offset = r["nominal"]["parameters"]["index_offset"]
    assert offset["unit"] == "arcsec" and offset["value"] == pytest.approx(OFFSET + bias, abs=1.0)
    row = next(x for x in r["candidates"] if x["name"] == "tape_torque")
    assert row["visible_fraction"] < 1e-10 and row["visibility"] == "structurally confounded"
    alias = {a["name"]: a["coefficient"] for a in
             next(a for a in row["aliases"] if a["effect_param"] == "M_tape")["absorbed_by"]}
    per_nnm = 1e-9 / K0  # rad per nN m; aliases are in display units (arcsec, arcmin)
    assert alias["index_offset"] == pytest.approx(per_nnm / units.ARCSEC, rel=1e-6)
    assert alias["alpha0"] == pytest.approx(-per_nnm / units.ARCMIN, rel=1e-6)
    advice = {a["design"]: a["mde_over_prior"] for a in r["design_advice"]
              if a["effect"] == "tape_torque"}
    best = min(advice, key=advice.get)
    assert "rotor momentum" in best and advice[best] < 0.1
    assert advice["second run with the compensation link on (kappa + 10)"] > 1e6


def _record(n=2401, dt=1.0, **attrs):
    t = np.arange(n) * dt
    y = 1e-4 * np.exp(-t / 300) * np.cos(t / 80) + 1e-6 * np.random.default_rng(0).normal(size=n)
    return BenchRecord(t, y[:, None], ("alpha",), {"latitude_deg": LAT} | attrs)


def test_bad_input_names_the_fix():
    with pytest.raises(ValueError, match="north-seeking period"):
        diagnose(_record(n=400), rig="gyrotheodolite")
    with pytest.raises(ValueError, match="without base vibration"):
        diagnose(_record(n_m=0.1), rig="gyrotheodolite")
    with pytest.raises(ValueError, match="unknown effect.*tape_torque"):
        diagnose(_record(), rig="gyrotheodolite", effects=["tape_zero"])
    bad = BenchRecord(np.arange(2401.0), np.zeros((2401, 1)) + np.arange(2401.0)[:, None],
                      ("azimuth",), {})
    with pytest.raises(ValueError, match="one channel 'alpha'"):
        diagnose(bad, rig="gyrotheodolite")
    # in arcsec the small-angle model fits a scaled copy (no gap, a north offset of hundreds of
    # "radians") unless refused
    rec = _record()
    with pytest.raises(ValueError, match=r"alpha reaches 20.65\d*, beyond the small-angle model's "
                       r"range \(1 rad\).*from arcsec: x 4.84814e-6"):
        diagnose(BenchRecord(rec.t, rec.y / units.ARCSEC, rec.channels, rec.attrs),
                 rig="gyrotheodolite")


@pytest.mark.slow
def test_gyrotheodolite_blind_harness(tmp_path):
    """Sealed cases diagnosed with the manifest out of reach: a null, a hidden tape torque (must
    stay unattributed), a strong torque step, an out-of-library pick-off line."""
    import shutil

    from gyrojax.validation import gyrotheodolite as bg

    bg.generate(tmp_path, 1, seed=3, null_fraction=1.0)
    bg.generate(tmp_path / "b", 3, seed=4, null_fraction=0.0, lambdas=(400.0,),
                families=("tape_torque", "torque_step", "pickoff_line"))
    for d in (tmp_path, tmp_path / "b"):
        shutil.move(d / "sealed", tmp_path.parent / f"{tmp_path.name}_{d.name}_sealed")
    null, = bg.run(tmp_path)
    tape, step, line = bg.run(tmp_path / "b")
    for d in (tmp_path, tmp_path / "b"):
        shutil.move(tmp_path.parent / f"{tmp_path.name}_{d.name}_sealed", d / "sealed")
    assert null["verdict"] == "no-gap"
    assert tape["verdict"] == "no-gap"
    assert step["verdict"] == "attributed" and step["effects"] == ["torque_step"]
    assert line["verdict"] in ("unexplained", "ambiguous", "no-gap")
    s = bg.score(tmp_path / "b", [tape, step, line])
    assert s["structural_silent"]["rate"] == 1.0
    assert s["out_of_library_honest"]["rate"] == 1.0
    # goal G8: the strong step's onset at its largest score within 2 min of the truth
    g8 = bg.localisation_scores(tmp_path / "b", [tape, step, line])
    assert g8["g8_step_onset"] == {"rate": 1.0, "se": pytest.approx(1e-6), "n": 1}
    assert g8["g8_step_onset_crb"]["n"] == 1 and g8["g8_step_onset_crb"]["rate"] > 0.99
    assert g8["g8_transient_decay"] is None


def test_gyrotheodolite_localisation_scores_by_hand(tmp_path):
    """goal G8 on a 40-min record (tolerance 2 min; decay grid step ratio 10^(1/7))."""
    from gyrojax.validation import gyrotheodolite as bg

    cases = {"a": {"family": "torque_step", "lambda": 32.0, "t_step": 10.0},
             "b": {"family": "torque_step", "lambda": 64.0, "t_step": 10.0},
             "c": {"family": "torque_step", "lambda": 16.0, "t_step": 10.0},  # below 32
             "d": {"family": "drift_transient", "lambda": 32.0, "tau_tr": 10.0}}
    (tmp_path / "sealed").mkdir()
    (tmp_path / "sealed" / "manifest.json").write_text(json.dumps({"cases": cases}))
    best = {"a": 11.9, "b": 12.1, "c": 30.0, "d": 13.8}  # 13.8 / 10 < 10^(1/7) = 1.39
    res = [{"sha": k, "record_s": 2400.0,
            "grid_best": {cases[k]["family"]: v}} for k, v in best.items()]
    g8 = bg.localisation_scores(tmp_path, res)
    assert g8["g8_step_onset"]["rate"] == 0.5 and g8["g8_step_onset"]["n"] == 2
    assert g8["g8_transient_decay"]["rate"] == 1.0


def test_nominal_fit_converges_when_the_model_jitters_at_its_solver_tolerance(tmp_path):
    """Near the optimum the adaptive ODE solve moves the model by ~1e-7 parameter scales from
    call to call; a step-size criterion alone then cycles (one of 1000 blind null records did).
    Emulate it: every model call shifts the prediction by +-2e-7 scales of alpha_dot0,
    alternately. The fit must stop on its negligible cost decrement, at the unjittered
    optimum to within that jitter."""
    from gyrojax.diagnose._gyrotheodolite import NOMINAL, GyrotheodoliteProblem
    from gyrojax.io import load_record

    rec = tmp_path / "null.nc"
    assert main(["simulate", "--rig", "gyrotheodolite", "--seed", "7", "--set",
                 f"index_offset={OFFSET}", "--set", "alpha0=5", "--out", str(rec)]) == 0
    prob = GyrotheodoliteProblem(load_record(rec), holdout=0.25)
    ref = prob.fit_nominal()
    col = prob.all_names.index("alpha_dot0")
    exact, calls = prob._eval, [0]

    def jittered(params, ts=None):
        y, jac = exact(params, ts)
        calls[0] += 1
        return y + (-1) ** calls[0] * 2e-7 * jac[:, col], jac

    prob._eval = jittered
    got = prob.fit_nominal()
    for k, s in zip(NOMINAL, prob.nominal_scales, strict=True):
        assert abs(float(got[k]) - float(ref[k])) < 1e-6 * s, k


def test_design_jacobians_stack_runs_each_with_its_own_release_state(tmp_path):
    """The advisor's designs by hand: the longer run keeps the sample count at half the rate
    (and says so); a two-run design's whitened Jacobian is the runs' blocks stacked, each run's
    model at its own rotor momentum and compensation gain (from the model's own Jacobian at
    ``H/2`` or ``kappa + 10``), the index offset, stiffness and damping shared, and the release
    state (``alpha0``, ``alpha_dot0``) its own per run (block diagonal); the advisor's one grid
    value per effect is that value's slice of the whole grid; and a record's own instrument
    constants (``H``, ``kappa``...) are the model's."""
    from gyrojax.diagnose._gyrotheodolite import NOMINAL, RUN_STATE, GyrotheodoliteProblem
    from gyrojax.io import load_record

    rec = tmp_path / "design.nc"
    assert main(["simulate", "--rig", "gyrotheodolite", "--seed", "2", "--set",
                 f"index_offset={OFFSET}", "--set", "alpha0=5", "--out", str(rec)]) == 0
    prob = GyrotheodoliteProblem(load_record(rec), holdout=0.25)
    t = prob.t
    (l_long, runs_long, t_long), (_, runs_k, t_k), (_, runs_h, t_h) = prob.designs()
    dt = t[1] - t[0]
    np.testing.assert_allclose(t_long, t[0] + 2 * dt * np.arange(len(t)), rtol=1e-12)
    assert l_long == f"{2 * (t[-1] - t[0]) / 60:.0f} min run ({2 * dt:g} s samples)"
    assert runs_long == (("run", 1.0, 0.0),) and t_k is t and t_h is t
    # the record's instrument constants are the model's
    other = GyrotheodoliteProblem(load_record(rec).with_conditions(H=0.9 * DEFAULTS["H"], kappa=3.0))
    assert float(other.base["H"]) == 0.9 * DEFAULTS["H"] and float(other.base["kappa"]) == 3.0
    params = {k: prob.base[k] for k in NOMINAL} | {"index_offset": jnp.asarray(OFFSET * units.ARCSEC)}
    sigma = np.array([2.0 * units.ARCSEC])
    shared = ("index_offset", "kappa", "F_KC")
    col = [prob.all_names.index(k) for k in shared + RUN_STATE]
    base = prob.base | params
    for runs, second in ((runs_k, {"kappa": base["kappa"] + 10.0}),
                         (runs_h, {"H": base["H"] * 0.5})):
        jn, every = prob.jacobians(params, sigma, conditions=runs)  # runs_h's kept below
        j1 = prob._eval(base)[1][:, col] / sigma[0]
        j2 = prob._eval(base | second)[1][:, col] / sigma[0]
        m = len(t)
        want = np.zeros((2 * m, 7))
        want[:m, :3], want[m:, :3] = j1[:, :3], j2[:, :3]
        want[:m, 3:5], want[m:, 5:7] = j1[:, 3:], j2[:, 3:]
        assert np.max(np.abs(j2 - j1)) > 1e-3 * np.max(np.abs(j1))  # the second run differs
        np.testing.assert_allclose(jn, want, rtol=1e-9, atol=1e-9 * np.max(np.abs(want)))
    # the advisor's one grid value per effect is that value's slice of the full grid
    _, one = prob.jacobians(params, sigma, conditions=runs_h,
                            grid={"torque_step": 5, "drift_transient": 2})
    for a, b in zip(every, one, strict=True):
        g = {"torque_step": 5, "drift_transient": 2}.get(a.name)
        if g is None:
            np.testing.assert_array_equal(b.jac, a.jac)
        else:
            assert b.grid == (a.grid[g],)
            np.testing.assert_allclose(b.jac[0], a.jac[g], rtol=1e-12, atol=1e-12)


def test_nominal_fit_stops_at_the_optimum_and_a_refit_keeps_its_grid_value(tmp_path):
    """The fits end where one more Gauss-Newton step is negligible (under ``STATIONARY_SE``,
    0.01 standard errors of the train residual's noise: the rule of every fit in gyrojax), and
    a refit with a torque step holds the onset the screening
    chose: a 1 nN m step at 12 min (the grid's 6th onset, 5 % of the 40-min record apart) is
    measured to 5 % there."""
    from gyrojax.diagnose._gyrotheodolite import NOMINAL, GyrotheodoliteProblem
    from gyrojax.io import load_record

    rec = tmp_path / "step.nc"
    assert main(["simulate", "--rig", "gyrotheodolite", "--seed", "9", "--set",
                 f"index_offset={OFFSET}", "--set", "alpha0=5", "--set", "M_step=1.0", "--set",
                 "t_step=12", "--out", str(rec)]) == 0
    prob = GyrotheodoliteProblem(load_record(rec), holdout=0.25)
    assert prob.step_grid_s[5] == pytest.approx(720.0, abs=1e-9)
    n = prob.n_train
    p0 = prob.fit_nominal()
    sigma = np.array([2.0 * units.ARCSEC])
    _, sigs = prob.jacobians(p0, sigma)
    step = next(s for s in sigs if s.name == "torque_step")
    _, coeffs, p = prob.refit(p0, [(step, 5)], sigma)
    assert float(p["t_step"]) == pytest.approx(720.0, abs=1e-9)
    assert coeffs["M_step"] == pytest.approx(1.0, rel=0.05)
    names = NOMINAL + ("M_step",)
    cols = [prob.all_names.index(k) for k in names]
    for fitted, free in ((prob.base | p0, NOMINAL), (p, names)):
        c = cols[:len(free)]
        pred, jac = prob._eval(fitted)
        r = prob.y[:n, 0] - pred[:n]
        left, *_ = np.linalg.lstsq(jac[:n, c], r, rcond=None)
        noise = np.sqrt(np.sum(r ** 2) / (n - len(free)))
        assert np.linalg.norm(jac[:n, c] @ left) / noise < STATIONARY_SE, free


def test_a_large_torque_step_is_fitted_with_damped_steps(tmp_path):
    """A 3 nN m torque step (150 arcsec of equilibrium shift) at 12 min leaves the nominal fit a
    large residual, where whole Gauss-Newton steps overshoot (a plain Gauss-Newton loop
    alternated for 20 steps there). The trust-region fit converges without a note; the refit at
    the screened onset measures the step to 1 %, and one more whole Gauss-Newton step from the
    nominal fit's end moves it by under ``STATIONARY_SE`` of the residual's RMS."""
    from gyrojax.diagnose._gyrotheodolite import NOMINAL, GyrotheodoliteProblem
    from gyrojax.io import load_record

    rec = tmp_path / "step3.nc"
    assert main(["simulate", "--rig", "gyrotheodolite", "--seed", "9", "--set",
                 f"index_offset={OFFSET}", "--set", "alpha0=5", "--set", "M_step=3.0", "--set",
                 "t_step=12", "--out", str(rec)]) == 0
    prob = GyrotheodoliteProblem(load_record(rec), holdout=0.25)
    n = prob.n_train
    p0 = prob.fit_nominal()
    assert prob.notes == []
    cols = [prob.all_names.index(k) for k in NOMINAL]
    pred, jac = prob._eval(prob.base | p0)
    r = prob.y[:n, 0] - pred[:n]
    left, *_ = np.linalg.lstsq(jac[:n, cols], r, rcond=None)
    rms = np.sqrt(np.sum(r**2) / (n - len(NOMINAL)))  # the step's misfit included
    assert np.linalg.norm(jac[:n, cols] @ left) / rms < STATIONARY_SE
    sigma = np.array([2.0 * units.ARCSEC])
    _, sigs = prob.jacobians(p0, sigma)
    step = next(s for s in sigs if s.name == "torque_step")
    _, coeffs, _ = prob.refit(p0, [(step, 5)], sigma)
    assert coeffs["M_step"] == pytest.approx(3.0, rel=0.01)
    assert prob.notes == []


@pytest.mark.parametrize("prior", [None, "design", "shell"])
def test_blind_harness_diagnoses_under_the_prior_it_is_given(tmp_path, monkeypatch, prior):
    """The blind suites' ``--prior`` reaches the diagnosis: ``run(prior=...)`` calls
    ``diagnose`` with that prior (none given: none passed, the diagnosis' default)."""
    import gyrojax.diagnose
    from gyrojax.validation import gyrotheodolite as bg

    bg.generate(tmp_path, 1, seed=3, null_fraction=1.0)
    seen = {}

    class Called(Exception):
        pass

    def fake(record, **kw):
        seen.update(kw)
        raise Called

    monkeypatch.setattr(gyrojax.diagnose, "diagnose", fake)
    with pytest.raises(Called):
        bg.run(tmp_path, prior=prior)
    assert seen.get("prior") == prior
    assert seen["rig"] == "gyrotheodolite"
