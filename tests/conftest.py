import os
import shutil
import tempfile

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402
import pytest  # noqa: E402

import gyrojax  # noqa: E402,F401  (switches JAX to float64)
from gyrojax._cache import CACHE_ENV, enable_compilation_cache  # noqa: E402


def pytest_configure(config):
    """One compilation cache per test run (``$GYROJAX_COMPILATION_CACHE`` if set), shared by
    the xdist workers, which inherit the controller's environment: what two tests compile
    alike is compiled once. A run made here is removed at its end."""
    if not hasattr(config, "workerinput") and CACHE_ENV not in os.environ:
        os.environ[CACHE_ENV] = config._gyrojax_cache = tempfile.mkdtemp(prefix="gyrojax-jax-")
    enable_compilation_cache()


def pytest_unconfigure(config):
    made = getattr(config, "_gyrojax_cache", None)
    if made:
        shutil.rmtree(made, ignore_errors=True)
        os.environ.pop(CACHE_ENV, None)


@pytest.fixture(autouse=True)
def _float64():
    assert jax.config.jax_enable_x64, "gyrojax must run JAX in float64"
