"""Simulated Newport/Oriel Cornerstone 130/260 monochromator on RS-232: drive physics and protocol.

The twin answers the bytes of the Cornerstone's RS-232 command set: every received character
is echoed (echo on, the factory default), a query's response follows the echo, responses end
with CR LF, and errors are only reported when asked (``STB?``: ``00`` or ``20``; ``ERROR?``: the
code, then reset). A grating change takes seconds, the filter wheel turns position by
position, ``GOWAVE`` takes time proportional to the move. Faults: a dropped output, a stuck
filter wheel. Served on a pty by ``PtyServer`` (``MonochromatorHost`` standalone, or an
``Instrument`` whose settings hold ``[monochromator]``), like the Zaber and SCPI twins.

References: Newport, Oriel Cornerstone 260 manual (MCS260), appendix I 16.2-16.7: syntax,
echo, ``STB?``/``ERROR?``, ``WAVE?[lf]500[cr][lf]``. Newport, Cornerstone 260B manual (MCS260B)
and 130B manual (MCS130B), 15.1-15.9: 9600 8N1, ``ECHO``, ``HANDSHAKE``, error codes 1-10,
``GOWAVE 500[cr][lf]`` echoed as sent, ``WAVE?[cr][lf]500.01[cr][lf]``.
"""

# Chosen where the manuals are silent (invented; the driver relies on none of it):
# - Statements are carried out one at a time: one received while the drive moves waits in the
#   input buffer (MCS260B 15.8: "about 20 commands") and is carried out, echo included, when the
#   move ends (instant clock: the clock jumps there). A host that asks WAVE? right after GOWAVE
#   therefore reads the final wavelength.
# - Timing: GOWAVE 0.05 s + |move| / (175 nm/s x 1200 / lines per mm); GRAT 6 s (turret) plus the
#   drive's move back to the wavelength (clamped to the new grating's range); FILTER 0.8 s per
#   position the 6-position wheel turns, the shortest way round; SHUTTER and queries no time.
# - Gratings: 1 = 1200 l/mm "350NM" 0-1400 nm, 2 = 600 l/mm "750NM" 0-2800 nm, 3 = 300 l/mm
#   "1600NM" 0-5600 nm (the drive's angle limit scales with 1/lines). GOWAVE beyond the current
#   grating's range or below 0: error 3, no motion. Power on: grating 1, 0 nm (zero order),
#   filter 1, shutter closed, units NM.
# - INFO? answers "CORNERSTONE 260 VER 2.31 TWIN"; GRAT? "number,lines,label"; WAVE? 2 decimals
#   in NM and WN (cm^-1), 5 in UM. A non-ASCII byte is echoed as "?".

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from gonio.sim.devices.port import PortEndpoint
from gonio.sim.physics.clock import SimClock
from gonio.sim.physics.faults import FaultSchedule

__all__ = ["Grating", "DEFAULT_GRATINGS", "ERRORS", "MonochromatorDrive", "CornerstoneTwin",
           "MonochromatorEndpoint", "MonochromatorHost", "PORT"]

#: the port's name (``sim://NAME/monochromator``, ``<link_dir>/monochromator``)
PORT = "monochromator"

#: MCS260B 15.9 (7 from MCS260 16.7): the codes ``ERROR?`` answers
ERRORS = {0: "no error", 1: "command not understood", 2: "bad parameter used in command",
          3: "destination position for wavelength motion not allowed",
          6: "accessory not present (usually filter wheel)", 7: "accessory already in specified position",
          8: "could not home wavelength drive", 9: "label too long", 10: "system error"}
STB_ERROR = 0x20          # MCS260 16.7: bit 5 set (decimal 32) after any error, answered "20"


@dataclass(frozen=True)
class Grating:
    """One grating of the turret: ruling (lines/mm), label and the drive's range (nm)."""

    lines: int
    label: str
    max_nm: float
    min_nm: float = 0.0


DEFAULT_GRATINGS = (Grating(1200, "350NM", 1400.0), Grating(600, "750NM", 2800.0), Grating(300, "1600NM", 5600.0))


class MonochromatorDrive:
    """The monochromator's mechanics in simulated time: grating turret, wavelength drive, filter
    wheel, shutter.

    Parameters
    ----------
    clock : SimClock
    gratings : sequence of Grating
    filters : int
        Positions of the filter wheel (0: no wheel; FILTER then answers error 6).
    slew_nm_per_s : float
        Drive speed on a 1200 l/mm grating, nm/s (scales with 1200 / lines).
    settle_s, grating_s, filter_step_s : float
        Settling after a drive move, turret change, one filter position, s.
    """

    def __init__(self, clock: SimClock, gratings=DEFAULT_GRATINGS, filters: int = 6, slew_nm_per_s: float = 175.0,
                 settle_s: float = 0.05, grating_s: float = 6.0, filter_step_s: float = 0.8):
        if not gratings:
            raise ValueError("a monochromator needs at least one grating")
        self.clock = clock
        self.gratings = tuple(gratings)
        self.filters = int(filters)
        self.slew = float(slew_nm_per_s)
        self.settle_s, self.grating_s, self.filter_step_s = float(settle_s), float(grating_s), float(filter_step_s)
        self.grating = 1
        self.nm = 0.0
        self.filter = 1 if self.filters else 0
        self.shutter_open = False
        self.busy_until = clock.now()
        self.filter_stuck = False         # fault: the wheel does not turn

    def wait_idle(self) -> None:
        """Let the clock reach the end of the current motion (a statement waits for it)."""
        self.clock.advance_to(self.busy_until)

    def _busy(self, seconds: float) -> float:
        self.busy_until = max(self.busy_until, self.clock.now()) + seconds
        return seconds

    def move_time(self, nm: float) -> float:
        """Seconds GOWAVE ``nm`` takes from here on the current grating."""
        speed = self.slew * 1200.0 / self.gratings[self.grating - 1].lines
        return self.settle_s + abs(nm - self.nm) / speed

    def go(self, nm: float) -> bool:
        """Drive to ``nm``; False (no motion) outside the current grating's range."""
        g = self.gratings[self.grating - 1]
        if not (math.isfinite(nm) and g.min_nm <= nm <= g.max_nm):
            return False
        self._busy(self.move_time(nm))
        self.nm = nm
        return True

    def select_grating(self, n: int) -> bool:
        """Turn the turret to grating ``n`` (1-based) and drive back to the wavelength, clamped."""
        if not 1 <= n <= len(self.gratings):
            return False
        if n == self.grating:
            return True
        self._busy(self.grating_s)
        self.grating = n
        g = self.gratings[n - 1]
        target = min(max(self.nm, g.min_nm), g.max_nm)
        self._busy(self.move_time(target))
        self.nm = target
        return True

    def select_filter(self, n: int) -> int:
        """Turn the wheel to position ``n``: 0 done, else the error code (2 bad, 6 no wheel)."""
        if not self.filters:
            return 6
        if not 1 <= n <= self.filters:
            return 2
        steps = abs(n - self.filter)
        steps = min(steps, self.filters - steps)
        self._busy(self.filter_step_s * steps)
        if not self.filter_stuck:
            self.filter = n
        return 0


_UNITS = {"NM": (lambda nm: nm, lambda v: v, "{:.2f}"),
          "UM": (lambda nm: nm / 1000.0, lambda v: v * 1000.0, "{:.5f}"),
          "WN": (lambda nm: 1e7 / nm if nm > 0 else 0.0, lambda v: 1e7 / v if v > 0 else math.nan, "{:.2f}")}


class CornerstoneTwin:
    """The Cornerstone's RS-232 statement server.

    Parameters
    ----------
    owner : object
        Has ``clock`` (an ``Instrument`` or a `MonochromatorHost`).
    echo : bool
        Echo on (the factory default) or off (``ECHO 0``).
    drop_at : iterable of int
        Statements (1-based count on this port) whose output, echo and response, is lost (the
        statement is carried out).
    drop_probability : float
        Chance that any statement's output is lost, drawn from ``rng``.
    rng : numpy.random.Generator or None
        Random draws of ``drop_probability`` (default ``default_rng(0)``).
    stuck_filter : bool
        The filter wheel does not turn (FILTER is accepted and takes its time).
    **drive
        `MonochromatorDrive` options.
    """

    encoding = "ascii"
    MAX_LINE = 128

    def __init__(self, owner, *, echo: bool = True, drop_at=(), drop_probability: float = 0.0, rng=None,
                 stuck_filter: bool = False, **drive):
        self.clock = owner.clock
        self.drive = MonochromatorDrive(self.clock, **drive)
        self.drive.filter_stuck = bool(stuck_filter)
        self.echo = bool(echo)
        self.handshake = False
        self.units = "NM"
        self.error = 0
        self.stb = 0
        self.drop_at = frozenset(int(n) for n in drop_at)
        if not 0.0 <= float(drop_probability) <= 1.0:
            raise ValueError(f"drop_probability {drop_probability!r} is not within 0..1")
        self.drop_probability = float(drop_probability)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.statements = 0
        self.dropped = 0
        self._raw = bytearray()           # bytes received and not echoed yet

    # ------------------------------------------------------------------ bytes
    def received(self, data: bytes) -> None:
        """Raw bytes from the host, kept for the echo: at most ``MAX_LINE`` bytes of a line (the
        rest, up to its LF, is lost, as the endpoint drops it)."""
        raw, start = self._raw, 0
        while start < len(data):
            end = data.find(b"\n", start)
            stop = len(data) if end < 0 else end + 1
            room = self.MAX_LINE - (len(raw) - (raw.rfind(b"\n") + 1))
            raw += data[start:min(stop if end < 0 else end, start + max(0, room))]
            if end >= 0:
                raw += b"\n"
            start = stop

    def leftover(self) -> str:
        """What is left of the complete lines once the endpoint has handled a write: lines of
        white space only (returned to be echoed at once, echo on) or lines it did not hand on
        (dropped); the partial line stays."""
        raw = self._raw
        cut = raw.rfind(b"\n") + 1
        text = bytes(raw[:cut])
        del raw[:cut]
        return text.decode("latin-1") if self.echo and not text.strip() else ""

    def _take_echo(self) -> str:
        """The bytes of the statement just ended, as received (through the LF that ends it)."""
        raw = self._raw
        start = 0
        while True:
            end = raw.find(b"\n", start)
            if end < 0:
                end = len(raw) - 1
                break
            if raw[:end].strip():
                break
            start = end + 1
        out = bytes(raw[:end + 1])
        del raw[:end + 1]
        return out.decode("latin-1")

    # ------------------------------------------------------------------ statements
    def handle(self, text: str) -> list[str]:
        """One statement (already stripped of its terminator): the lines to send, each with its
        own terminator (the echo as received, responses with CR LF)."""
        raw = self._take_echo()
        echo = raw if self.echo else None       # as received, before it acts: ECHO 0 is echoed
        self.statements += 1
        self.drive.wait_idle()
        try:
            answer = self._execute(text.strip())
        except _Error as exc:
            answer = None
            self._fail(exc.code)
        out = [echo] if echo is not None else []
        if answer is not None:
            out.append(answer + "\r\n")
        if self.handshake:
            out.append(self._status() + "\r\n")
        if self.statements in self.drop_at or (self.drop_probability and self.rng.random() < self.drop_probability):
            self.dropped += 1
            return []
        return out

    def overlong(self, text: str) -> list[str]:
        """A statement longer than ``MAX_LINE``: not understood (error 1), echoed as far as kept."""
        echo = self._take_echo()
        self.statements += 1
        self._fail(1)
        return [echo] if self.echo else []

    def again(self, text: str) -> list[str]:
        """The endpoint's ``again`` fault does not apply to this protocol: carry it out."""
        return self.handle(text)

    def _fail(self, code: int) -> None:
        self.error = code
        self.stb = STB_ERROR

    def _status(self) -> str:
        stb, self.stb = self.stb, 0
        return f"{stb:02X}"

    def _execute(self, text: str) -> str | None:
        head, _, rest = text.partition(" ")
        head = head.upper()
        args = [a.strip() for a in rest.split(",")] if rest.strip() else []
        d = self.drive
        if head.endswith("?"):
            if args:
                raise _Error(2)
            return self._query(head)
        if head == "GOWAVE":
            value = _number(args)
            to_nm = _UNITS[self.units][1]
            if not d.go(to_nm(value)):
                raise _Error(3)
        elif head == "GRAT":
            if not d.select_grating(_integer(args)):
                raise _Error(2)
        elif head == "FILTER":
            code = d.select_filter(_integer(args))
            if code:
                raise _Error(code)
        elif head == "SHUTTER":
            word = _word(args)
            if word not in ("O", "C"):
                raise _Error(2)
            d.shutter_open = word == "O"
        elif head == "UNITS":
            word = _word(args)
            if word not in _UNITS:
                raise _Error(2)
            self.units = word
        elif head in ("ECHO", "HANDSHAKE"):
            flag = _integer(args)
            if flag not in (0, 1):
                raise _Error(2)
            setattr(self, head.lower(), bool(flag))
        else:
            raise _Error(1)
        return None

    def _query(self, head: str) -> str:
        d = self.drive
        if head == "WAVE?":
            from_nm, _, fmt = _UNITS[self.units]
            return fmt.format(from_nm(d.nm))
        if head == "GRAT?":
            g = d.gratings[d.grating - 1]
            return f"{d.grating},{g.lines},{g.label}"
        if head == "FILTER?":
            if not d.filters:
                raise _Error(6)
            return str(d.filter)
        if head == "SHUTTER?":
            return "O" if d.shutter_open else "C"
        if head == "UNITS?":
            return self.units
        if head == "ERROR?":
            code, self.error = self.error, 0
            return str(code)
        if head == "STB?":
            return self._status()
        if head == "INFO?":
            return "CORNERSTONE 260 VER 2.31 TWIN"
        if head in ("ECHO?", "HANDSHAKE?"):
            return str(int(getattr(self, head[:-1].lower())))
        raise _Error(1)


class _Error(Exception):
    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def _number(args: list[str]) -> float:
    if len(args) != 1:
        raise _Error(2)
    try:
        value = float(args[0])
    except ValueError:
        raise _Error(2) from None
    if not math.isfinite(value):
        raise _Error(2)
    return value


def _integer(args: list[str]) -> int:
    value = _number(args)
    if value != int(value):
        raise _Error(2)
    return int(value)


def _word(args: list[str]) -> str:
    if len(args) != 1:
        raise _Error(2)
    return args[0].upper()


class MonochromatorEndpoint(PortEndpoint):
    """The monochromator's port: lines end at LF (MCS260 16.3: a statement acts only once its
    LF arrives; a CR before it is part of the terminator), every received byte goes to the twin
    for its echo, and the twin terminates its own lines."""

    def __init__(self, owner, server: CornerstoneTwin, name: str = PORT):
        super().__init__(owner, name, server, b"", split_cr=False)

    def feed(self, data: bytes) -> None:
        with self.lock:
            self.server.received(bytes(data))
            super().feed(data)
            blank = self.server.leftover()
            if blank and self.present():
                self._queue(blank.encode("ascii", "replace"))


class MonochromatorHost:
    """One simulated monochromator on its own: what ``PtyServer`` and the port endpoint need of
    an instrument (a clock, a lock, an empty fault schedule, the ports).

    Parameters
    ----------
    clock : SimClock, str, float or None
        ``SimClock.coerce`` spec (default instant).
    **twin
        `CornerstoneTwin` options.
    """

    def __init__(self, clock=None, **twin):
        self.clock = SimClock.coerce(clock)
        self.lock = threading.RLock()
        self.faults = FaultSchedule()
        self.fault_seed = 0
        self.monochromator = CornerstoneTwin(self, **twin)
        self.ports = {PORT: MonochromatorEndpoint(self, self.monochromator)}
