"""Monochromator driver: a Newport/Oriel Cornerstone 130/260 on RS-232 (9600 8N1).

`Monochromator.go_to` picks the grating and the order-sorting filter for a wavelength from
``[monochromator]`` ``gratings`` and ``filters`` (each ``[[n, from_nm, to_nm], ...]``), sets
them, drives there and reads ``WAVE?`` back. Statements end with CR LF; the instrument echoes
what it receives (unless ``ECHO 0``) and reports errors only when asked (``STB?`` then
``ERROR?``), so every command is followed by ``STB?`` and a code raises a one-line
`DeviceError` with the manual's meaning. A missing or garbled reply is retried, then the port
is reopened once, then `CommunicationError`.

References: Newport, Oriel Cornerstone 260 manual (MCS260), appendix I 16.2-16.7 (syntax, echo,
``STB?`` ``00``/``20``, error codes); Cornerstone 260B/130B manuals (MCS260B, MCS130B)
15.1-15.9 (9600 8N1, ``ECHO``, ``GOWAVE 500[cr][lf]`` echoed as sent, ``WAVE?`` answered
``500.01``, error codes 1-10).
"""

# Why the driver does what it does:
# - The echo is recognised, not assumed: at open, INFO? is sent and the first line compared with
#   it (echo on: the factory default on RS-232; off after ECHO 0, and never on USB). With the echo
#   on, a first line that is not this statement's echo is a stray or late line: the exchange is
#   retried, so a late answer is never taken for the next one.
# - The grating, the filter and the wavelength are read back after every change, not remembered:
#   the manual warns that the RS-232, USB and hand-controller ports are all live at once.
# - A query that is echoed but not answered was refused (errors live only in the status byte):
#   STB? and ERROR? are read at once and the code raised, rather than the query retried.
# - Every command here sets an absolute state (GOWAVE, GRAT, FILTER, SHUTTER, UNITS), so a command
#   whose echo was lost is simply sent again.
# - A statement's echo and answer may come only when the drive has finished a move (the
#   instrument buffers statements while it moves), so reads after a motion command wait up to
#   ``move_timeout_s`` on top of the port's timeout.

from __future__ import annotations

import math
import re
import time
from typing import Mapping

import serial

from gonio.bench.drivers.serialport import SerialDevice
from gonio.core.errors import CommunicationError, DeviceError, GonioError

__all__ = ["Monochromator", "ERRORS", "DEFAULTS", "choose", "ranges"]

#: MCS260B 15.9 (code 7 from MCS260 16.7): what ``ERROR?`` answers
ERRORS = {1: "command not understood", 2: "bad parameter used in command",
          3: "destination position for wavelength motion not allowed",
          6: "accessory not present (usually filter wheel)", 7: "accessory already in specified position",
          8: "could not home wavelength drive", 9: "label too long", 10: "system error"}

#: ``[monochromator]`` defaults. Order sorting: a grating passes lambda/2 in second order too, so
#: above twice the shortest wavelength of the source a long-pass filter must block it: position 1
#: open up to 400 nm, 2 (a 385 nm long-pass) 400-750 nm, 3 (a 715 nm long-pass) 750-1400 nm.
DEFAULTS = {"gratings": [[1, 200.0, 650.0], [2, 650.0, 1400.0]],
            "filters": [[1, 200.0, 400.0], [2, 400.0, 750.0], [3, 750.0, 1400.0]],
            "move_timeout_s": 30.0, "tolerance_nm": 0.5, "baudrate": 9600}

_PRINTABLE = re.compile(r"[ -~]{1,80}")


def _ranges(value, key: str, empty: bool = False) -> list[tuple[int, float, float]]:
    """``[[n, from_nm, to_nm], ...]`` checked: n >= 1, finite, from < to (and not empty unless
    ``empty``); else one line."""
    fix = (f"[monochromator] {key} = {str(value)[:60]}: give [[n, from_nm, to_nm], ...] with n >= 1 and "
           "from_nm < to_nm, e.g. [[1, 200, 650], [2, 650, 1400]]" + (", or [] for none" if empty else ""))
    if not isinstance(value, (list, tuple)) or not (value or empty):
        raise GonioError(fix)
    out = []
    for row in value:
        if not isinstance(row, (list, tuple)) or len(row) != 3 or any(isinstance(x, bool) for x in row):
            raise GonioError(fix)
        try:
            n, lo, hi = int(row[0]), float(row[1]), float(row[2])
        except (TypeError, ValueError):
            raise GonioError(fix) from None
        if n != row[0] or n < 1 or not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
            raise GonioError(fix)
        out.append((n, lo, hi))
    return out


#: ``[monochromator]`` ``gratings`` or ``filters`` checked (plans read them before any port opens)
ranges = _ranges


def choose(ranges, nm: float) -> int | None:
    """The first ``n`` of ``ranges`` whose [from, to] holds ``nm`` (None if none does)."""
    for n, lo, hi in ranges:
        if lo <= nm <= hi:
            return n
    return None


def _positive(m: Mapping, key: str) -> float:
    value = m.get(key, DEFAULTS[key])
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    if not ok:
        raise GonioError(f"[monochromator] {key} = {value!r:.40}: give a positive number")
    return float(value)


class Monochromator(SerialDevice):
    """A Cornerstone 130/260 monochromator on a serial port.

    Parameters
    ----------
    port_url : str
        ``/dev/ttyUSB2``, a pty path, or any pyserial URL.
    settings : mapping or None
        Instrument settings; its ``[monochromator]`` table (keys in `DEFAULTS`) overrides the defaults.
    timeout : float
        Seconds to wait for a line when nothing moves.
    retries : int
        Re-sends of a statement that got no, or a garbled, answer before the port is reopened
        for one more round.
    """

    what, flag = "monochromator", "monochromator port"

    def __init__(self, port_url: str, settings: Mapping | None = None, *, timeout: float = 1.0, retries: int = 2):
        m = dict((settings or {}).get("monochromator") or {})
        unknown = sorted(set(m) - set(DEFAULTS))
        if unknown:
            raise GonioError(f"[monochromator] has no key {unknown[0]!r}; known keys: {', '.join(DEFAULTS)}")
        self.gratings = _ranges(m.get("gratings", DEFAULTS["gratings"]), "gratings")
        self.filters = _ranges(m.get("filters", DEFAULTS["filters"]), "filters", empty=True)   # []: no wheel
        self.move_timeout_s = _positive(m, "move_timeout_s")
        self.tolerance_nm = _positive(m, "tolerance_nm")
        baud = m.get("baudrate", DEFAULTS["baudrate"])
        if baud not in serial.Serial.BAUDRATES or isinstance(baud, bool):
            raise GonioError(f"[monochromator] baudrate = {baud!r:.40}: give a standard rate such as 9600")
        if not (math.isfinite(timeout) and timeout > 0):
            raise GonioError(f"monochromator timeout {timeout!r} s is invalid; give a positive number of seconds")
        super().__init__(port_url, int(baud), float(timeout))
        self.retries = int(retries)
        self.retries_used = 0
        self.echo: bool | None = None          # found by identify()
        self.info = ""
        self.open()
        try:
            self.identify()
            self.command("HANDSHAKE 0")         # standard mode: no status line after each statement
            self.command("UNITS NM")
        except BaseException:
            self.close()
            raise

    @property
    def range_nm(self) -> tuple[float, float]:
        """The lowest and highest wavelength the ``gratings`` (and ``filters``) ranges cover, nm."""
        rows = [self.gratings] + ([self.filters] if self.filters else [])
        return max(min(r[1] for r in t) for t in rows), min(max(r[2] for r in t) for t in rows)

    # ------------------------------------------------------------------ lines
    def _readline(self, wait: float) -> str | None:
        """One line within ``wait`` seconds, without its terminator; None if none came whole;
        a garbled one is neither the echo nor a number."""
        return self.read_line(wait, garbled="\ufffd")

    def _lines(self, wait: float):
        """Non-empty lines within one deadline of ``wait`` seconds (None once it passes)."""
        deadline = time.monotonic() + wait
        while True:
            left = deadline - time.monotonic()
            line = self._readline(max(left, 1e-3)) if left > 0 else None
            if line != "":
                yield line
                if line is None:
                    return

    def _exchange(self, statement: str, answer: bool, wait: float) -> str | None:
        """Send ``statement``; read its echo (echo on) and its answer (a query). Returns the answer
        ("" for a command), or None when a line is missing or the echo is not this statement's."""
        try:
            if self._port.in_waiting:
                self._port.reset_input_buffer()            # a late line of an earlier exchange
            self._port.write((statement + "\r\n").encode("ascii"))
        except (serial.SerialException, OSError, AttributeError):
            return None
        lines = self._lines(wait)
        if self.echo:
            got = next(lines)
            if got is None or got.upper() != statement.upper():
                return None
        if not answer:
            return ""
        got = next(lines)
        return _UNANSWERED if got is None and self.echo else got

    def _send(self, statement: str, answer: bool, parse=str, wait: float | None = None):
        """An exchange with retries and one reopen of the port; ``parse`` raises ValueError for a
        garbled answer (retried). `CommunicationError` once every try failed."""
        if not _PRINTABLE.fullmatch(str(statement)) or statement != statement.strip():
            raise GonioError(f"monochromator statement {str(statement)[:40]!r} is not one line of at most 80 "
                             "printable ASCII characters; send one statement")
        wait = self.timeout if wait is None else float(wait)
        last = "no answer"
        for round_ in range(2):
            if round_ or self._port is None:
                try:
                    self.reconnect()
                except CommunicationError:
                    if round_:
                        raise
                    continue
            for _ in range(self.retries + 1):
                got = self._exchange(statement, answer, wait)
                if got is _UNANSWERED:          # it arrived (echoed) but got no answer: refused?
                    if statement not in ("STB?", "ERROR?"):
                        self._check(statement)
                    got = None
                if got is None:
                    last = "no answer" if answer or not self.echo else "no echo"
                else:
                    try:
                        return parse(got)
                    except ValueError:
                        last = f"a garbled answer {got[:40]!r}"
                self.retries_used += 1
        raise CommunicationError(f"monochromator on {self.port_url} gave {last} to {statement!r} after retries "
                                 "and a reconnect; check that it is on, the cable and the baud rate "
                                 f"({self.baudrate}), then try again")

    # ------------------------------------------------------------------ statements
    def query(self, text: str, parse=str, wait: float | None = None):
        """A query's parsed answer (retried where missing or garbled)."""
        return self._send(text, True, parse, wait)

    def command(self, text: str, wait: float | None = None) -> None:
        """Send a command, then read the status byte, waiting up to ``wait`` s (default: the port's
        timeout plus ``move_timeout_s``; the instrument answers once a move ends); an error raises
        `DeviceError` with the manual's meaning."""
        self._send(text, False)
        self._check(text, self._move_wait() if wait is None else wait)

    def _check(self, text: str, wait: float | None = None) -> None:
        """``STB?`` (within ``wait`` s), and where it says error ``ERROR?``: `DeviceError` naming
        ``text``, the code and its meaning."""
        stb = self.query("STB?", _status, wait=wait)
        if stb:
            code = self.query("ERROR?", _code)
            why = ERRORS.get(code, f"unknown error code {code}")
            raise DeviceError(f"monochromator on {self.port_url} refused {text!r}: error {code}, {why}; "
                              + _ADVICE.get(code, "check the statement and the [monochromator] settings"))

    def identify(self) -> str:
        """``INFO?``: the model and firmware line (first found: whether the instrument echoes)."""
        if self.echo is None:
            self.echo = self._detect_echo()
        self.info = self.query("INFO?", _text)
        return self.info

    def _detect_echo(self) -> bool:
        """Send ``INFO?`` and look at the first line back: the statement itself (echo on) or its
        answer (echo off)."""
        for _ in range(self.retries + 1):
            try:
                if self._port.in_waiting:
                    self._port.reset_input_buffer()
                self._port.write(b"INFO?\r\n")
            except (serial.SerialException, OSError, AttributeError):
                self.retries_used += 1
                continue
            lines = self._lines(self.timeout)
            first = next(lines)
            if first is None:
                self.retries_used += 1
                continue
            if first.upper() == "INFO?":
                next(lines)                     # its answer
                return True
            return False
        raise CommunicationError(f"monochromator on {self.port_url} does not answer INFO?; check that it is on, "
                                 f"the cable and the baud rate ({self.baudrate}; the Cornerstone's is 9600)")

    def _move_wait(self) -> float:
        return self.timeout + self.move_timeout_s

    def grating(self) -> int:
        """``GRAT?``: the grating in use (its number)."""
        return self.query("GRAT?", _grating)

    def filter(self) -> int:
        """``FILTER?``: the filter wheel's position."""
        return self.query("FILTER?", _integer)

    def wavelength(self) -> float:
        """``WAVE?``: the wavelength, nm (once a move under way has ended)."""
        return self.query("WAVE?", _wavelength, self._move_wait())

    def shutter(self, open_: bool) -> None:
        """Open (True) or close the shutter, and check that it did."""
        want = "O" if open_ else "C"
        self.command(f"SHUTTER {want}")
        got = self.query("SHUTTER?", _word)
        if got != want:
            raise DeviceError(f"monochromator shutter reads {got!r} after SHUTTER {want}; check the shutter")

    def go_to(self, nm: float) -> float:
        """Set the grating and the order-sorting filter for ``nm`` (settings' ranges), drive
        there and return the wavelength the instrument reads back, nm."""
        try:
            nm = float(nm)
        except (TypeError, ValueError):
            raise GonioError(f"wavelength {str(nm)[:40]!r} is not a number; give nm, e.g. 550") from None
        lo, hi = self.range_nm
        g, f = choose(self.gratings, nm), choose(self.filters, nm)
        if not math.isfinite(nm) or g is None or (f is None and self.filters):
            raise GonioError(f"wavelength {nm:g} nm is outside the monochromator's ranges ({lo:g}-{hi:g} nm "
                             "for gratings and filters); choose one inside, or widen [monochromator] gratings "
                             "and filters")
        if self.grating() != g:
            self.command(f"GRAT {g}")
            now = self.grating()
            if now != g:
                raise DeviceError(f"monochromator grating reads {now} after GRAT {g}; check the turret, then retry")
        if f is not None and self.filter() != f:
            self.command(f"FILTER {f}")
            now = self.filter()
            if now != f:
                raise DeviceError(f"monochromator filter wheel stayed at {now} after FILTER {f}: the wheel may be "
                                  "stuck; check it, then retry")
        self.command(f"GOWAVE {_number(nm)}")
        got = self.wavelength()
        if abs(got - nm) > self.tolerance_nm:
            raise DeviceError(f"monochromator reads {got:g} nm after GOWAVE {_number(nm)}, more than "
                              f"{self.tolerance_nm:g} nm off; check its calibration or [monochromator] tolerance_nm")
        return got


_UNANSWERED = object()        # a query was echoed but not answered

_ADVICE = {3: "the wavelength is outside this grating's range: check [monochromator] gratings",
           6: "no filter wheel answers: check it is fitted and cabled, or set [monochromator] filters = []",
           2: "check the value sent and the [monochromator] settings"}


def _number(nm: float) -> str:
    """``500`` for 500.0, ``587.1`` for 587.1 (as the manual writes GOWAVE), to 0.001 nm."""
    return f"{nm:.3f}".rstrip("0").rstrip(".")


def _status(line: str) -> int:
    """``STB?``: two hex digits (MCS260 16.7: ``00`` no error, ``20`` error)."""
    if not re.fullmatch(r"[0-9A-Fa-f]{1,2}", line):
        raise ValueError(line)
    return int(line, 16)


def _integer(line: str) -> int:
    if not re.fullmatch(r"\d{1,3}", line):
        raise ValueError(line)
    return int(line)


_code = _integer


def _grating(line: str) -> int:
    """``GRAT?``: ``number,lines,label``; the number."""
    return _integer(line.split(",", 1)[0])


def _text(line: str) -> str:
    """A printable line of at most 80 characters."""
    if not _PRINTABLE.fullmatch(line):
        raise ValueError(line)
    return line


def _word(line: str) -> str:
    return _text(line).upper()


def _wavelength(line: str) -> float:
    value = float(line) if re.fullmatch(r"-?\d{1,6}(\.\d{0,6})?", line) else math.nan
    if not math.isfinite(value):
        raise ValueError(line)
    return value
