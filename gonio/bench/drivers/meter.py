"""SCPI power meter driver (the source monitor on its own port).

Queries end with ``?`` and get one line back; set commands get nothing back, so after every
set command the error queue (``SYST:ERR?``) is read and a non-zero code raises. Lines end
with ``\\n``. The port is a pyserial URL (``serial.serial_for_url``: ``/dev/ttyUSB1``, a pty,
``sim://NAME/meter``) or a VISA resource string (``USB0::0x1313::0x8072::P2000000::INSTR``,
``ASRL/dev/ttyUSB0::INSTR``, ``TCPIP0::host::5025::SOCKET``) opened through PyVISA with the
pure-Python pyvisa-py backend (``@py``), as USB-TMC meters such as the Thorlabs PM100D/USB
are reached.
"""

from __future__ import annotations

import math
import re

import serial

from gonio.core.errors import CommunicationError, DeviceError, GonioError
from gonio.bench.drivers.serialport import SerialDevice

__all__ = ["PowerMeter", "is_visa_resource"]

#: Longest program message sent (characters, without the newline): a guard against a value gone
#: wrong (the simulator refuses longer lines: ``gonio.sim.devices.scpi_grammar.ScpiMeter.MAX_LINE``).
MAX_COMMAND = 256
_NOT_PRINTABLE = re.compile("[^ -~]")

_VISA = re.compile(r"^(ASRL|USB\d*|TCPIP\d*|GPIB\d*|VXI\d*|PXI\d*)[^\s]*::(INSTR|SOCKET)$", re.IGNORECASE)


def is_visa_resource(text: str) -> bool:
    """Whether ``text`` is a VISA resource string (``...::INSTR`` or ``...::SOCKET``)."""
    return isinstance(text, str) and len(text) <= 256 and bool(_VISA.match(text))


class _VisaPort:
    """The few pyserial calls the driver makes, on a PyVISA resource."""

    def __init__(self, resource: str, baudrate: int, timeout: float):
        import pyvisa

        self._rm = pyvisa.ResourceManager("@py")
        self._errors = (pyvisa.errors.VisaIOError, OSError, ValueError)
        try:
            self._res = self._rm.open_resource(resource, read_termination="\n", write_termination="",
                                               timeout=max(1, int(timeout * 1000)))
            if resource.upper().startswith("ASRL"):
                self._res.baud_rate = int(baudrate)
        except Exception:
            self._rm.close()
            raise

    in_waiting = 0                       # unknown through VISA: nothing to drain

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
        ``sim://NAME/meter``, a pty path or ``/dev/ttyUSB1``.
    baudrate : int
    timeout : float
        Seconds to wait for a reply line.
    retries : int
        Re-sends of a query that got no or a garbled answer, before a reconnect and one more
        round; then `CommunicationError`.
    """

    what, flag = "power-meter", "--meter-port"

    def __init__(self, port_url: str, baudrate: int = 115200, timeout: float = 1.0, *, retries: int = 2):
        super().__init__(port_url, baudrate, timeout)
        self.retries = retries
        self.retries_used = 0
        self.open()

    def open(self) -> None:
        """Open the port: a VISA resource through PyVISA (pyvisa-py), else a pyserial URL."""
        if self._port is not None or not is_visa_resource(self.port_url):
            return super().open()
        try:
            self._port = _VisaPort(self.port_url, self.baudrate, self.timeout)
        except ImportError:
            raise CommunicationError(f"the power-meter resource {self.port_url!r} needs PyVISA and pyvisa-py; "
                                     "install them or give a serial port to --meter-port") from None
        except Exception as exc:           # PyVISA's errors are many and backend-specific
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise CommunicationError(f"cannot open the power-meter resource {self.port_url!r} ({msg}); "
                                     "check the cable and the --meter-port value") from None

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

    def _read(self) -> str | None:
        try:
            line = self._port.readline()
        except (serial.SerialException, OSError):
            return None
        if not line.endswith(b"\n"):
            return None
        try:
            return line.decode("ascii").strip()
        except UnicodeDecodeError:
            return None

    def query(self, text: str, parse=str):
        """Send a query and return its parsed one-line answer (retries, then a reconnect)."""
        text = self._checked(text)
        last = "no answer"
        if self._port is None:                 # a reconnect failed earlier: try again now
            self.open()
        for round_ in range(2):
            if round_:
                self.reconnect()
            for _ in range(self.retries + 1):
                line = self._read() if self._write(text) else None
                if line is None:
                    last = "no answer"
                    self.retries_used += 1
                    continue
                try:
                    return parse(line)
                except ValueError:
                    last = f"garbled answer {line!r}"
                    self.retries_used += 1
        raise CommunicationError(f"power meter on {self.port_url} gave {last} to {text!r} after retries and "
                                 "a reconnect; check it is on and connected, then resume the session")

    def command(self, text: str) -> None:
        """Send a set command, then read the error queue; raise `DeviceError` on an error."""
        text = self._checked(text)
        if self._port is None:
            self.open()
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
        """Set the correction wavelength (nm) and the samples averaged per reading."""
        if not (math.isfinite(wavelength_nm) and wavelength_nm > 0):
            raise GonioError(f"meter wavelength {wavelength_nm!r} nm is invalid; fix [meter] wavelength_nm")
        if int(averaging) < 1:
            raise GonioError(f"meter averaging {averaging!r} is invalid; fix [meter] averaging")
        self.command(f"SENS:CORR:WAV {wavelength_nm:g}")
        self.command(f"SENS:AVER:COUN {int(averaging)}")

    def wavelength(self) -> float:
        """The correction wavelength (nm)."""
        return self.query("SENS:CORR:WAV?", float)

    def power(self) -> float:
        """``MEAS:POW?``: optical power in W."""
        def parse(line: str) -> float:
            value = float(line)
            if not math.isfinite(value):
                raise ValueError(line)
            return value
        return self.query("MEAS:POW?", parse)
