"""JAX's persistent compilation cache for gyrojax's command line and test suite.

A diagnosis compiles its fits (optimistix loops around diffrax solves) once per process: 2-15 s
on a 2-core machine, most of a CLI run's time. With the cache on, a later process loads the
compiled executables from disk instead (the tracing is still done); the cache's keys hold the
computation, the compile options and the jax version, so a changed model or jax compiles anew.
"""

from __future__ import annotations

import os

import jax

__all__ = ["CACHE_ENV", "default_cache_dir", "enable_compilation_cache"]

CACHE_ENV = "GYROJAX_COMPILATION_CACHE"  # a folder, or "off"


def default_cache_dir() -> str | None:
    """The folder the CLI caches compilations in: ``$GYROJAX_COMPILATION_CACHE`` if set
    (``None`` when it is ``off``), else ``$XDG_CACHE_HOME/gyrojax/jax`` (``~/.cache/...``)."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "no") else env
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "gyrojax", "jax")


def enable_compilation_cache(path: str | os.PathLike | None = None, *,
                             min_compile_s: float = 0.2,
                             max_size_bytes: int = 2 << 30) -> str | None:
    """Turn on JAX's persistent compilation cache (a process-wide JAX setting; gyrojax's CLI
    calls it, a notebook may).

    **Arguments:**
    - `path`: the cache folder (made if missing); default :func:`default_cache_dir`.
    - `min_compile_s`: compilations shorter than this are not stored.
    - `max_size_bytes`: the folder's size, beyond which the least recently used entries go
      (2 GiB; a diagnosis of each rig stores 1-5 MB).

    **Returns:** the folder in use, or ``None`` when ``$GYROJAX_COMPILATION_CACHE`` is ``off``
    (and no `path` is given) or the folder cannot be made (the run goes on uncached).
    """
    folder = os.fspath(path) if path is not None else default_cache_dir()
    if folder is None:
        return None
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", int(max_size_bytes))
    return folder
