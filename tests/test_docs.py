"""The documentation's Python runs: every ```python block of a page, in order, in one
namespace (a page is one session), in a fresh directory. The compile check is quick and runs by
default; running the pages compiles the rigs' fits and runs in the slow suite."""

import os
import re
from pathlib import Path

import matplotlib
import pytest

DOCS = Path(__file__).parent.parent / "docs"
PAGES = sorted(p for p in DOCS.rglob("*.md") if "```python" in p.read_text(encoding="utf-8"))


def _code(page: Path) -> str:
    return "\n".join(re.findall(r"```python\n(.*?)```", page.read_text(encoding="utf-8"), re.S))


def _ids(pages):
    return [str(p.relative_to(DOCS)) for p in pages]


def test_the_documented_pages_hold_python():
    """The guides that show code are found (a renamed page or fence would silently drop out)."""
    names = set(_ids(PAGES))
    assert {"concepts.md", "estimation.md", "observability.md", "montecarlo.md",
            "diagnosis.md", "getting-started.md"} <= names, names


@pytest.mark.parametrize("page", PAGES, ids=_ids(PAGES))
def test_each_page_compiles(page):
    compile(_code(page), str(page), "exec")


@pytest.mark.slow  # each page compiles the fits it shows (10-60 s); CI runs them
@pytest.mark.parametrize("page", PAGES, ids=_ids(PAGES))
def test_each_page_runs(page, tmp_path, monkeypatch):
    code = _code(page)
    if "REAL_DATA_SETS" in code:
        from gyrojax.datasets import data_root
        try:
            data_root()
        except Exception as exc:  # noqa: BLE001 - the data are optional
            pytest.skip(f"the real data are not here: {exc}")
    monkeypatch.chdir(tmp_path)
    backend = matplotlib.get_backend()
    exec(compile(code, str(page), "exec"), {"__name__": "__docs__"})
    assert matplotlib.get_backend() == backend
    assert os.getcwd() == str(tmp_path)


def test_public_signatures_resolve():
    """Every public function's annotations (jaxtyping shapes included) name real types: the API
    reference renders them, and a typo would otherwise only show there."""
    import importlib
    import inspect
    import typing

    names = ["gyrojax.simulate", "gyrojax.io", "gyrojax.estimate.kalman",
             "gyrojax.estimate.least_squares", "gyrojax.estimate.observer",
             "gyrojax.estimate.platform", "gyrojax.estimate.schuler", "gyrojax.estimate.spiral",
             "gyrojax.estimate.multiposition", "gyrojax.analysis.observability",
             "gyrojax.analysis.spectral", "gyrojax.analysis.vibration", "gyrojax.analysis.mounting",
             "gyrojax.analysis.montecarlo", "gyrojax.models.imu", "gyrojax.models.schuler"]
    import pandas
    import xarray

    local = {"xr": xarray, "pd": pandas}  # imported for type checking only in gyrojax.io
    checked = 0
    for name in names:
        mod = importlib.import_module(name)
        for attr in getattr(mod, "__all__", ()):
            fn = getattr(mod, attr)
            if inspect.isfunction(fn) and fn.__module__ == name:
                typing.get_type_hints(fn, localns=local)
                checked += 1
    assert checked >= 60
