"""matplotlib figures: records, fits and residuals, Monte Carlo error budgets."""

from __future__ import annotations

import numpy as np

from . import units


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path):
    from .io import atomic_write

    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))


def plot_fit(rig, record, conditions, report, path=None):
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


def plot_budget(budget, path=None):
    """Bar chart of the RMS drift-identification error per scheme and parameter (deg/h, log)."""
    plt = _plt()
    from .models.esg import DRIFT_NAMES

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    x = np.arange(len(DRIFT_NAMES))
    w = 0.8 / len(budget.schemes)
    for ax, which, title in zip(axes, ("drift_only", "joint"),
                                ("drift only (mounting errors ignored)", "drift + mounting errors")):
        rms = budget.rms(which)
        for i, s in enumerate(budget.schemes):
            ax.bar(x + i * w, rms[s], w, label=s)
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


def plot_frequency_study(study, path=None):
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
