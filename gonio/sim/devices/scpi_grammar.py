"""SCPI server of the simulated power meter: IEEE 488.2 common commands and the PM100D set.

Sources: IEEE 488.2 (common commands, status byte and standard event register, ``;``
between message units, responses of one line joined by ``;``), SCPI-1999 (long/short
header forms, optional nodes in brackets, numeric suffixes, MIN/MAX/DEF numeric arguments,
unit suffixes, error codes and texts, 9.9E37 / 9.91E37 for infinity and not-a-number), the
Thorlabs PM100D/PM100USB command set as its manual writes it and as the clients a lab uses
send it: the ThorlabsPM100 package (1.2.2: long mixed-case headers such as
``Sense:Correction:WAVelength``, ``Measure:Scalar:POWer`` without ``?``, ``FETCh?``,
``Status:Operation:CONDition?``) and PyMeasure 0.16's ``ThorlabsPM100USB``
(``SYST:SENSOR:IDN?``, ``SENS:CORR:WAV? MIN``, ``MEAS:POW?``).
"""

# The header table (`COMMANDS`) is written in the manual's notation: upper-case letters are the
# short form, ``[...]`` an optional node, ``#`` a numeric suffix (``SENSe1``; only 1 exists on a
# one-channel meter), ``*`` any further nodes. Behaviour chosen where the documents are silent
# (invented: the identity, the sensor, the ranges, FETC? and zeroing, the status registers, the
# line limits) is listed in docs/interfaces.md, section 4 (the simulated PM100D).

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from gonio.core.preflight import control_character

__all__ = ["ScpiMeter", "COMMANDS", "SCPI_INF", "SCPI_NAN"]

#: SCPI-99 vol. 1, 7.2.1.5: +infinity (-SCPI_INF: -infinity) and not-a-number as numbers
SCPI_INF, SCPI_NAN = 9.9e37, 9.91e37

ERRORS = {
    -101: "Invalid character", -102: "Syntax error", -104: "Data type error", -108: "Parameter not allowed",
    -109: "Missing parameter", -113: "Undefined header", -131: "Invalid suffix",
    -222: "Data out of range", -224: "Illegal parameter value", -230: "Data corrupt or stale",
    -241: "Hardware missing", -350: "Queue overflow", -363: "Input buffer overrun",
}
# standard event status register bits (IEEE 488.2)
_OPC, _QYE, _DDE, _EXE, _CME = 1, 4, 8, 16, 32
_NODE = re.compile(r"\[:?([A-Za-z]+)(#?)\]|:?([A-Za-z]+|\*)(#?)")


@dataclass(frozen=True)
class _Node:
    long: str                  # upper case
    short: str
    optional: bool
    suffix: bool               # takes a numeric suffix (only 1 here)

    def matches(self, word: str) -> bool:
        if self.suffix:
            m = re.fullmatch(r"([A-Z]+)(\d*)", word)
            if m is None or m.group(2) not in ("", "1"):
                return False
            word = m.group(1)
        return word == self.long or word == self.short


def _nodes(pattern: str) -> tuple[_Node, ...]:
    out = []
    for m in _NODE.finditer(pattern):
        name, suffix = (m.group(1), m.group(2)) if m.group(1) else (m.group(3), m.group(4))
        short = "".join(c for c in name if c.isupper()) or name.upper()
        out.append(_Node(name.upper(), short, m.group(1) is not None, bool(suffix)))
    return tuple(out)


def _match(words: list[str], nodes: tuple[_Node, ...]) -> bool:
    if not nodes:
        return not words
    node = nodes[0]
    if node.long == "*":
        return True
    if words and node.matches(words[0]) and _match(words[1:], nodes[1:]):
        return True
    return node.optional and _match(words, nodes[1:])


@dataclass(frozen=True)
class _Setting:
    """A value the meter keeps: ``kind`` num, int, bool or enum; MIN/MAX/DEF from ``lo``, ``hi``,
    ``default``; ``units`` the accepted suffixes and their scales; ``choices`` an enum's words."""

    kind: str
    default: object
    lo: float = -math.inf
    hi: float = math.inf
    units: tuple = ()
    choices: tuple = ()


_W = (("W", 1.0), ("MW", 1e-3), ("UW", 1e-6), ("NW", 1e-9), ("PW", 1e-12), ("DBM", None))
_A = (("A", 1.0), ("MA", 1e-3), ("UA", 1e-6), ("NA", 1e-9), ("PA", 1e-12))
_POWER_RANGES = tuple(5e-8 * 10.0 ** k for k in range(7))          # 50 nW .. 50 mW
_CURRENT_RANGES = tuple(5e-8 * 10.0 ** k for k in range(6))        # 50 nA .. 5 mA
_RESPONSIVITY_550 = 0.3                                            # A/W of the photodiode at 550 nm

SETTINGS = {
    "wav": _Setting("num", 550.0, 400.0, 1100.0, (("NM", 1.0), ("UM", 1e3), ("M", 1e9))),
    "aver": _Setting("int", 1, 1, 10000),
    "beam": _Setting("num", 9.5, 0.1, 50.0, (("MM", 1.0), ("CM", 10.0), ("UM", 1e-3))),
    "loss": _Setting("num", 0.0, -60.0, 60.0, (("DB", 1.0),)),
    "resp": _Setting("num", None, 1e-5, 1e3, (("AW", 1.0), ("A/W", 1.0))),
    "pow_range": _Setting("num", _POWER_RANGES[-1], _POWER_RANGES[0], _POWER_RANGES[-1], _W[:-1]),
    "pow_auto": _Setting("bool", 1),
    "pow_ref": _Setting("num", 0.0, 0.0, _POWER_RANGES[-1], _W[:-1]),
    "pow_ref_state": _Setting("bool", 0),
    "pow_unit": _Setting("enum", "W", choices=(("W", "W"), ("DBM", "DBM"))),
    "curr_range": _Setting("num", _CURRENT_RANGES[-1], _CURRENT_RANGES[0], _CURRENT_RANGES[-1], _A),
    "curr_auto": _Setting("bool", 1),
    "curr_ref": _Setting("num", 0.0, 0.0, _CURRENT_RANGES[-1], _A),
    "curr_ref_state": _Setting("bool", 0),
    "peak": _Setting("num", 15.0, 1.0, 95.0, (("PCT", 1.0),)),
    "lpass": _Setting("bool", 0),
    "adapter": _Setting("enum", "PHOT", choices=(("PHOTODIODE", "PHOT"), ("THERMAL", "THER"), ("PYRO", "PYRO"))),
    "beeper": _Setting("bool", 1),
    "lfreq": _Setting("int", 50, 50, 60),
    "brightness": _Setting("num", 1.0, 0.0, 1.0),
    "contrast": _Setting("num", 0.5, 0.0, 1.0),
}
#: measurement functions: the photodiode's, then those it lacks (error -241)
_FUNCTIONS = {"POW": "POWer", "CURR": "CURRent", "PDEN": "PDENsity", "FREQ": "FREQuency"}
_MISSING = ("VOLTage", "TEMPerature", "ENERgy", "EDENsity", "RESistance")
_REGISTERS = ("OPERation", "QUEStionable", "MEASurement", "AUXillary")
_SENSE = "[SENSe#]:"

#: (pattern, forms ("q" query, "s" set), handler key): the first pattern that matches the header
#: and has its form runs
COMMANDS: list[tuple[str, str, str]] = [
    ("SYSTem:ERRor[:NEXT]", "q", "err"), ("SYSTem:ERRor:COUNt", "q", "err_count"),
    ("SYSTem:VERSion", "q", "version"), ("SYSTem:SENSor:IDN", "q", "sensor_idn"),
    ("SYSTem:BEEPer[:IMMediate]", "s", "beep"), ("SYSTem:BEEPer:STATe", "qs", "=beeper"),
    ("SYSTem:LFRequency", "qs", "=lfreq"), ("SYSTem:DATE", "qs", "date"), ("SYSTem:TIME", "qs", "time"),
    ("STATus[:OPERation]:PRESet", "s", "status_preset"),
    *[(f"STATus:{r}:PRESet", "s", "status_preset") for r in _REGISTERS[1:]],   # as ThorlabsPM100 sends it
    *[(f"STATus:{r}[:EVENt]", "q", f"status_event:{r[:4].upper()}") for r in _REGISTERS],
    *[(f"STATus:{r}:CONDition", "q", f"status_cond:{r[:4].upper()}") for r in _REGISTERS],
    *[(f"STATus:{r}:{w}", "qs", f"status_reg:{r[:4].upper()}:{w[:4].upper()}")
      for r in _REGISTERS for w in ("ENABle", "PTRansition", "NTRansition")],
    ("CALibration:STRing", "q", "cal_string"),
    ("DISPlay:BRIGhtness", "qs", "=brightness"), ("DISPlay:CONTrast", "qs", "=contrast"),
    ("ABORt", "s", "abort"), ("INITiate#[:IMMediate]", "s", "init"),
    ("FETCh#[:SCALar][:POWer]", "q", "fetch"), ("READ#[:SCALar][:POWer]", "q", "read"),
    ("CONFigure#", "q", "conf?"),
    *[(f"CONFigure#[:SCALar]:{f}" + ("[:DC]" if f == "CURRent" else ""), "s", f"conf:{k}")
      for k, f in _FUNCTIONS.items()],
    ("CONFigure#[:SCALar][:POWer]", "s", "conf:POW"),
    *[(f"CONFigure#[:SCALar]:{f}" + ("[:DC]" if f == "VOLTage" else ""), "s", "missing") for f in _MISSING],
    *[(f"MEASure#[:SCALar]:{f}" + ("[:DC]" if f == "CURRent" else ""), "qs", f"meas:{k}")
      for k, f in _FUNCTIONS.items()],
    ("MEASure#[:SCALar][:POWer]", "qs", "meas:POW"),
    *[(f"MEASure#[:SCALar]:{f}" + ("[:DC]" if f == "VOLTage" else ""), "qs", "missing") for f in _MISSING],
    (_SENSE + "AVERage[:COUNt]", "qs", "=aver"),
    (_SENSE + "CORRection:COLLect:ZERO[:INITiate]", "s", "zero"),
    (_SENSE + "CORRection:COLLect:ZERO:ABORt", "s", "zero_abort"),
    (_SENSE + "CORRection:COLLect:ZERO:STATe", "q", "zero_state"),
    (_SENSE + "CORRection:COLLect:ZERO:MAGNitude", "q", "zero_magnitude"),
    (_SENSE + "CORRection:BEAMdiameter", "qs", "=beam"),
    (_SENSE + "CORRection:WAVelength", "qs", "=wav"),
    (_SENSE + "CORRection:POWer:THERmopile:*", "qs", "missing"),
    (_SENSE + "CORRection:POWer[:PDIOde][:RESPonse]", "qs", "=resp"),
    (_SENSE + "CORRection:ENERgy:*", "qs", "missing"),
    (_SENSE + "CORRection[:LOSS[:INPut]][:MAGNitude]", "qs", "=loss"),
    (_SENSE + "POWer[:DC]:RANGe:AUTO", "qs", "=pow_auto"),
    (_SENSE + "POWer[:DC]:RANGe[:UPPer]", "qs", "=pow_range"),
    (_SENSE + "POWer[:DC]:REFerence:STATe", "qs", "=pow_ref_state"),
    (_SENSE + "POWer[:DC]:REFerence[:VALue]", "qs", "=pow_ref"),
    (_SENSE + "POWer[:DC]:UNIT", "qs", "=pow_unit"),
    (_SENSE + "CURRent[:DC]:RANGe:AUTO", "qs", "=curr_auto"),
    (_SENSE + "CURRent[:DC]:RANGe[:UPPer]", "qs", "=curr_range"),
    (_SENSE + "CURRent[:DC]:REFerence:STATe", "qs", "=curr_ref_state"),
    (_SENSE + "CURRent[:DC]:REFerence[:VALue]", "qs", "=curr_ref"),
    (_SENSE + "FREQuency:RANGe[:UPPer]", "q", "freq_upper"), (_SENSE + "FREQuency:RANGe:LOWer", "q", "freq_lower"),
    (_SENSE + "PEAKdetector:THReshold", "qs", "=peak"),
    (_SENSE + "VOLTage:*", "qs", "missing"), (_SENSE + "ENERgy:*", "qs", "missing"),
    ("INPut#[:PDIOde]:FILTer[:LPASs][:STATe]", "qs", "=lpass"),
    ("INPut#:ADAPter[:TYPE]", "qs", "=adapter"),
    ("INPut#:THERmopile:*", "qs", "missing"), ("INPut#:PYRo:*", "qs", "missing"),
]
_TABLE = [(_nodes(p), forms, key) for p, forms, key in COMMANDS]
_COMMON = {"*IDN?", "*RST", "*CLS", "*OPC", "*OPC?", "*WAI", "*STB?", "*ESR?", "*ESE", "*ESE?",
           "*SRE", "*SRE?", "*TST?"}
_SUFFIX_HEAD = re.compile(r"^([+-]?(?:\d+\.?\d*|\.\d+)(?:E[+-]?\d+)?)\s*(.*)$")


def _lookup(words: list[str], query: bool) -> str | None:
    """The handler key of a header's nodes; None (error -113) when no command has it in this form."""
    form = "q" if query else "s"
    for nodes, forms, key in _TABLE:
        if form in forms and _match(words, nodes):
            return key
    return None


def _nr3(value: float) -> str:
    return f"{value:.6E}"


class ScpiMeter:
    """SCPI server of the power meter port (a Thorlabs PM100D with an S120C photodiode sensor)."""

    IDN = "Thorlabs,PM100D,P0000001,2.8.0"
    SENSOR_IDN = "S120C,SIM00002,01-Jan-2024,1,18,49"
    NO_SENSOR_IDN = "no sensor,,,0,0,0"
    WAV_RANGE = (SETTINGS["wav"].lo, SETTINGS["wav"].hi)
    WAV_DEFAULT = SETTINGS["wav"].default
    AVER_RANGE = (SETTINGS["aver"].lo, SETTINGS["aver"].hi)
    #: longest program message (characters, without the terminator) the meter reads
    MAX_LINE = 256

    def __init__(self, instrument):
        self.inst = instrument
        self.queue: list[int] = []
        self.esr = 0
        self.ese = 0
        self.sre = 0
        self.reset_state()

    def reset_state(self) -> None:
        """``*RST``'s defaults of what the grammar keeps (the physics keeps wavelength and averaging)."""
        self.values = {k: s.default for k, s in SETTINGS.items() if k not in ("wav", "aver")}
        self.function = "POW"
        self.fetched: float | None = None
        self.zero = 0.0
        self.status = {r[:4].upper(): {"ENAB": 0, "PTRA": 0x7FFF, "NTRA": 0} for r in _REGISTERS}
        self.date, self.time = (2024, 1, 1), (0, 0, 0)

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
                words = header.lstrip(":").split(":")
                query = words[-1].endswith("?")
                words[-1] = words[-1][:-1] if query else words[-1]
                if not rooted and base:
                    words = base + words
                base = words[:-1]
                key = _lookup(words, query) if all(w.isalnum() for w in words) else None
                if key is None:
                    self._error(-113)
                    continue
                reply = self._scpi(key, query, arg)
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
            v = self._number(arg, _Setting("int", 0, 0, 255))
            if v is not None:
                setattr(self, header[1:].lower(), int(v))
            return None
        if arg is not None:
            self._error(-108)
            return None
        if header == "*IDN?":
            return self.IDN
        if header == "*RST":
            self.meter.reset()
            self.reset_state()
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

    def _scpi(self, key: str, query: bool, arg: str | None) -> str | None:
        if key == "missing":                      # a thermopile's, pyro's or thermistor's header
            self._error(-241)
            return None
        if key.startswith("="):
            return self._setting(key[1:], query, arg)
        if key.startswith("status_reg:"):
            _, reg, what = key.split(":")
            if query:
                return None if not self._no_arg(arg) else str(self.status[reg][what])
            v = self._number(arg, _Setting("int", 0, 0, 0x7FFF))
            if v is not None:
                self.status[reg][what] = int(v)
            return None
        if key in ("date", "time"):
            return self._date_time(key, query, arg)
        if not self._no_arg(arg):
            return None
        m = self.meter
        if key == "err":
            if not self.queue:
                return '0,"No error"'
            code = self.queue.pop(0)
            return f'{code},"{ERRORS[code]}"'
        if key == "err_count":
            return str(len(self.queue))
        if key == "version":
            return "1999.0"
        if key == "sensor_idn":
            return self.SENSOR_IDN if m.sensor else self.NO_SENSOR_IDN
        if key == "cal_string":
            return f'"{self.SENSOR_IDN.split(",")[2]}"' if m.sensor else '""'
        if key.startswith("status_event:") or key.startswith("status_cond:"):
            return "0"
        if key == "status_preset":
            for reg in self.status.values():
                reg.update(ENAB=0, PTRA=0x7FFF, NTRA=0)
            return None
        if key in ("beep", "abort", "zero_abort"):
            return None
        if key == "zero":
            self.zero = self._measure_raw(dark=True)
            return None
        if key == "zero_state":
            return "0"
        if key == "zero_magnitude":
            return _nr3(self.zero)
        if key in ("freq_upper", "freq_lower"):
            return _nr3(1e5 if key == "freq_upper" else 0.0)
        if key == "conf?":
            return self.function
        if key.startswith("conf:"):
            self.function = key[5:]
            return None
        if key.startswith("meas:"):
            self.function = key[5:]
            value = self._reading()
            if query:
                return _nr3(value)
            self.fetched = value
            return None
        if key == "read":
            return _nr3(self._reading())
        if key == "init":
            self.fetched = self._reading()
            return None
        # fetch
        if self.fetched is None:
            self._error(-230)
            return None
        return _nr3(self.fetched)

    def _no_arg(self, arg: str | None) -> bool:
        if arg is not None:
            self._error(-108)
            return False
        return True

    # ------------------------------------------------------------------ settings
    def _get(self, key: str):
        m = self.meter
        if key == "wav":
            return m.wavelength
        if key == "aver":
            return m.average
        if key == "resp":
            r = self.values["resp"]
            return self._responsivity(m.wavelength) if r is None else r
        return self.values[key]

    def _put(self, key: str, value) -> None:
        m = self.meter
        if key == "wav":
            m.wavelength = float(value)
            self.values["resp"] = None            # the responsivity follows the wavelength again
        elif key == "aver":
            m.average = int(value)
        elif key in ("pow_range", "curr_range"):
            ranges = _POWER_RANGES if key == "pow_range" else _CURRENT_RANGES
            self.values[key] = next(r for r in ranges if r >= value * (1 - 1e-9))
            self.values[key.split("_")[0] + "_auto"] = 0      # choosing a range ends auto-ranging
        else:
            self.values[key] = value

    @staticmethod
    def _responsivity(wavelength: float) -> float:
        return _RESPONSIVITY_550 * wavelength / 550.0

    def _setting(self, key: str, query: bool, arg: str | None) -> str | None:
        s = SETTINGS[key]
        if query:
            if arg is not None and s.kind in ("num", "int"):
                v = self._limit(arg, s, key)
            elif not self._no_arg(arg):
                return None
            else:
                v = self._get(key)
            if v is None:
                return None
            return str(int(v)) if s.kind in ("int", "bool") else v if s.kind == "enum" else _nr3(v)
        if s.kind == "bool":
            v = self._word(arg, (("ON", 1), ("OFF", 0), ("1", 1), ("0", 0)))
        elif s.kind == "enum":
            v = self._word(arg, tuple((w, short) for w, short in s.choices)
                           + tuple((short, short) for _, short in s.choices))
        else:
            v = self._number(arg, s, key)
            if v is not None and not s.lo <= v <= s.hi * (1 + 1e-9):
                self._error(-222)
                return None
            if v is not None and s.kind == "int" and v != int(v):
                self._error(-222)
                return None
        if v is not None:
            self._put(key, v)
        return None

    def _limit(self, arg: str, s: _Setting, key: str):
        a = arg.strip().upper()
        if a in ("MIN", "MINIMUM"):
            return s.lo
        if a in ("MAX", "MAXIMUM"):
            return s.hi
        if a in ("DEF", "DEFAULT"):
            return self._responsivity(SETTINGS["wav"].default) if s.default is None else s.default
        self._error(-108)
        return None

    def _word(self, arg: str | None, words: tuple):
        if arg is None:
            self._error(-109)
            return None
        a = arg.strip().upper()
        for w, v in words:
            if a == w:
                return v
        self._error(-224)
        return None

    def _number(self, arg: str | None, s: _Setting, key: str = "") -> float | None:
        """A numeric argument: a number, MIN/MAX/DEF, or a number with one of ``s.units``."""
        if arg is None:
            self._error(-109)
            return None
        a = arg.strip().upper()
        if a in ("MIN", "MINIMUM", "MAX", "MAXIMUM", "DEF", "DEFAULT"):
            return self._limit(a, s, key)
        m = _SUFFIX_HEAD.match(a)
        if m is None:
            self._error(-104)
            return None
        v, unit = float(m.group(1)), m.group(2).strip()
        if unit:
            scale = dict(s.units).get(unit, 0.0)
            if not scale:
                self._error(-131)
                return None
            v *= scale
        if not math.isfinite(v):
            self._error(-222)
            return None
        return v

    def _date_time(self, key: str, query: bool, arg: str | None) -> str | None:
        if query:
            return None if not self._no_arg(arg) else ",".join(str(v) for v in getattr(self, key))
        parts = (arg or "").split(",")
        try:
            vals = tuple(int(p) for p in parts)
        except ValueError:
            self._error(-104)
            return None
        limits = ((2000, 2099), (1, 12), (1, 31)) if key == "date" else ((0, 23), (0, 59), (0, 59))
        if len(vals) != 3 or not all(lo <= v <= hi for v, (lo, hi) in zip(vals, limits)):
            self._error(-222 if len(vals) == 3 else -109)
            return None
        setattr(self, key, vals)
        return None

    # ------------------------------------------------------------------ readings
    def _measure_raw(self, dark: bool = False) -> float:
        """One averaged power reading (W) at the wavelength's responsivity; takes the averaging's
        time. ``dark``: the sensor covered (a zero adjustment): the meter's own offset and noise."""
        m, clock = self.meter, self.inst.clock
        t0 = clock.now()
        duration = m.average * m.sample_time
        power, nm = (0.0, None) if dark else self.inst.light(t0 + 0.5 * duration)
        clock.advance(duration)
        return m.read(power, nm)

    def _reading(self) -> float:
        """A reading of the configured function, with the range, unit, loss, offset and delta-mode
        settings applied; SCPI's 9.9E37 / -9.9E37 / 9.91E37 where it has no number."""
        value = self._measure_raw()
        m, v = self.meter, self.values
        if not m.sensor:
            return SCPI_NAN
        if v["resp"] is not None:                  # a responsivity set by hand, not the wavelength's
            value *= self._responsivity(m.wavelength) / v["resp"]
        if v["loss"]:
            value *= 10.0 ** (v["loss"] / 10.0)
        value -= self.zero
        f = self.function
        if f == "FREQ":
            return 0.0
        if f == "CURR":
            current = value * self._get("resp")
            top = _CURRENT_RANGES[-1] if v["curr_auto"] else v["curr_range"]
            if current > top:
                return SCPI_INF
            return current - (v["curr_ref"] if v["curr_ref_state"] else 0.0)
        top = _POWER_RANGES[-1] if v["pow_auto"] else v["pow_range"]
        if value > top:
            return SCPI_INF
        if v["pow_ref_state"]:
            value -= v["pow_ref"]
        if f == "PDEN":
            return value / (math.pi * (v["beam"] / 20.0) ** 2)    # W/cm^2 over the beam's area
        if v["pow_unit"] == "DBM":
            return 10.0 * math.log10(value / 1e-3) if value > 0 else -SCPI_INF
        return value
