"""What every driver does with its port: open it through pyserial's ``serial_for_url`` (so
``sim://``, a pty path and /dev/ttyUSB0 are the same to it), close it, and say in one line
which port and which CLI flag to check when it does not open."""

from __future__ import annotations

import serial

from gonio.core.errors import CommunicationError

__all__ = ["SerialDevice"]


class SerialDevice:
    """Base of the serial drivers: ``port_url``, ``baudrate``, ``timeout`` and the port.

    Subclasses name the instrument (``what``) and the CLI flag that gives its port (``flag``)
    for the error message.
    """

    what = "serial"
    flag = "--port"

    def __init__(self, port_url: str, baudrate: int = 115200, timeout: float = 1.0):
        self.port_url = port_url
        self.baudrate = baudrate
        self.timeout = timeout
        self.reconnects = 0
        self._port = None

    def open(self) -> None:
        """Open the port (a second call is a no-op while it is open)."""
        if self._port is not None:
            return
        try:
            self._port = serial.serial_for_url(self.port_url, baudrate=self.baudrate, timeout=self.timeout)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise CommunicationError(f"cannot open the {self.what} port {self.port_url!r} ({exc}); "
                                     f"check the cable and the {self.flag} value") from None

    def close(self) -> None:
        """Close the port."""
        if self._port is not None:
            try:
                self._port.close()
            finally:
                self._port = None

    def reconnect(self) -> None:
        """Close and reopen the port (the caller re-queries the device's state)."""
        self.close()
        self.reconnects += 1
        self.open()

    def read_line(self, wait: float | None = None, garbled: str | None = None) -> str | None:
        """One line within ``wait`` seconds (default the port's timeout), without its terminator
        or surrounding space; None if none came whole or the port failed; ``garbled`` for a
        line that is not ASCII. The port's timeout is restored after a ``wait`` of its own."""
        port = self._port
        own = wait is not None and wait != self.timeout
        try:
            if own:
                port.timeout = wait
            try:
                line = port.readline()
            finally:
                if own and self._port is port:
                    port.timeout = self.timeout
        except (serial.SerialException, OSError, ValueError):
            return None
        if not line.endswith(b"\n"):
            return None
        try:
            return line.decode("ascii").strip()
        except UnicodeDecodeError:
            return garbled

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
