"""Ctrl-C, SIGTERM and SIGHUP during a capture, and SIGTERM or SIGHUP while gonio starts.

Ctrl-C once asks the run to stop at the next point boundary; Ctrl-C twice, or one SIGTERM (a
service manager stopping the bench) or SIGHUP (the terminal closing), stops it at the next safe
point (`StopNow`), and the capture stops the stages, switches the LED off, journals the stop
and exits resumably (status 3).
"""

from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["StopNow", "Interrupts", "SignalStop", "startup_signals"]


class StopNow(KeyboardInterrupt):
    """A second Ctrl-C, or SIGTERM / SIGHUP: stop the stages now (raised at a safe point)."""

    def __init__(self, why: str):
        super().__init__(why)
        self.why = why


class Interrupts:
    """The signal handlers of a capture run.

    The handlers only set flags; `check` raises `StopNow` at the run's safe points (each poll
    of a moving stage, each settle or pause, before and after each exposure, between
    calibration frames, between points), so a signal never lands inside a driver's exchange or
    the simulator's renderer. First SIGINT: stop at the next point boundary (``requested``).
    Second SIGINT, or one SIGTERM or SIGHUP: stop now. A third SIGINT raises `StopNow` at
    once, wherever the run is (the last resort for a run stuck outside the safe points). Once
    the stop is under way, or during the clean-up (``deferred``), signals only set flags, so
    stopping the stages, switching the LED off and journalling are never cut short.
    """

    SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))

    def __init__(self):
        self.requested = False          # stop at the next point boundary
        self.stop: str | None = None    # stop now: why
        self.stopping = False           # StopNow was raised
        self.deferred = False           # cleaning up
        self._old: dict = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._old[sig] = signal.signal(sig, self._handler)
        return self

    def _handler(self, signum, frame):
        name = "Ctrl-C twice" if signum == signal.SIGINT else signal.Signals(signum).name
        if self.stopping or self.deferred:
            self.requested = True
            return
        if signum == signal.SIGINT and not self.requested:
            self.requested = True
            return
        self.requested = True
        if self.stop is not None and signum == signal.SIGINT:
            self.stopping = True
            raise StopNow("Ctrl-C three times")
        if self.stop is None:
            self.stop = name

    def check(self) -> None:
        """Raise `StopNow` if a stop was asked for (called at the run's safe points)."""
        if self.stop is not None and not self.stopping and not self.deferred:
            self.stopping = True
            raise StopNow(self.stop)

    def __exit__(self, *exc):
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old = {}


class SignalStop(KeyboardInterrupt):
    """SIGTERM or SIGHUP before a command put in its own handlers (`startup_signals`): the
    clean-up that a Ctrl-C gets runs (``except KeyboardInterrupt``, ``finally``), then gonio says
    which signal stopped it and exits with 128 + its number."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        self.name = signal.Signals(signum).name
        super().__init__(f"stopped by {self.name}")


@contextlib.contextmanager
def startup_signals():
    """While gonio's main runs (put in first thing): SIGTERM and SIGHUP raise `SignalStop`.
    Without this a signal during the start-up (seconds of imports, opening ports) ended the
    process silently (issue 40). A command's own handlers (`Interrupts`, ``sim serve``) replace
    these while it runs and put them back after; a signal in between raises at once, and what is
    being written is written whole or not at all (every writer renames a finished temporary
    file). The previous handlers are restored on exit (main() called in-process)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise SignalStop(signum)

    old = {}
    try:
        for name in ("SIGTERM", "SIGHUP"):
            if hasattr(signal, name):
                old[name] = signal.signal(getattr(signal, name), stop)
        yield
    finally:
        for name, handler in old.items():
            signal.signal(getattr(signal, name), handler)
