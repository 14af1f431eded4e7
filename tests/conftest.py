import gc
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


def _memory_maps() -> int | None:
    """This process's memory-map count (Linux), or ``None`` where it cannot be read."""
    try:
        with open("/proc/self/maps", "rb") as fh:
            return sum(1 for _ in fh)
    except OSError:
        return None


def _map_limit() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as fh:
            return int(fh.read())
    except (OSError, ValueError):
        return 65530


MAP_LIMIT = _map_limit()


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    """Every compiled XLA:CPU program holds a few memory maps of its own, and a test worker
    that runs hundreds of tests holds thousands of programs: past the kernel's limit
    (``vm.max_map_count``, 65530 by default) LLVM cannot map the next one and the worker
    crashes (a segfault in whatever test compiles then). After a test that leaves the process
    above half the limit, JAX's caches are cleared: the programs are freed, and a later test
    that needs one again loads it from the run's persistent compilation cache."""
    yield
    n = _memory_maps()
    if n is not None and n > MAP_LIMIT // 2:
        jax.clear_caches()
        gc.collect()
