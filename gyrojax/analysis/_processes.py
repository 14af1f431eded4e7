"""Worker processes for ``monte_carlo(..., processes=k)``: one CPU process per core.

One Python process drives JAX's CPU device on one core for the graphs gyrojax's Monte Carlo runs
(a vmapped ODE solve, then small batched LAPACK least-squares problems): XLA does not split them
over threads, and sharding over several host devices in one process deadlocks jaxlib 0.10.2's
batched LAPACK (docs/decisions/0007-monte-carlo-worker-processes.md). So the CPU's other cores
are used by worker processes, each pinned to one core and running the chunks it is handed on its one device.

The pool is started on first use and kept. Each worker is a fresh interpreter (``python -m
gyrojax.analysis._processes``): no forked JAX state, and unlike ``multiprocessing``'s spawn the
caller's script is not imported again, so it needs no ``if __name__ == "__main__"`` guard. A
second call with the same trial function reuses each worker's compiled batch function;
:func:`shutdown` stops the workers (also at exit). The trial function goes to the workers once,
by value, through ``cloudpickle`` (closures, lambdas, notebook functions).
Chunks are handed out as workers become free, so a slow core does not hold the others back.
"""

from __future__ import annotations

import atexit
import os
import socket
import subprocess
import sys
import traceback
from collections import OrderedDict
from collections.abc import Callable
from multiprocessing.connection import Connection, wait

__all__ = ["available_cores", "run_chunks", "shutdown"]

_MAX_FNS = 8  # trial functions each worker keeps (with their compilations)


def available_cores() -> list[int]:
    """The CPU cores this process may run on (its affinity set), sorted."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:  # no affinity API (macOS): all cores, unpinned
        return list(range(os.cpu_count() or 1))


def _pin(core, pid=0):
    if core is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(pid, {core})


class _LoadError:
    def __init__(self, text):
        self.text = text


def _worker(conn, core):
    """A worker's loop: messages ("fn", token, bytes), ("drop", token),
    ("run", token, index, draws, kwargs) -> ("ok", index, outputs) | ("err", index, text),
    ("stop",)."""
    _pin(core)  # before JAX starts its CPU client and thread pool
    import cloudpickle
    import jax

    jax.config.update("jax_platforms", "cpu")
    from .montecarlo import monte_carlo

    fns = {}
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        kind = msg[0]
        if kind == "stop":
            return
        if kind == "fn":
            try:
                fns[msg[1]] = cloudpickle.loads(msg[2])
            except BaseException:  # noqa: BLE001 - e.g. a module the worker cannot import
                fns[msg[1]] = _LoadError(traceback.format_exc())
        elif kind == "drop":
            fns.pop(msg[1], None)
        elif kind == "run":
            _, token, index, draws, kwargs = msg
            try:
                fn = fns[token]
                if isinstance(fn, _LoadError):
                    raise RuntimeError("the trial function could not be unpickled in the "
                                       f"worker process:\n{fn.text}")
                out = monte_carlo(fn, draws, devices=jax.devices()[:1], **kwargs)
                conn.send(("ok", index, out))
            except BaseException:  # noqa: BLE001 - the parent re-raises it with the traceback
                conn.send(("err", index, traceback.format_exc()))


class _Pool:
    def __init__(self, n: int):
        cores = available_cores()
        # pin one worker per core while there are enough cores; more workers than cores float
        self.cores = [cores[i] if n <= len(cores) else None for i in range(n)]
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
        self.conns, self.procs = [], []
        for core in self.cores:
            mine, theirs = socket.socketpair()
            fd = theirs.fileno()
            p = subprocess.Popen(
                [sys.executable, "-m", "gyrojax.analysis._processes", str(fd),
                 "-1" if core is None else str(core)], pass_fds=(fd,), env=env,
                stdin=subprocess.DEVNULL)
            _pin(core, p.pid)  # also from here, before the child reaches JAX
            theirs.close()
            self.conns.append(Connection(mine.detach()))
            self.procs.append(p)
        self.fns: OrderedDict[int, tuple[Callable, int]] = OrderedDict()  # id(fn) -> (fn, token)
        self.next_token = 0

    @property
    def size(self) -> int:
        return len(self.procs)

    def token(self, fn) -> int:
        """The workers' token for ``fn``, sending it to them on first use. The pool holds
        ``fn`` while its token lives, so ``id(fn)`` cannot be reused by another object."""
        hit = self.fns.get(id(fn))
        if hit is not None and hit[0] is fn:
            self.fns.move_to_end(id(fn))
            return hit[1]
        import cloudpickle

        try:
            payload = cloudpickle.dumps(fn)
        except Exception as e:
            raise TypeError(f"monte_carlo(processes=...): the trial function {fn!r} cannot be "
                            f"pickled for the worker processes ({e}); close over arrays and "
                            "picklable objects only, or run with processes=None") from e
        token, self.next_token = self.next_token, self.next_token + 1
        for c in self.conns:
            c.send(("fn", token, payload))
        self.fns[id(fn)] = (fn, token)
        while len(self.fns) > _MAX_FNS:
            _, (_, old) = self.fns.popitem(last=False)
            for c in self.conns:
                c.send(("drop", old))
        return token

    def alive(self) -> bool:
        return all(p.poll() is None for p in self.procs)

    def close(self, graceful: bool = True):
        for c, p in zip(self.conns, self.procs, strict=True):
            if graceful and p.poll() is None:
                try:
                    c.send(("stop",))
                except OSError:
                    pass
        for p in self.procs:
            try:
                p.wait(timeout=5 if graceful else 0.01)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=5)
        for c in self.conns:
            c.close()


_pool: _Pool | None = None


def shutdown():
    """Stop the Monte Carlo worker processes (they restart on the next ``processes=`` call)."""
    global _pool
    if _pool is not None:
        pool, _pool = _pool, None
        pool.close()


atexit.register(shutdown)


def _get_pool(n: int) -> _Pool:
    global _pool
    if _pool is not None and (_pool.size != n or not _pool.alive()):
        shutdown()
    if _pool is None:
        _pool = _Pool(n)
    return _pool


def run_chunks(fn, chunks: list, processes: int, kwargs: dict, on_done: Callable[[int], None]):
    """``monte_carlo(fn, chunk, devices=<its one CPU device>, **kwargs)`` for every chunk (a
    pytree of numpy arrays) on ``processes`` pinned worker processes; the outputs in chunk
    order. ``on_done(i)`` is called as chunk ``i`` finishes. A worker's exception is raised
    here with its traceback, and the pool is restarted on the next call."""
    global _pool
    pool = _get_pool(processes)
    token = pool.token(fn)  # raises before anything is sent if fn cannot be pickled
    ok = False
    try:
        outs = [None] * len(chunks)
        todo = list(range(len(chunks)))[::-1]
        busy = {}  # conn -> chunk index
        for c in pool.conns:
            if todo:
                i = todo.pop()
                c.send(("run", token, i, chunks[i], kwargs))
                busy[c] = i
        while busy:
            for c in wait(list(busy)):
                i = busy.pop(c)
                w = pool.conns.index(c)
                try:
                    kind, index, out = c.recv()
                except (EOFError, OSError):
                    code = pool.procs[w].poll()
                    raise RuntimeError(
                        f"monte_carlo: worker process {w} (core {pool.cores[w]}) exited with "
                        f"code {code} while running chunk {i}; if it ran out of memory, give a "
                        "smaller chunk_size or fewer processes") from None
                if kind == "err":
                    raise RuntimeError(f"monte_carlo: worker process {w} (core "
                                       f"{pool.cores[w]}) failed on chunk {index}:\n{out}")
                outs[index] = out
                on_done(index)
                if todo:
                    j = todo.pop()
                    c.send(("run", token, j, chunks[j], kwargs))
                    busy[c] = j
        ok = True
        return outs
    finally:
        if not ok:  # a failed or interrupted run leaves work in flight: restart the pool
            if _pool is pool:
                _pool = None
            pool.close(graceful=False)


def _main():
    """Entry point of a worker process: ``python -m gyrojax.analysis._processes FD CORE``."""
    fd, core = int(sys.argv[1]), int(sys.argv[2])
    _worker(Connection(fd), None if core < 0 else core)


if __name__ == "__main__":
    _main()
