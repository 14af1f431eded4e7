"""Regenerate the figures of the rig guides (``docs/figures/*.png``) from the command line and
the library, as a user would make them: ``python docs/make_figures.py`` (a few minutes, mostly
compilation). Each figure's command is printed before it runs."""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

OUT = Path(__file__).resolve().parent / "figures"

COMMANDS = [
    "gyrojax demo --plot esg_demo.png",
    "gyrojax observer --omega0 1 10 100 1000 --plot gyrotheodolite_fig1.png",
    "gyrojax simulate --rig schuler --periods 2 --sample 10 --set nudot2=0.05 --out ins.nc",
    "gyrojax diagnose ins.nc --rig schuler --plot schuler_gap.png",
    "gyrojax simulate --rig platform --schedule '{\"table_amplitudes_g\": [9, 7]}' --out plat.nc",
    "gyrojax diagnose plat.nc --rig platform --plot platform_gap.png",
    "gyrojax simulate --rig imu --poses 12 --dwell 10 --set sax=800 --set maxy=2 --latitude 45 "
    "--out imu.csv",
    "gyrojax diagnose imu.csv --rig imu --latitude 45 --plot imu_gap.png",
]

PYTHON = '''
import jax, numpy as np
from gyrojax import units
from gyrojax.analysis import mounting_error_budget
from gyrojax.analysis.spectral import allan_deviation, fit_noise_likelihood, fit_noise_terms
from gyrojax.plots import plot_allan, plot_budget

rng = np.random.default_rng(0)
rate_hz, n = 100.0, 360_000                       # one hour at 100 Hz
arw = 0.2 * units.DEG / 60 * np.sqrt(rate_hz)     # 0.2 deg/sqrt(h), per sample
rrw = 20 * units.DEG_PER_HOUR / 60 / np.sqrt(rate_hz)  # 20 deg/h/sqrt(h), per sample
x = arw * rng.standard_normal(n) + np.cumsum(rrw * rng.standard_normal(n))
ad = allan_deviation(x, rate_hz)
fits = {"Allan NNLS": fit_noise_terms(ad), "Whittle ML": fit_noise_likelihood(x, rate_hz).terms}
plot_allan(ad, fits, title="white rate noise + rate random walk", path="allan.png")
plot_budget(mounting_error_budget(jax.random.key(0), 2000, alpha20_deg=30.0), path="budget.png")
'''


def main() -> None:
    OUT.mkdir(exist_ok=True)
    bindir = Path(sys.executable).parent
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ['PATH']}", MPLBACKEND="Agg")
    with tempfile.TemporaryDirectory() as tmp:
        for cmd in COMMANDS:
            print("$", cmd, flush=True)
            subprocess.run(shlex.split(cmd), cwd=tmp, env=env, check=True,
                           stdout=subprocess.DEVNULL)
        print("$ python (Allan deviation, Monte Carlo budget)", flush=True)
        subprocess.run([sys.executable, "-c", PYTHON], cwd=tmp, env=env, check=True)
        for png in sorted(Path(tmp).glob("*.png")):
            shutil.copy(png, OUT / png.name)
            print("wrote", OUT / png.name)


if __name__ == "__main__":
    main()
