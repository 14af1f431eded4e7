"""The README's examples run and say what they claim: every `gyrojax` command line it and its
command-line page (docs/cli.md) show parses with the CLI's own parser, and its Python tour runs
and prints what its comments say."""

import re
import shlex
from pathlib import Path

import jax
import pytest

from gyrojax.cli import build_parser

README = Path(__file__).parent.parent / "README.md"
CLI_DOC = Path(__file__).parent.parent / "docs" / "cli.md"  # the README's command-line page


def _blocks(lang: str, *pages: Path) -> list[str]:
    return [b for page in pages or (README,)
            for b in re.findall(rf"```{lang}\n(.*?)```", page.read_text(), re.S)]


def _cli_lines() -> list[tuple[str, list[str]]]:
    """(line, argv) of every `gyrojax ...` command in the README's bash blocks (also the
    `.venv/bin/gyrojax` of a chained install line)."""
    out = []
    for block in _blocks("bash", README, CLI_DOC):
        for line in block.splitlines():
            tokens = shlex.split(line, comments=True)
            segment: list[str] = []
            for tok in [*tokens, "&&"]:
                if tok != "&&":
                    segment.append(tok)
                    continue
                if segment and Path(segment[0]).name == "gyrojax":
                    out.append((line, segment[1:]))
                segment = []
    return out


def test_readme_cli_examples_parse():
    lines = _cli_lines()
    # the README shows the ESG, Schuler, platform, IMU and gyrotheodolite commands: a parser
    # that found none of them (a changed fence, say) must not pass
    assert len(lines) >= 25, [x for x, _ in lines]
    assert {argv[0] for _, argv in lines} >= {"demo", "simulate", "fit", "observability",
                                              "montecarlo", "effects", "diagnose", "observer"}
    parser = build_parser()
    for line, argv in lines:
        try:
            args = parser.parse_args(argv)
        except SystemExit:
            pytest.fail(f"the README's command does not parse: {line.strip()}")
        assert args.command == argv[0]


@pytest.mark.slow  # ~80 s: the tour fits, reproduces Tables 2-3 and diagnoses with design advice
def test_readme_tour_runs_and_prints_what_it_says(tmp_path, monkeypatch, capsys):
    tour, = _blocks("python")
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(tour, str(README), "exec"), ns)
    out = capsys.readouterr().out
    # the fit against the generating parameters (deg/h), within 4 of its standard errors
    fit = ns["report"].to_json()
    assert fit["converged"]
    for name, truth in (("m11", 0.15), ("mc2", -0.15)):
        p = fit["parameters"][name]
        assert p["unit"] == "deg/h" and abs(p["value"] - truth) < 4 * p["stderr"], (name, p)
    # equatorial scheme: the rotor tilt has no signature (variant 3 of docs/rigs/esg.md)
    assert "unobservable directions: theta1; theta2" in out
    assert "| polar | 206 | 200 |" in out  # Table 2, first row, as the README says
    # "here: no-gap - the 60 arcsec eps3 is almost wholly absorbed by the drifts, which the
    # ranking says by name (visible fraction ~4e-8)"
    gap = ns["gap"]
    assert gap.kind == "no-gap", gap.markdown()
    vis = gap.candidate("base_misalignment")["visible_fraction"]
    assert 1e-9 < vis < 1e-7, vis
    assert "Verdict: no-gap" in out
    # "at alpha 0.05 about one record in 20 with nothing visible alarms (key(0) does)"
    rec0 = ns["gj"].simulate(ns["rig"], ns["truth"], ns["cond"], ns["ts"], key=jax.random.key(0),
                             noise_std=ns["units"].ARCSEC)
    rep0 = ns["diagnose"](rec0, conditions={"scheme": "equatorial", "latitude_deg": 55.75},
                          design_advice=False)
    assert rep0.kind != "no-gap", rep0.markdown()
