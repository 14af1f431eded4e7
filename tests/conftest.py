import os

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402
import pytest  # noqa: E402

import gyrojax  # noqa: E402,F401  (switches JAX to float64)


@pytest.fixture(autouse=True)
def _float64():
    assert jax.config.jax_enable_x64, "gyrojax must run JAX in float64"
