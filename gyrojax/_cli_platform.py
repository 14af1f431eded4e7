"""``gyrojax simulate|fit|observability --rig platform``: the platform under linear vibration.

The schedule and the record layout are in :mod:`gyrojax.models.platform_schedule`.
"""

from __future__ import annotations

import numpy as np

from ._cli_base import AbstractRigCommands, emit_json, load, parse_sets
from .models.platform_schedule import (
    CHANNELS,
    dwell_times,
    load_schedule,
    schedule_conditions,
    simulate_schedule,
    split_record,
)


def simulate(args):
    import jax

    from .io import record_path, save_record
    from .models.platform import TRUE_TABLE2, PlatformRig

    out = record_path(args.out)  # ValueError: exit 2, before the simulation
    s = load_schedule(args.schedule) if args.schedule else load_schedule({})
    space = PlatformRig().param_space
    params = space.make(TRUE_TABLE2, display=True) | parse_sets(args.set, space)
    rec = simulate_schedule(params, s, jax.random.key(args.seed), noise_arcsec=args.noise_arcsec)
    ts = dwell_times(s)
    save_record(rec, out, units=PlatformRig.CHANNEL_UNITS)
    print(f"wrote {out}: {len(s['positions_deg'])} positions x "
          f"{len(s['table_amplitudes_g'])} amplitudes ({s['table_amplitudes_g']} g), "
          f"{len(ts)} samples per dwell")


def fit(args):
    import equinox as eqx
    import jax.numpy as jnp

    from . import units
    from .estimate.least_squares import convergence_text
    from .estimate.platform import (
        platform_gauss_newton,
        platform_kalman,
        platform_regression,
        record_kappas,
        two_amplitude_resolution,
    )
    from .models.platform import COEFF_NAMES, PlatformRig

    record = load(args, CHANNELS)
    attrs = record.conditions
    if args.schedule:
        s = load_schedule(args.schedule)
    elif "schedule_json" in attrs:
        s = load_schedule(attrs["schedule_json"])
    else:
        raise ValueError("the record carries no schedule; give --schedule FILE")
    data = split_record(record, s)
    ts = jnp.asarray(dwell_times(s))
    recs, conds, kappas = [], [], record_kappas(data, s)
    for k, (c, kap) in enumerate(zip(schedule_conditions(s), kappas)):
        recs.append(jnp.asarray(data[k, :, :, :3]))
        conds.append(eqx.tree_at(lambda x: x.kappa, c, jnp.full(len(s["positions_deg"]), kap)))
    space = PlatformRig().param_space
    method = args.method or "joint"
    if method not in ("joint", "s21", "kalman", "gauss-newton"):
        raise ValueError(f"--method {method!r} is not a platform method; use joint (regression "
                         "(S22) of all amplitudes, the default), s21, kalman (the source's EKF) "
                         "or gauss-newton (batch fit of the ODE model)")
    if method == "s21":
        if len(recs) != 2:
            raise ValueError("--method s21 needs a schedule with exactly two amplitudes")
        if min(s["table_amplitudes_g"]) == 0:
            raise ValueError("--method s21 with a 0 g amplitude: the amplitude prior (17) divides "
                             "by the first amplitude; use --method joint")
        free = tuple(n for n in COEFF_NAMES if not n.startswith("D_oo"))
        fits = [platform_regression(ts, [r], [c], free=free) for r, c in zip(recs, conds)]
        est = two_amplitude_resolution(fits[0].full(), fits[1].full(), kappas[0], kappas[1])
        se = {}
        noise = float(fits[0].noise_std)
    else:
        res = platform_regression(ts, recs, conds)
        noise = float(res.noise_std)
        if method == "kalman":
            res = platform_kalman(ts, recs, conds, noise_std=noise)
        elif method == "gauss-newton":
            res = platform_gauss_newton(ts, recs, conds, start=res.as_dict(), noise_std=noise)
        est, se = res.as_dict(), res.stderr_dict()
    # a regression (joint, s21) is a direct solve and the filter one pass: only Gauss-Newton
    # can stop short of its solution
    fit_info = ({"converged": bool(res.converged), "num_steps": int(res.num_steps),
                 "remaining_step_se": float(res.remaining_step_se)}
                if method == "gauss-newton" else {"converged": True})
    print(f"platform fit ({method}); kappa from the accelerometers: "
          + ", ".join(f"{k:.4f}" for k in kappas) + f"; angle noise {noise / units.ARCSEC:.3f} "
          "arcsec")
    print(f"{'coefficient':12s} {'estimate':>12s} {'stderr':>10s}  unit")
    out = {}
    for n in COEFF_NAMES:
        p = space[n]
        v = float(p.to_display(est[n]))
        e = float(p.to_display(se[n])) if n in se else None
        out[n] = {"value": v, "stderr": e, "unit": p.display_unit}
        print(f"{n:12s} {v:12.5f} {'' if e is None else f'{e:10.2g}'}  {p.display_unit}")
    if method == "gauss-newton":
        print(convergence_text(res.converged, res.num_steps, res.remaining_step_se))
    emit_json({"method": method, "parameters": out, "kappa": kappas,
               "noise_std_arcsec": noise / units.ARCSEC} | fit_info, args.json)


def observability(args):
    from .analysis.observability import analyse_jacobian
    from .analysis.platform_design import (
        design_information,
        dwell_jacobians,
        propose_positions,
        score_design,
    )
    from .models.platform import COEFF_NAMES, PlatformRig

    s = load_schedule(args.schedule) if args.schedule else load_schedule({})
    pos = np.asarray(s["positions_deg"], float)
    a0s = [a / s["attenuation"] for a in s["table_amplitudes_g"]]
    jacs = [dwell_jacobians(pos, a, mounting=s["mounting_matrix"]) for a in a0s]
    # null directions in the coefficients' own units (all rad/s inside: deg/h, deg/h/g, ...)
    scales = PlatformRig().param_space.scales(COEFF_NAMES)
    rep = analyse_jacobian(np.concatenate([j.reshape(-1, 30) for j in jacs]) / scales,
                           COEFF_NAMES)
    print(rep.summary())
    info = sum(design_information(j, dwell_s=s["dwell_s"], dt=s["sample_s"]) for j in jacs)
    sc = score_design(info)
    print(f"design: rank {sc.rank}/30, log det {sc.log_det:.2f}, worst standard error "
          f"{sc.worst_se:.3g} coefficient scales ({sc.worst})")
    out = {"observability": rep.to_json(), "design": sc.__dict__}
    if args.propose and sc.rank == 30:
        best_pos, best = propose_positions(a0s, n_positions=len(pos), dwell_s=s["dwell_s"],
                                           dt=s["sample_s"], mounting=s["mounting_matrix"])
        print(f"proposed {len(pos)}-position design: log det {best.log_det:.2f}, worst standard "
              f"error {best.worst_se:.3g} ({best.worst}); positions (deg): {best_pos.tolist()}")
        out["proposed"] = {"positions_deg": best_pos.tolist(), **best.__dict__}
    emit_json(out, args.json)


class PlatformCommands(AbstractRigCommands):
    """The platform's commands."""

    name = "platform"
    COMMANDS = ("simulate", "fit", "observability", "diagnose")
    ELSEWHERE = "gyrojax simulate, fit, observability or diagnose --rig platform"

    def add_arguments(self, command, group):
        if command in ("simulate", "fit", "observability", "diagnose"):
            group.add_argument("--schedule", metavar="JSON",
                               help="platform: test schedule file (positions_deg, "
                                    "table_amplitudes_g, attenuation, frequency_hz, dwell_s, "
                                    "sample_s, latitude_deg, mounting, phases_rad: the "
                                    "vibration phase of each dwell, amplitude-major); default "
                                    "Table 1 at 9 and 7 g; a simulated record carries its "
                                    "schedule")
        if command == "observability":
            group.add_argument("--propose", action="store_true",
                               help="platform: also search a better position set (Fisher "
                                    "information)")
        if command == "diagnose":
            group.add_argument("--split", choices=("same-design", "design-shift"),
                               help="platform: held-out plan (same-design = the end of every "
                                    "dwell, the default; design-shift = the last vibration "
                                    "amplitude's run, whole)")
            group.add_argument("--nominal-terms", metavar="TERMS",
                               help="platform: comma-separated drift-law terms the nominal "
                                    "model carries for every gyro, from "
                                    "f,i,o,s,ii,oo,ss,io,is,os (default all but oo, the source's "
                                    "model; f,i,o,s = the first-order model); every "
                                    "coefficient left out is screened as an effect of its own")

    def simulate(self, args):
        args.noise_arcsec = 1.0 if args.noise_arcsec is None else args.noise_arcsec
        simulate(args)

    def fit(self, args):
        fit(args)

    def observability(self, args):
        observability(args)

    def load(self, args):
        from .models.platform_schedule import schedule_json

        record = load(args, CHANNELS)
        if args.schedule:
            record = record.with_conditions(
                schedule_json=schedule_json(load_schedule(args.schedule)))
        return record

    def diagnose_options(self, args):
        terms = None
        if args.nominal_terms is not None:
            terms = tuple(t.strip() for t in args.nominal_terms.split(",") if t.strip())
        return {"split": args.split, "nominal_terms": terms}
