"""matplotlib figures: records, fits and residuals, Monte Carlo error budgets."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from . import units

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from .analysis.mounting import MountingBudget, MountingBudgetStats
    from .analysis.spectral import AllanDeviation, NoiseTerms
    from .analysis.vibration import FrequencyStudy
    from .diagnose import GapReport
    from .estimate import FitReport
    from .record import BenchRecord


def _plt():
    """pyplot, on whatever backend the session has: none is chosen or switched here (a
    notebook's inline figures keep showing; with no display, matplotlib itself falls back to
    Agg)."""
    import matplotlib.pyplot as plt

    return plt


FIGURE_FORMATS = ("png", "pdf", "svg")


def figure_format(path) -> str:
    """The figure format a file name asks for (its suffix: .png, .pdf or .svg)."""
    from pathlib import Path

    fmt = Path(path).suffix.lower().lstrip(".")
    if fmt not in FIGURE_FORMATS:
        raise ValueError(f"figure file {str(path)!r}: use a "
                         + ", ".join(f".{f}" for f in FIGURE_FORMATS) + " file name")
    return fmt


def figure_writer(fig, path):
    """A ``write_fn(tmp_path)`` for :func:`gyrojax.io.write_together` saving ``fig`` in the
    format ``path`` names (checked now)."""
    fmt = figure_format(path)
    return lambda tmp: fig.savefig(tmp, dpi=110, format=fmt)


def _save(fig, path):
    """Save ``fig`` to ``path`` and close it in pyplot (a figure written to a file is not
    shown again, and a loop of saved plots keeps no figure open); it stays a figure to use."""
    from .io import atomic_write

    atomic_write(path, figure_writer(fig, path))
    _plt().close(fig)


def plot_fit(rig, record: BenchRecord, conditions, report: FitReport,
             path: str | os.PathLike | None = None) -> Figure:
    """Measured vs fitted gimbal angles (deg) and residuals (arcsec) over time (h)."""
    from .simulate import integrate

    plt = _plt()
    t_h = np.asarray(record.t) / units.HOUR
    pred = np.asarray(integrate(rig, report.params, conditions, record.t))
    y = np.asarray(record.y)
    fig, ax = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for j, name in enumerate(record.channels):
        ax[0].plot(t_h, y[:, j] / units.DEG, ".", ms=2, label=f"{name} measured")
        ax[0].plot(t_h, pred[:, j] / units.DEG, "-", lw=1, label=f"{name} fit ({report.method})")
        ax[1].plot(t_h, (y[:, j] - pred[:, j]) / units.ARCSEC, lw=0.7, label=name)
    ax[0].set_ylabel("gimbal angle [deg]")
    ax[0].legend(fontsize=8, ncol=2)
    ax[1].set_ylabel("residual [arcsec]")
    ax[1].set_xlabel("time [h]")
    ax[1].legend(fontsize=8)
    ax[0].set_title(f"fit by {report.method}: residual RMS "
                    f"{report.residual_rms / units.ARCSEC:.3f} arcsec")
    fig.tight_layout()
    if path:
        _save(fig, path)
    return fig


def plot_budget(budget: MountingBudget | MountingBudgetStats,
                path: str | os.PathLike | None = None) -> Figure:
    """Bar chart of the RMS drift-identification error per scheme and parameter (deg/h, log),
    with its standard error."""
    plt = _plt()
    from .models.esg import DRIFT_NAMES

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    x = np.arange(len(DRIFT_NAMES))
    w = 0.8 / len(budget.schemes)
    for ax, which, title in zip(axes, ("drift_only", "joint"),
                                ("drift only (mounting errors ignored)", "drift + mounting errors")):
        rms, se = budget.rms(which), budget.rms_se(which)
        for i, s in enumerate(budget.schemes):
            ax.bar(x + i * w, rms[s], w, yerr=se[s], capsize=2, label=s)
        ax.set_xticks(x + 0.4 - w / 2, DRIFT_NAMES)
        ax.set_yscale("log")
        ax.set_title(title, fontsize=10)
    axes[0].set_ylabel("RMS error [deg/h]")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Monte Carlo error budget, {budget.n_draws} draws per scheme")
    fig.tight_layout()
    if path:
        _save(fig, path)
    return fig


def plot_frequency_study(study: FrequencyStudy, path: str | os.PathLike | None = None) -> Figure:
    """Fig. 1 of the gyrotheodolite paper: amplitude (rad/s per g, log-log) and phase (deg) of the
    true rate response to ``n_X`` and of the observer's estimate for each ``omega0``."""
    plt = _plt()
    w = np.asarray(study.omegas)
    fig, ax = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    curves = [("plant (10)", np.asarray(study.plant), dict(color="k", lw=2.2))]
    curves += [(f"observer, omega0 = {w0:g} 1/s", np.asarray(study.observer[i]), dict(lw=1.1))
               for i, w0 in enumerate(np.asarray(study.omega0s))]
    for label, h, style in curves:
        ax[0].loglog(w, np.abs(h), label=label, **style)
        ax[1].semilogx(w, np.degrees(np.unwrap(np.angle(h))), label=label, **style)
    ax[0].set_ylabel("|alpha_dot / n_X| [rad/s per g]")
    ax[1].set_ylabel("phase [deg]")
    ax[1].set_xlabel("vibration frequency omega [rad/s]")
    ax[0].legend(fontsize=8)
    ax[0].set_title("azimuth-rate response to vibration: plant and observer estimate")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    if path:
        _save(fig, path)
    return fig


def plot_gap_report(report: GapReport, path: str | os.PathLike | None = None) -> Figure:
    """One figure of a gap diagnosis: the time x channel gap map (-log10 q per dyadic window),
    the whitened residuals before and after the verdict's refit (train | held-out), the
    candidate ranking (posterior, score test -log10 p), the tau band (Allan variance of the
    residual over its null prediction, 95 % EDF intervals) and the position / condition / aux cells
    (-log10 q)."""
    plt = _plt()
    cells = [x for x in report.where if x["axis"] == "time"]
    chans = list(report.channels)
    levels = sorted({x["level"] for x in cells})
    n_rows = len(levels) * len(chans)
    # the map grows with its rows (dyadic levels x channels: 30 on a six-channel IMU record)
    h_map = max(1.1, 0.09 * n_rows)
    fig = plt.figure(figsize=(11, 2.56 * (h_map + 3.0)))
    gs = fig.add_gridspec(4, 2, height_ratios=[h_map, 1.0, 1.0, 1.0])
    ax_map = fig.add_subplot(gs[0, :])
    widths = [min(x["t1"] - x["t0"] for x in cells if x["level"] == lv) for lv in levels]
    cmap = plt.get_cmap("magma_r")
    for x in cells:
        row = levels.index(x["level"]) * len(chans) + chans.index(x["channel"])
        val = min(-np.log10(max(x["q"], 1e-300)), 10.0)
        ax_map.barh(row, (x["t1"] - x["t0"]) / units.HOUR, left=x["t0"] / units.HOUR, height=0.9,
                    color=cmap(val / 10.0), edgecolor="k" if x["significant"] else "none", lw=0.6)
    _label_map_rows(ax_map, widths, chans)
    ax_map.set_xlabel("time [h]")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, 10))
    fig.colorbar(sm, ax=ax_map, label="-log10 q (capped at 10)")
    ax_map.set_title(_map_title(report), fontsize=9)
    t_h = report.t / units.HOUR
    split = report.t[report.n_train - 1] / units.HOUR if report.n_heldout else None
    for k, (res, title) in enumerate([(report.residual_all, "nominal model"),
                                      (report.residual_after, "after refit")]):
        ax = fig.add_subplot(gs[1 + k, 0])
        if res is None:
            ax.text(0.5, 0.5, "no refit (no gap, or nothing to refit)", ha="center",
                    transform=ax.transAxes)
        else:
            for j, c in enumerate(chans):
                ax.plot(t_h, res[:, j], lw=0.6, label=c)
        if split is not None:
            ax.axvline(split, color="k", ls="--", lw=0.8)
        ax.set_ylabel("residual / noise")
        ax.set_title(f"whitened residual, {title} (train | held-out)", fontsize=9)
        if res is not None:  # a legend without lines is a matplotlib warning, and empty
            ax.legend(fontsize=6, ncol=min(len(chans), 6), loc="upper right", framealpha=0.7)
    ax_rank = fig.add_subplot(gs[1:3, 1])
    names = [r.name for r in report.ranking][::-1]
    post = [r.posterior for r in report.ranking][::-1]
    logp = [min(-np.log10(max(r.p, 1e-300)), 50.0) for r in report.ranking][::-1]
    yy = np.arange(len(names))
    ax_rank.barh(yy - 0.2, post, height=0.4, label="posterior")
    ax2 = ax_rank.twiny()
    ax2.barh(yy + 0.2, logp, height=0.4, color="tab:orange", label="-log10 p (score)")
    ax_rank.set_yticks(yy)
    ax_rank.set_yticklabels([f"{n}\n({r['flag']})" for n, r in
                             zip(names, report.ranking[::-1])], fontsize=7)
    ax_rank.set_xlabel("posterior")
    ax2.set_xlabel("-log10 p of the score test (capped at 50)")
    ax_rank.set_xlim(0, 1)
    _plot_tau_band(fig.add_subplot(gs[3, 0]), report.where, chans)
    _plot_positions(fig.add_subplot(gs[3, 1]), report.where, chans)
    fig.tight_layout()
    if path:
        _save(fig, path)
    return fig


def _label_map_rows(ax, widths, chans):
    """The gap map's rows: each channel on a row of its own (minor ticks), each dyadic level's
    window length once beside its group (major ticks), a rule between the groups."""
    n_ch = len(chans)
    rows = range(len(widths) * n_ch)
    ax.set_yticks(rows, minor=True)
    ax.set_yticklabels([c for _ in widths for c in chans], minor=True)
    # tick_params, not set_yticklabels(fontsize=): that styles only the tick objects that exist
    ax.tick_params(axis="y", which="minor", labelsize=7 if len(rows) <= 16 else 5)
    if n_ch == 1:  # one row per level: the length is the row's label
        ax.set_yticks(rows)
        ax.set_yticklabels([f"{w / units.HOUR:.2g} h" for w in widths])
        ax.tick_params(axis="y", which="major", labelsize=7)
        ax.tick_params(axis="y", which="minor", left=False, labelleft=False)
    else:
        ax.set_yticks([k * n_ch + (n_ch - 1) / 2 for k in range(len(widths))])
        ax.set_yticklabels([f"{w / units.HOUR:.2g} h" for w in widths])
        ax.tick_params(axis="y", which="major", length=0, labelsize=7,
                       pad=4 + 4.2 * max(len(c) for c in chans))
        for k in range(1, len(widths)):
            ax.axhline(k * n_ch - 0.5, color="0.4", lw=0.6, zorder=3)
    ax.set_ylim(len(rows) - 0.5, -0.5)  # the whole record first, shorter windows below
    ax.set_ylabel("window length" if n_ch == 1 else "window length, channel", fontsize=8)


def _map_title(report) -> str:
    """The verdict and the significant frequency lines (each named once, with its count of
    channels), wrapped to two lines at most."""
    import textwrap

    head = f"verdict: {report.kind} {', '.join(report.verdict.effects)}".rstrip()
    names = [x["cell"] for x in report.where if x["axis"] == "frequency" and x["significant"]]
    if names:
        counts = dict.fromkeys(names, 0)
        for nm in names:
            counts[nm] += 1
        lines = ", ".join(nm if k == 1 else f"{nm} x{k}" for nm, k in counts.items())
        head += f"; significant lines: {lines}"
    return "\n".join(textwrap.wrap(head, 150, max_lines=2, placeholder=" ..."))


def _plot_tau_band(ax, where, chans):
    cells = [x for x in where if x["axis"] == "tau"]
    if not cells:
        ax.text(0.5, 0.5, "no tau band (record too short)", ha="center", transform=ax.transAxes)
        return
    full = any(x.get("rate") == "full" for x in cells)
    for j, c in enumerate(chans):
        color = None
        for rate in (None, "full"):  # the decided rows' band, then the full-rate band
            xs = [x for x in cells if x["channel"] == c and x.get("rate") == rate]
            if not xs:
                continue
            tau = np.array([x["tau_s"] for x in xs]) * (1 + 0.04 * (j - (len(chans) - 1) / 2))
            r = np.array([x["statistic"] for x in xs])
            ci = np.array([x["ci95"] for x in xs]).T
            line = ax.errorbar(tau, r, yerr=[r - ci[0], ci[1] - r],
                               fmt="o-" if rate is None else "s--", ms=4 if rate is None else 3,
                               lw=0.8, capsize=2, color=color,
                               label=c if color is None else None)
            color = line[0].get_color()
            sig = [x.get("significant", False) for x in xs]
            ax.scatter(tau[sig], r[sig], s=60, facecolors="none", edgecolors=color, lw=1.4)
    if full:
        ax.plot([], [], "ks--", ms=3, lw=0.8, label="full rate (reported)")
    ax.axhline(1.0, color="k", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("tau [s]")
    ax.set_ylabel("AVAR ratio")
    ax.set_title("tau band: Allan variance of the residual / null (ringed: significant)",
                 fontsize=9)
    ax.legend(fontsize=7)


def _plot_positions(ax, where, chans):
    cells = [x for x in where if x["axis"] in ("position", "condition", "aux")]
    if not cells:
        ax.text(0.5, 0.5, "no test positions or auxiliary channels in this record",
                ha="center", transform=ax.transAxes)
        ax.set_axis_off()
        return

    def label(x):
        return f"all at {x['cell']}" if x["axis"] == "condition" else x["cell"]
    labels = list(dict.fromkeys(label(x) for x in cells))
    width = 0.8 / len(chans)
    for j, c in enumerate(chans):
        xs = {label(x): x for x in cells if x["channel"] == c}
        val = [min(-np.log10(max(xs[k]["q"], 1e-300)), 10.0) if k in xs else 0.0
               for k in labels]
        ax.bar(np.arange(len(labels)) + (j - (len(chans) - 1) / 2) * width, val, width,
               label=c)
    ax.set_xticks(range(len(labels)))
    ax.set_xticklabels(labels, rotation=90, fontsize=5 if len(labels) > 20 else 7)
    ax.set_ylabel("-log10 q (capped at 10)")
    ax.set_title("position / condition / auxiliary-channel cells", fontsize=9)
    ax.legend(fontsize=7, ncol=min(len(chans), 6))


def plot_allan(ad: AllanDeviation, fits: Mapping[str, NoiseTerms] | None = None, *, unit: str = "deg/h",
               title: str = "", path: str | os.PathLike | None = None, ax: Axes | None = None) -> Figure:
    """Overlapping Allan deviation with its confidence intervals, and the AVAR curves of fitted
    noise terms (``fits``: label -> :class:`gyrojax.analysis.spectral.NoiseTerms`), in ``unit``
    (deg/h for a gyro, mg for an accelerometer)."""
    plt = _plt()
    if ax is None:
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
    else:
        fig = ax.figure
    k = units.from_unit(1.0, unit)
    ax.errorbar(ad.tau, ad.adev / k, yerr=[(ad.adev - ad.lo) / k, (ad.hi - ad.adev) / k], fmt="o",
                ms=3, capsize=2, label=f"ADEV ({ad.confidence:.0%} interval, edf)")
    tau = np.geomspace(ad.tau[0], ad.tau[-1], 200)
    for (label, terms), style in zip((fits or {}).items(), ("-", "--", ":", "-.")):
        ax.plot(tau, np.sqrt(terms.avar(tau)) / k, style, lw=1.2, label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("tau [s]")
    ax.set_ylabel(f"Allan deviation [{unit}]")
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=9)
    if path:
        _save(fig, path)
    return fig
