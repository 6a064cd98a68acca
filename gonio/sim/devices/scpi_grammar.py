"""SCPI server of the simulated power meter: IEEE 488.2 common commands and a PM100 subset.

Sources: IEEE 488.2 (common commands, status byte and standard event register, ``;``
between message units, responses of one line joined by ``;``), SCPI-1999 (long/short
header forms, optional nodes in brackets, MIN/MAX/DEF numeric arguments, unit suffixes,
error codes and texts), the Thorlabs PM100D/PM100USB command set as PyMeasure 0.16's
``ThorlabsPM100USB`` uses it.

Headers (case-insensitive, long or short, optional leading colon, optional nodes
``[SENSe:]``, ``[:SCALar]``, ``[:IMMediate]``, ``[:NEXT]``):
``*IDN? *RST *CLS *OPC *OPC? *WAI *STB? *ESR? *ESE[?] *SRE[?] *TST?``,
``SYST:ERR[:NEXT]?``, ``SYST:VERS?``, ``SYST:SENS:IDN?``, ``SENS:CORR:WAV[?] [MIN|MAX|DEF]``,
``SENS:AVER:COUN[?] [MIN|MAX|DEF]``, ``MEAS[:SCAL][:POW]?``, ``READ?``, ``CONF[:SCAL]:POW``,
``CONF?``, ``INIT[:IMM]``, ``FETC?``. Behaviour chosen where the documents are silent: below.
"""

# PyMeasure 0.16's ThorlabsPM100USB sends SYST:SENSOR:IDN? in its constructor, SENS:CORR:WAV? MIN,
# SENS:CORR:WAV? MAX, SENSE:CORR:WAV <nm> and MEAS:POW?.
#
# Chosen where the documents are silent (invented):
# - SYST:SENS:IDN? answers "S120C,SIM00002,01-Jan-2024,1,18,49": name, serial, calibration
#   date, type 1 (photodiode), subtype 18, flags 49 = power sensor (1) + response settable (16)
#   + wavelength settable (32), the bits as PyMeasure reads them from the PM100D manual. The
#   values of type/subtype and the date are invented.
# - SENS:CORR:WAV range 400..1100 nm (that of a silicon photodiode sensor such as the S120C);
#   DEF is 550 nm; averaging 1..10000, DEF 1. A suffix NM, UM or M scales the number; any other
#   suffix is error -131.
# - FETC? before any INIT (or after *RST): error -230, no reply. MEAS? without a function
#   measures power. CONF? answers POW.
# - *TST? answers 0 (self-test passed); SYST:VERS? answers 1999.0.
# - A line longer than MAX_LINE characters (the port endpoint keeps no more of it) is discarded
#   unexecuted with error -363 (input buffer overrun); one holding a control character (C0, DEL,
#   C1; IEEE 488.2 would read most as white space) is discarded with error -101 (invalid
#   character). Neither gets a response.

from __future__ import annotations

import math

from gonio.core.preflight import control_character

__all__ = ["ScpiMeter"]

ERRORS = {
    -101: "Invalid character", -102: "Syntax error", -104: "Data type error", -108: "Parameter not allowed",
    -109: "Missing parameter", -113: "Undefined header", -131: "Invalid suffix",
    -222: "Data out of range", -230: "Data corrupt or stale", -350: "Queue overflow",
    -363: "Input buffer overrun",
}
_LONG = {
    "SENSE": "SENS", "CORRECTION": "CORR", "WAVELENGTH": "WAV", "AVERAGE": "AVER",
    "COUNT": "COUN", "MEASURE": "MEAS", "POWER": "POW", "SYSTEM": "SYST", "ERROR": "ERR",
    "SENSOR": "SENS", "CONFIGURE": "CONF", "INITIATE": "INIT", "IMMEDIATE": "IMM",
    "FETCH": "FETC", "SCALAR": "SCAL", "VERSION": "VERS",
}
_SHORT = set(_LONG.values()) | {"NEXT", "IDN", "READ"}
#: canonical headers (after the optional nodes are dropped)
_HEADERS = {
    "SYST:ERR?", "SYST:VERS?", "SYST:SENS:IDN?", "SENS:CORR:WAV", "SENS:CORR:WAV?",
    "SENS:AVER:COUN", "SENS:AVER:COUN?", "MEAS:POW?", "READ?", "CONF:POW", "CONF?", "INIT",
    "FETC?",
}
_COMMON = {"*IDN?", "*RST", "*CLS", "*OPC", "*OPC?", "*WAI", "*STB?", "*ESR?", "*ESE", "*ESE?",
           "*SRE", "*SRE?", "*TST?"}
_SUFFIX = {"NM": 1.0, "UM": 1e3, "M": 1e9}
# standard event status register bits (IEEE 488.2)
_OPC, _QYE, _DDE, _EXE, _CME = 1, 4, 8, 16, 32


def _canon(nodes: list[str], query: bool) -> str | None:
    out = []
    for n in nodes:
        n = _LONG.get(n, n)
        if n not in _SHORT:
            return None
        out.append(n)
    if out[:1] in (["CORR"], ["AVER"]):
        out.insert(0, "SENS")
    if out[:1] in (["MEAS"], ["CONF"]) and out[1:2] == ["SCAL"]:
        del out[1]
    if out == ["MEAS"] and query:
        out = ["MEAS", "POW"]
    if out == ["INIT", "IMM"]:
        out = ["INIT"]
    if out == ["SYST", "ERR", "NEXT"]:
        out = ["SYST", "ERR"]
    h = ":".join(out) + ("?" if query else "")
    return h if h in _HEADERS else None


class ScpiMeter:
    """SCPI server of the power meter port."""

    IDN = "gonio,SimPowerMeter,SIM00001,0.1.0"
    SENSOR_IDN = "S120C,SIM00002,01-Jan-2024,1,18,49"
    WAV_RANGE = (400.0, 1100.0)
    WAV_DEFAULT = 550.0
    AVER_RANGE = (1, 10000)
    #: longest program message (characters, without the terminator) the meter reads
    MAX_LINE = 256

    def __init__(self, instrument):
        self.inst = instrument
        self.queue: list[int] = []
        self.esr = 0
        self.ese = 0
        self.sre = 0
        self.fetched: float | None = None

    @property
    def meter(self):
        return self.inst.meter

    def _error(self, code: int) -> None:
        if len(self.queue) >= 10:
            self.queue[-1] = -350
        else:
            self.queue.append(code)
        self.esr |= _CME if -200 < code <= -100 else _EXE if -300 < code <= -200 else _DDE

    # ------------------------------------------------------------------ framing
    def handle(self, text: str) -> list[str]:
        """Execute one program message (units split at ``;``); return its response line(s).

        A header after ``;`` without a leading ``:`` or ``*`` is relative to the previous
        header's path (SCPI-1999, 6.2.4); the responses of the queries of one line come back
        joined by ``;`` in one line (IEEE 488.2, 8.4).
        """
        text = text.strip(" \r\n")
        if not text:
            return []
        if len(text) > self.MAX_LINE:
            return self.overlong(text)
        if control_character(text) is not None:
            self._error(-101)
            return []
        answers: list[str] = []
        base: list[str] = []
        for unit in text.split(";"):
            unit = unit.strip()
            if not unit:
                self._error(-102)
                break
            parts = unit.split(None, 1)
            header = parts[0].upper()
            arg = parts[1].strip() if len(parts) > 1 else None
            if header.startswith("*"):
                reply = self._common(header, arg)
            else:
                rooted = header.startswith(":")
                nodes = header.lstrip(":").split(":")
                query = nodes[-1].endswith("?")
                nodes[-1] = nodes[-1].rstrip("?")
                if not rooted and base:
                    nodes = base + nodes
                base = nodes[:-1]
                canon = _canon(nodes, query) if all(nodes) else None
                if canon is None:
                    self._error(-113)
                    continue
                reply = self._scpi(canon, arg)
            if reply is not None:
                answers.append(reply)
        return [";".join(answers)] if answers else []

    def overlong(self, text: str) -> list[str]:
        """A line longer than ``MAX_LINE`` (``text``: its first characters): error -363, no response."""
        self._error(-363)
        return []

    # ------------------------------------------------------------------ commands
    def _common(self, header: str, arg: str | None) -> str | None:
        if header not in _COMMON:
            self._error(-113)
            return None
        if header in ("*ESE", "*SRE"):
            v = self._number(arg, (0, 255), 0)
            if v is not None:
                setattr(self, header[1:].lower(), int(v))
            return None
        if arg is not None:
            self._error(-108)
            return None
        m = self.meter
        if header == "*IDN?":
            return self.IDN
        if header == "*RST":
            m.reset()
            self.fetched = None
            return None
        if header == "*CLS":
            self.queue.clear()
            self.esr = 0
            return None
        if header == "*OPC":
            self.esr |= _OPC        # every operation of the simulator completes at once
            return None
        if header == "*OPC?":
            return "1"
        if header == "*WAI":
            return None
        if header == "*STB?":
            return str(self._stb())
        if header == "*ESR?":
            v, self.esr = self.esr, 0
            return str(v)
        if header == "*ESE?":
            return str(self.ese)
        if header == "*SRE?":
            return str(self.sre)
        return "0"                  # *TST?

    def _stb(self) -> int:
        """Status byte: bit 2 error queue not empty (SCPI), bit 5 ESB, bit 6 MSS (IEEE 488.2)."""
        stb = (4 if self.queue else 0) | (32 if self.esr & self.ese else 0)
        if stb & self.sre & ~64:
            stb |= 64
        return stb

    def _scpi(self, h: str, arg: str | None) -> str | None:
        m = self.meter
        if h in ("SENS:CORR:WAV", "SENS:AVER:COUN"):
            wav = h == "SENS:CORR:WAV"
            rng = self.WAV_RANGE if wav else self.AVER_RANGE
            v = self._number(arg, rng, self.WAV_DEFAULT if wav else 1, units=wav)
            if v is None:
                return None
            if not rng[0] <= v <= rng[1] or (not wav and v != int(v)):
                self._error(-222)
                return None
            if wav:
                m.wavelength = float(v)
            else:
                m.average = int(v)
            return None
        if h == "SENS:CORR:WAV?":
            v = self._limit_arg(arg, self.WAV_RANGE, m.wavelength)
            return None if v is None else f"{v:.6E}"
        if h == "SENS:AVER:COUN?":
            v = self._limit_arg(arg, self.AVER_RANGE, m.average)
            return None if v is None else str(int(v))
        if arg is not None and h != "CONF:POW":
            self._error(-108)
            return None
        if h == "SYST:ERR?":
            if not self.queue:
                return '0,"No error"'
            code = self.queue.pop(0)
            return f'{code},"{ERRORS[code]}"'
        if h == "SYST:VERS?":
            return "1999.0"
        if h == "SYST:SENS:IDN?":
            return self.SENSOR_IDN
        if h in ("MEAS:POW?", "READ?"):
            return f"{self._measure():.6E}"
        if h == "CONF:POW":
            if arg is not None:         # CONF:POW [<expected value>]: accepted, ignored
                if self._number(arg, (0.0, math.inf), 0.0) is None:
                    return None
            return None
        if h == "CONF?":
            return "POW"
        if h == "INIT":
            self.fetched = self._measure()
            return None
        # FETC?
        if self.fetched is None:
            self._error(-230)
            return None
        return f"{self.fetched:.6E}"

    def _measure(self) -> float:
        m, clock = self.meter, self.inst.clock
        t0 = clock.now()
        duration = m.average * m.sample_time
        power = self.inst.lamp.power(t0 + 0.5 * duration)
        clock.advance(duration)
        return m.read(power)

    # ------------------------------------------------------------------ arguments
    def _limit_arg(self, arg, rng, value):
        if arg is None:
            return value
        a = arg.upper()
        if a in ("MIN", "MINIMUM"):
            return rng[0]
        if a in ("MAX", "MAXIMUM"):
            return rng[1]
        self._error(-108)
        return None

    def _number(self, arg: str | None, rng, default, units: bool = False) -> float | None:
        """A numeric argument: a number, MIN/MAX/DEF, or (``units``) a number with NM/UM/M."""
        if arg is None:
            self._error(-109)
            return None
        a = arg.strip().upper()
        if a in ("MIN", "MINIMUM"):
            return rng[0]
        if a in ("MAX", "MAXIMUM"):
            return rng[1]
        if a in ("DEF", "DEFAULT"):
            return default
        scale = 1.0
        if units:
            for suffix in ("NM", "UM", "M"):
                if a.endswith(suffix) and a[: -len(suffix)].strip():
                    a, scale = a[: -len(suffix)].strip(), _SUFFIX[suffix]
                    break
        try:
            v = float(a) * scale
        except ValueError:
            head = a.rstrip("ABCDEFGHIJKLMNOPQRSTUVWXYZ")
            try:
                float(head)
            except ValueError:
                self._error(-104)
                return None
            self._error(-131)
            return None
        if not math.isfinite(v):
            self._error(-222)
            return None
        return v
