"""SCPI power meter driver (the source monitor on its own port).

Queries end with ``?`` and get one line back; set commands get nothing back, so after every
set command the error queue (``SYST:ERR?``) is read and a non-zero code raises. Lines end
with ``\\n``. The port is a pyserial URL (``serial.serial_for_url``: ``/dev/ttyUSB1``, a pty,
``sim://NAME/meter``) or a VISA resource string (``USB0::0x1313::0x8072::P2000000::INSTR``,
``ASRL/dev/ttyUSB0::INSTR``, ``TCPIP0::host::5025::SOCKET``) opened through PyVISA, as USB-TMC
meters such as the Thorlabs PM100D/USB are reached: with the VISA library ``[meter]
visa_library`` names (``"@py"`` for pyvisa-py, ``"@ivi"`` or a path for NI-VISA or another
vendor's), by default PyVISA's own choice (an installed IVI/NI-VISA library, else pyvisa-py).
SCPI-99's 9.9E37 / -9.9E37 / 9.91E37 readings are refused (`MeterRangeError`), never a power.
"""

# Timing: a reading averages SENS:AVER:COUN samples of [meter] sample_time_s each, so MEAS:POW?
# waits that long on top of the port's timeout. A reply that misses its wait may still arrive:
# the driver then resynchronises before the next exchange (a *OPC?;*OPC? marker, whose joined
# answer 1;1 no single query gives; what comes before it is a late reply, dropped), so a late
# reading is never taken for the answer to the next query.
# Readings: SCPI-99 (vol. 1, 7.2.1.5) codes 9.9E37 (+infinity: over range), -9.9E37 (-infinity:
# under range, e.g. no light in dBm) and 9.91E37 (not a number), each named in the error.

from __future__ import annotations

import math
import re
import time
from typing import Mapping

import serial

from gonio.core.errors import CommunicationError, DeviceError, GonioError
from gonio.bench.drivers.serialport import SerialDevice

__all__ = ["PowerMeter", "MeterRangeError", "is_visa_resource", "scpi_code", "SAMPLE_TIME_S"]

#: Longest program message sent (characters, without the newline): a guard against a value gone
#: wrong (the simulator refuses longer lines: ``gonio.sim.devices.scpi_grammar.ScpiMeter.MAX_LINE``).
MAX_COMMAND = 256
_NOT_PRINTABLE = re.compile("[^ -~]")

_VISA = re.compile(r"^(ASRL|USB\d*|TCPIP\d*|GPIB\d*|VXI\d*|PXI\d*)[^\s]*::(INSTR|SOCKET)$", re.IGNORECASE)

#: Seconds per averaged sample the driver allows for when ``[meter] sample_time_s`` is not given:
#: generous for a PM100-class meter (the simulator's is 0.3 ms), so a long average never outlasts
#: the wait.
SAMPLE_TIME_S = 3e-3
#: The resynchronisation marker and its answer (IEEE 488.2: the responses of one line joined by ``;``).
_SYNC, _SYNC_ANSWER = "*OPC?;*OPC?", "1;1"
#: Lines read while resynchronising before the marker's answer must have come.
_SYNC_LINES = 16

#: SCPI-99 vol. 1, 7.2.1.5: the numeric codes a reading may carry instead of a value.
_CODES = ((9.91e37, "9.91E37, SCPI's not-a-number: the meter has no valid reading (no sensor, or a sensor "
                    "fault); check the sensor and its cable"),
          (9.9e37, "9.9E37, SCPI's +infinity: the light is over the meter's range; switch auto-ranging on "
                   "(SENS:POW:RANG:AUTO ON) or choose a higher range"),
          (-9.9e37, "-9.9E37, SCPI's -infinity: the reading is under the meter's range (no light in dBm?); "
                    "check the beam and the meter's unit"))


def is_visa_resource(text: str) -> bool:
    """Whether ``text`` is a VISA resource string (``...::INSTR`` or ``...::SOCKET``)."""
    return isinstance(text, str) and len(text) <= 256 and bool(_VISA.match(text))


def scpi_code(value: float) -> str | None:
    """What a SCPI not-a-number or infinity code in a reading means (None for a plain value).

    Compared to 5 significant digits: a meter may print 9.9E37 as ``9.900000E+37`` or
    ``+9.90E+37``."""
    if not math.isfinite(value):
        return None
    for code, why in _CODES:
        if abs(value - code) <= 1e-5 * abs(code):
            return why
    return None


class MeterRangeError(DeviceError):
    """The meter answered a SCPI over-range, under-range or not-a-number code, not a power."""


class _VisaPort:
    """The few pyserial calls the driver makes, on a PyVISA resource."""

    def __init__(self, resource: str, baudrate: int, timeout: float, library: str | None):
        import pyvisa

        self._rm = pyvisa.ResourceManager(library) if library else pyvisa.ResourceManager()
        self._errors = (pyvisa.errors.VisaIOError, OSError, ValueError)
        try:
            self._res = self._rm.open_resource(resource, read_termination="\n", write_termination="",
                                               timeout=max(1, int(timeout * 1000)))
            if resource.upper().startswith("ASRL"):
                self._res.baud_rate = int(baudrate)
        except Exception:
            self._rm.close()
            raise

    in_waiting = 0                       # unknown through VISA: the resync marker drains instead

    @property
    def timeout(self) -> float:
        return self._res.timeout / 1000.0

    @timeout.setter
    def timeout(self, seconds: float) -> None:
        self._res.timeout = max(1, int(math.ceil(seconds * 1000)))

    def reset_input_buffer(self) -> None:
        pass

    def write(self, data: bytes) -> int:
        try:
            return self._res.write_raw(bytes(data))
        except self._errors as exc:
            raise serial.SerialException(str(exc)) from None

    def readline(self) -> bytes:
        try:
            return self._res.read().encode("ascii", "replace") + b"\n"
        except self._errors:
            return b""                   # a timeout, as pyserial's readline gives it
        except UnicodeDecodeError:
            return b"\xff\n"

    def close(self) -> None:
        try:
            self._res.close()
        finally:
            self._rm.close()


class PowerMeter(SerialDevice):
    """A SCPI optical power meter (Thorlabs PM100-like).

    Parameters
    ----------
    port_url : str
        ``sim://NAME/meter``, a pty path, ``/dev/ttyUSB1`` or a VISA resource.
    baudrate : int
    timeout : float
        Seconds to wait for a reply line, on top of a reading's averaging time.
    retries : int
        Re-sends of a query that got no or a garbled answer, before a reconnect and one more
        round; then `CommunicationError`.
    sample_time_s : float
        Seconds per averaged sample (a reading waits ``averaging * sample_time_s`` longer).
    visa_library : str or None
        The VISA library of a VISA resource (``"@py"``, ``"@ivi"``, a path); None or ``""``:
        PyVISA's default (IVI/NI-VISA where installed, else pyvisa-py).
    """

    what, flag = "power-meter", "--meter-port"

    def __init__(self, port_url: str, baudrate: int = 115200, timeout: float = 1.0, *, retries: int = 2,
                 sample_time_s: float = SAMPLE_TIME_S, visa_library: str | None = None):
        super().__init__(port_url, baudrate, timeout)
        if not (math.isfinite(sample_time_s) and sample_time_s > 0):
            raise GonioError(f"meter sample time {sample_time_s!r} s is invalid; fix [meter] sample_time_s")
        self.retries = retries
        self.retries_used = 0
        self.sample_time_s = float(sample_time_s)
        self.visa_library = visa_library or None
        self.averaging: int | None = None      # samples per reading, once configured or read
        self._late: float | None = None        # a reply may still come: the longest wait it had
        self.open()

    @classmethod
    def from_settings(cls, port_url: str, settings: Mapping | None, baudrate: int = 115200,
                      timeout: float = 1.0, **kw) -> "PowerMeter":
        """The meter on ``port_url`` with ``[meter] sample_time_s`` and ``visa_library`` of ``settings``."""
        m = (settings or {}).get("meter", {}) or {}
        library = m.get("visa_library")
        if library is not None and (not isinstance(library, str) or len(library) > 400 or not library.isprintable()):
            raise GonioError(f"[meter] visa_library = {library!r:.60}: give a VISA library such as \"@py\" or "
                             "\"@ivi\", or leave it out for PyVISA's default")
        try:
            sample = float(m.get("sample_time_s", SAMPLE_TIME_S))
        except (TypeError, ValueError):
            sample = math.nan
        return cls(port_url, baudrate, timeout, sample_time_s=sample, visa_library=library, **kw)

    def open(self) -> None:
        """Open the port: a VISA resource through PyVISA, else a pyserial URL."""
        if self._port is not None or not is_visa_resource(self.port_url):
            return super().open()
        try:
            self._port = _VisaPort(self.port_url, self.baudrate, self.timeout, self.visa_library)
        except ImportError:
            raise CommunicationError(f"the power-meter resource {self.port_url!r} needs PyVISA and a VISA library "
                                     "(pyvisa-py or NI-VISA); install them or give a serial port to --meter-port") from None
        except Exception as exc:           # PyVISA's errors are many and backend-specific
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            lib = f" with the VISA library {self.visa_library!r}" if self.visa_library else ""
            raise CommunicationError(f"cannot open the power-meter resource {self.port_url!r}{lib} ({msg}); "
                                     "check the cable, the --meter-port value and [meter] visa_library") from None

    def _drain(self) -> None:
        """Drop unread input: a late answer to an earlier query, or one a killed process left."""
        try:
            if self._port.in_waiting:
                self._port.reset_input_buffer()
        except (serial.SerialException, OSError, AttributeError, NotImplementedError):
            pass

    @staticmethod
    def _checked(text: str) -> str:
        """``text`` as one SCPI program message unit: printable ASCII (a control character such
        as a newline would end the line and start another command), no ``;`` (which chains
        another unit), at most `MAX_COMMAND` characters; else `GonioError`."""
        text = str(text)
        bad = _NOT_PRINTABLE.search(text)
        if bad is not None:
            raise GonioError(f"power-meter command {text[:40]!r} holds {bad.group()!r}, not printable ASCII; "
                             "send one command of printable characters")
        if ";" in text:
            raise GonioError(f"power-meter command {text[:40]!r} chains commands with ';'; send one at a time")
        if len(text) > MAX_COMMAND:
            raise GonioError(f"power-meter command {text[:40]!r}... is {len(text)} characters long, "
                             f"more than {MAX_COMMAND}; send a shorter command")
        return text

    def _write(self, text: str) -> bool:
        """Send one line; False if the port failed (the caller retries, then reconnects)."""
        self._drain()
        try:
            self._port.write((text + "\n").encode("ascii"))
            return True
        except (serial.SerialException, OSError):
            return False

    def _read(self, wait: float | None = None) -> str | None:
        """One reply line within ``wait`` seconds (default the port's timeout); None if none came."""
        return self.read_line(wait)

    def _resync(self) -> bool:
        """After an answer that did not come in time (or came garbled): send the marker and drop
        every line before its answer, waiting as long as the late reply's own query could take.
        True once in step again."""
        wait = max(self._late or 0.0, self.timeout)
        if not self._write(_SYNC):
            return False
        deadline = time.monotonic() + wait + self.timeout
        for _ in range(_SYNC_LINES):
            left = deadline - time.monotonic()
            if left <= 0:
                break
            line = self._read(max(left, 0.001))
            if line is None:
                break
            if line == _SYNC_ANSWER:
                self._late = None
                return True
        return False

    def query(self, text: str, parse=str, *, wait: float | None = None):
        """Send a query and return its parsed one-line answer (retries, then a reconnect).

        ``wait``: seconds to wait for the answer (default the port's timeout); a reply that
        misses it is dropped by a resynchronisation before the next exchange. ``parse`` raises
        ValueError for a garbled answer (retried); any other error it raises is the answer's.
        """
        text = self._checked(text)
        wait = self.timeout if wait is None else float(wait)
        last = "no answer"
        if self._port is None:                 # a reconnect failed earlier: try again now
            self.open()
        for round_ in range(2):
            if round_:
                self.reconnect()
            for _ in range(self.retries + 1):
                if self._late is not None and not self._resync():
                    last = "no answer to a resynchronisation"
                    self.retries_used += 1
                    continue
                line = self._read(wait) if self._write(text) else None
                if line is None:
                    last = "no answer"
                    self._late = max(self._late or 0.0, wait)    # it may still come: resync first
                    self.retries_used += 1
                    continue
                try:
                    return parse(line)
                except ValueError:
                    last = f"garbled answer {line!r}"
                    self._late = max(self._late or 0.0, wait)    # a stray line, perhaps: resync first
                    self.retries_used += 1
        raise CommunicationError(f"power meter on {self.port_url} gave {last} to {text!r} after retries and "
                                 "a reconnect; check it is on and connected, then resume the session")

    def command(self, text: str) -> None:
        """Send a set command, then read the error queue; raise `DeviceError` on an error."""
        text = self._checked(text)
        if self._port is None:
            self.open()
        if self._late is not None:
            self._resync()                     # a failed resync: error() below tries again
        if not self._write(text):
            raise CommunicationError(f"power meter on {self.port_url} cannot be written; check the cable, "
                                     "then resume the session")
        code, msg = self.error()
        if code != 0:
            raise DeviceError(f"power meter rejected {text!r}: {code} {msg}; check the [meter] settings")

    def error(self) -> tuple[int, str]:
        """Pop one entry of the error queue: ``(code, message)``; ``(0, "No error")`` if empty."""
        def parse(line: str) -> tuple[int, str]:
            code, _, msg = line.partition(",")
            return int(code), msg.strip().strip('"')
        return self.query("SYST:ERR?", parse)

    def identify(self) -> str:
        """``*IDN?``: ``Vendor,Model,Serial,Firmware``."""
        def parse(line: str) -> str:
            if line.count(",") < 3:
                raise ValueError(line)
            return line
        return self.query("*IDN?", parse)

    def configure(self, wavelength_nm: float, averaging: int) -> None:
        """Set the correction wavelength (nm), the samples averaged per reading and the unit (W)."""
        if not (math.isfinite(wavelength_nm) and wavelength_nm > 0):
            raise GonioError(f"meter wavelength {wavelength_nm!r} nm is invalid; fix [meter] wavelength_nm")
        if int(averaging) < 1:
            raise GonioError(f"meter averaging {averaging!r} is invalid; fix [meter] averaging")
        self.command(f"SENS:CORR:WAV {wavelength_nm:g}")
        self.averaging = None                  # unknown until the meter took the new count
        self.command(f"SENS:AVER:COUN {int(averaging)}")
        self.averaging = int(averaging)

    def wavelength(self) -> float:
        """The correction wavelength (nm)."""
        return self.query("SENS:CORR:WAV?", float)

    def reading_time(self) -> float:
        """Seconds one reading averages for (``averaging * sample_time_s``; the count is read from
        the meter the first time where `configure` did not set it)."""
        if self.averaging is None:
            def parse(line: str) -> int:
                n = int(float(line))
                if n < 1:
                    raise ValueError(line)
                return n
            self.averaging = self.query("SENS:AVER:COUN?", parse)
        return self.averaging * self.sample_time_s

    def power(self) -> float:
        """``MEAS:POW?``: optical power in W, waiting for the reading's averaging on top of the
        port's timeout. `MeterRangeError` for a SCPI over-range, under-range or not-a-number code."""
        def parse(line: str) -> float:
            value = float(line)
            why = scpi_code(value)
            if why is not None:
                raise MeterRangeError(f"power meter on {self.port_url} reads {why}")
            if not math.isfinite(value):
                raise ValueError(line)
            return value
        return self.query("MEAS:POW?", parse, wait=self.timeout + self.reading_time())
