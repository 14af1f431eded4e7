"""The persistent compilation cache the CLI keeps (gyrojax._cache)."""

import os
import subprocess
import sys

from gyrojax._cache import CACHE_ENV, default_cache_dir, enable_compilation_cache

PROBE = """
import sys, jax, jax.numpy as jnp
events = []
jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
import gyrojax
print(gyrojax.enable_compilation_cache(min_compile_s=0.0))
jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T + 2.0)(jnp.ones((3, 3))).block_until_ready()
print(sum(e == "/jax/compilation_cache/cache_hits" for e in events))
"""


def test_the_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(CACHE_ENV, "off")
    assert default_cache_dir() is None
    assert enable_compilation_cache() is None  # off: JAX's setting left as it was
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "c"))
    assert default_cache_dir() == str(tmp_path / "c")
    monkeypatch.delenv(CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == os.path.join(str(tmp_path), "gyrojax", "jax")


def test_a_second_process_loads_what_the_first_compiled(tmp_path):
    """The first process stores its compiled programs; a second one with the same folder hits
    the cache."""
    def run(value):
        env = dict(os.environ, **{CACHE_ENV: value})
        out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True,
                             text=True, check=True).stdout.split()
        return out[0], int(out[1])

    folder = str(tmp_path / "cache")
    assert run(folder) == (folder, 0)
    stored = os.listdir(folder)
    assert any(n.endswith("-cache") for n in stored)
    assert run(folder)[1] >= 1

