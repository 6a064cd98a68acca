"""Work run in a child process with a deadline: a call that may not return (a render of a user's
scene, a C++ loop no Python signal reaches) is killed when its time is up.

:func:`call_with_deadline` runs ``fn(*args, **kwargs)`` in a fresh ``spawn`` process (no copy of
the caller's threads or JIT state), sends the result or the exception back through a pipe, and
kills the child (SIGKILL) at the deadline; the caller then gets a :class:`GonioError` of one line.
``fn``, its arguments and its result must pickle; ``fn`` must be importable by name.
"""

from __future__ import annotations

import multiprocessing
import time

from gonio.core.errors import GonioError

__all__ = ["call_with_deadline"]


def _child(conn, fn, args, kwargs):
    try:
        result = ("ok", fn(*args, **kwargs))
    except BaseException as exc:                 # the caller re-raises it as it is
        result = ("error", exc)
    try:
        conn.send(result)
    except Exception as exc:                     # an unpicklable result or exception
        conn.send(("error", RuntimeError(f"{type(exc).__name__}: {exc}")))
    conn.close()


def call_with_deadline(fn, args=(), kwargs=None, *, seconds: float, what: str, hint: str = ""):
    """``fn(*args, **kwargs)`` in a child process; its result, or its exception re-raised here;
    GonioError (one line naming ``what``) when it runs past ``seconds`` or dies without answering."""
    ctx = multiprocessing.get_context("spawn")
    here, there = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(there, fn, tuple(args), dict(kwargs or {})), daemon=True)
    proc.start()
    there.close()
    end = time.monotonic() + float(seconds)
    try:
        if not here.poll(max(0.0, end - time.monotonic())):
            raise GonioError(f"{what} did not finish within its {seconds:g} s{'; ' + hint if hint else ''}")
        try:
            status, value = here.recv()
        except EOFError:
            proc.join(5)
            raise GonioError(f"{what} ended without an answer (exit status {proc.exitcode}); "
                             "it may have run out of memory") from None
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join()
        here.close()
    if status == "error":
        raise value
    return value
