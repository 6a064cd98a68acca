"""pyserial URL handler ``expect://NAME``: a port that plays a registered `Exchange`."""

from __future__ import annotations

from serial.serialutil import SerialBase, SerialException, PortNotOpenError

from . import SCRIPTS


class Serial(SerialBase):
    def open(self):
        if self._port is None:
            raise SerialException("port must be set")
        name = self._port.split("://", 1)[1]
        if name not in SCRIPTS:
            raise SerialException(f"could not open port {self._port}: no such device")
        self.script = SCRIPTS[name]
        self.script.opened += 1
        self._wbuf = b""
        self._rbuf = b""
        self.is_open = True

    def close(self):
        if self.is_open:
            self.script.closed += 1
        self.is_open = False

    def _reconfigure_port(self):
        pass

    @property
    def in_waiting(self):
        return len(self._rbuf)

    def write(self, data):
        if not self.is_open:
            raise PortNotOpenError()
        self._wbuf += bytes(data)
        while b"\n" in self._wbuf:
            line, self._wbuf = self._wbuf.split(b"\n", 1)
            reply = self.script.next(line + b"\n")
            if reply is not None:
                self._rbuf += reply
        return len(data)

    def read(self, size=1):
        if not self.is_open:
            raise PortNotOpenError()
        out, self._rbuf = self._rbuf[:size], self._rbuf[size:]
        return out

    def reset_input_buffer(self):
        self._rbuf = b""

    def reset_output_buffer(self):
        self._wbuf = b""
