"""Simulated time for the virtual instrument, in two modes.

``instant`` (unit tests, CI)
    Simulated time advances only when the simulation says so: every command line a port
    receives advances it by ``latency`` seconds (the time to transmit and process a line), an
    exposure by its duration, a ``MEAS:POW?`` by its averaging time, a read on the ``sim://``
    transport that has to wait for bytes by the read timeout. With ``jump_on_busy`` (the
    default) a Zaber reply that reports ``BUSY`` moves the clock on to the moment the device's
    motion ends (or the next scheduled motion event, e.g. a stall), so a poll loop ends after
    two polls without any sleeping. Nothing ever sleeps.

``scaled``
    Simulated time is ``scale`` times the wall time since construction (``scale=1``: real
    time, for rehearsals; ``scale=10``: a demo ten times faster). ``advance`` sleeps for
    ``dt / scale`` of wall time.
"""

from __future__ import annotations

import threading
import time

__all__ = ["SimClock"]


class SimClock:
    """Simulated clock.

    Parameters
    ----------
    mode : {"instant", "scaled"}
        See the module docstring.
    scale : float
        Simulated seconds per wall second in ``scaled`` mode. Ignored in ``instant`` mode.
    latency : float
        Simulated seconds each received command line costs in ``instant`` mode, s.
    jump_on_busy : bool
        In ``instant`` mode, whether a ``BUSY`` reply moves the clock to the end of the motion.
    start : float
        Initial simulated time, s.
    """

    def __init__(self, mode: str = "instant", scale: float = 1.0, latency: float = 1e-3,
                 jump_on_busy: bool = True, start: float = 0.0):
        if mode not in ("instant", "scaled"):
            raise ValueError(f"clock mode must be 'instant' or 'scaled', not {mode!r}")
        if not scale > 0:
            raise ValueError("clock scale must be > 0")
        self.mode = mode
        self.scale = float(scale)
        self.latency = float(latency)
        self.jump_on_busy = bool(jump_on_busy)
        self._t = float(start)
        self._wall0 = time.monotonic()
        self._lock = threading.Lock()
        #: how ``advance`` waits in ``scaled`` mode (wall seconds); an instrument puts its own
        #: here, one that lets go of its lock while a device waits (``Instrument.wait``)
        self.sleep = time.sleep

    @property
    def instant(self) -> bool:
        """True in ``instant`` mode."""
        return self.mode == "instant"

    def now(self) -> float:
        """Current simulated time, s."""
        if self.instant:
            return self._t
        return self._t + (time.monotonic() - self._wall0) * self.scale

    def advance(self, dt: float) -> None:
        """Let ``dt`` simulated seconds pass (instant: add; scaled: sleep ``dt/scale``)."""
        if dt <= 0:
            return
        if self.instant:
            with self._lock:
                self._t += float(dt)
        else:
            self.sleep(dt / self.scale)

    def advance_to(self, t: float) -> None:
        """Let simulated time reach ``t`` (no-op if it already has)."""
        self.advance(t - self.now())

    def tick(self) -> None:
        """Cost of one received command line (instant mode only)."""
        if self.instant:
            self.advance(self.latency)

    @classmethod
    def coerce(cls, spec=None, default: str = "instant") -> "SimClock":
        """A clock from a spec: a SimClock, None (``default``), ``"instant"``, ``"real"``,
        ``"scaled"`` (real time), ``"scaled:10"`` or a number (the scale)."""
        if isinstance(spec, SimClock):
            return spec
        if spec is None:
            spec = default
        if isinstance(spec, (int, float)):
            return cls("scaled", scale=float(spec))
        text = str(spec).strip().lower()
        if text == "instant":
            return cls("instant")
        if text in ("real", "realtime", "scaled"):
            return cls("scaled", scale=1.0)
        if text.startswith("scaled:"):
            return cls("scaled", scale=float(text.split(":", 1)[1]))
        raise ValueError(f"unknown clock {spec!r} (instant, real, scaled:FACTOR or a number)")

    def __repr__(self) -> str:
        return (f"SimClock(mode={self.mode!r}, scale={self.scale}, latency={self.latency}, "
                f"jump_on_busy={self.jump_on_busy}, now={self.now():.6f})")
