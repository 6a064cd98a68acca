"""pyserial URL handler for ``sim://NAME/PORT`` (PORT: ``zaber``, ``meter``, ``camera``).

``import gonio.sim`` appends ``"gonio.sim"`` to ``serial.protocol_handler_packages``; pyserial
then imports this module (``gonio.sim.protocol_sim``) for the ``sim`` scheme and instantiates
``Serial``. NAME is an ``Instrument`` registered in this process.

Reads in an ``instant``-clock instrument never sleep: bytes the host asks for that are not
there advance the simulated clock by the read timeout (as a real port would have waited),
then the read returns what there is. ``timeout=None`` returns what there is at once (nothing
can arrive later: the simulator answers synchronously). With a ``scaled`` clock reads wait
in wall time like a real port. A vanished port (fault) raises ``SerialException`` on every
call and on ``open`` until it is back; each failing call costs 0.1 s of simulated time in
instant mode, so a host's retry loop sees it come back.
"""

from __future__ import annotations

import time
import urllib.parse

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from gonio.sim.instrument import lookup
from gonio.sim.devices.port import PortVanished

__all__ = ["Serial"]

RETRY_COST = 0.1    # simulated seconds a failing call on a vanished port costs (instant clock)


class Serial(SerialBase):
    """Serial port onto a simulated instrument's port."""

    def open(self):
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        ep = self._endpoint_from_url(self.portstr)
        inst = ep.inst
        with inst.lock:
            if not ep.present():
                inst.clock.tick()
                if inst.clock.instant:
                    inst.clock.advance(RETRY_COST)
                raise SerialException(f"could not open port {self.portstr}: [Errno 2] No such file or directory")
            self._ep = ep
            self._generation = ep.generation
        self.is_open = True

    def _endpoint_from_url(self, url: str):
        parts = urllib.parse.urlsplit(url)
        if parts.scheme != "sim":
            raise SerialException(f"expected a string in the form 'sim://NAME/PORT', not {url!r}")
        port = parts.path.strip("/")
        try:
            inst = lookup(parts.netloc)
        except KeyError:
            raise SerialException(f"no simulated instrument registered as {parts.netloc!r}") from None
        if port not in inst.ports:
            raise SerialException(f"unknown port {port!r} ({', '.join(inst.ports)})")
        return inst.ports[port]

    def from_url(self, url):
        """Validate a URL (pyserial API)."""
        self._endpoint_from_url(url)
        return url

    def _reconfigure_port(self):
        pass

    def close(self):
        self.is_open = False

    def _alive(self):
        if not self.is_open:
            raise PortNotOpenError()
        try:
            self._ep.check(self._generation)
        except PortVanished:
            clock = self._ep.inst.clock
            if clock.instant:
                clock.advance(RETRY_COST)
            raise SerialException("device reports readiness to read but returned no data "
                                  "(device disconnected or multiple access on port?)") from None

    @property
    def in_waiting(self):
        self._alive()
        self._ep.poll()
        return self._ep.pending()

    def read(self, size=1):
        def take(got, out):
            n = max(0, min(len(out), size - len(got)))
            return n, len(got) + n >= size

        return self._read(take)

    def read_until(self, expected=b"\n", size=None):
        """pyserial's ``read_until`` (and :meth:`readline`): bytes up to and including
        ``expected``, at most ``size`` of them, or what came before the timeout.

        The same bytes and the same simulated time as pyserial's own, which calls ``read(1)``
        per byte (io's ``readline`` does too): each byte there is taken, and a wait for bytes
        that are not there costs the read timeout once (instant clock) or waits for them up to
        it (scaled clock; one deadline for the line, as pyserial's ``Timeout``). Here the
        buffer is searched once per wait instead: a simulated capture's hosts read ~49 000
        bytes a session (the quick plan), and the per-byte reads cost 2.0 s of a capture's 4.3 s
        of CPU (cProfile, 2026-12-02)."""
        expected = bytes(expected)
        if not expected:
            raise ValueError("read_until needs a non-empty terminator")

        def take(got, out):
            room = len(out) if size is None else max(0, min(len(out), size - len(got)))
            # a terminator may straddle what was taken already and what is waiting
            tail = max(0, len(got) - len(expected) + 1)
            found = (bytes(got[tail:]) + bytes(out[:room])).find(expected)
            if found >= 0:
                return found + len(expected) - (len(got) - tail), True
            return room, size is not None and len(got) + room >= size

        return self._read(take)

    def _read(self, take):
        """The reads' loop: with the alerts that came due queued, ``take(got, waiting)`` says
        how many of the waiting bytes to take and whether the read is then complete (under the
        port's reply-buffer lock only: a read never waits for another port's device); if not,
        wait (:meth:`_wait`) and look again."""
        self._alive()
        ep = self._ep
        got = bytearray()
        deadline = None if self._timeout is None else time.monotonic() + self._timeout
        while True:
            self._alive()
            ep.poll()
            state = {}

            def count(out):
                n, state["done"] = take(got, out)
                return n

            got += ep.take_with(count)
            if state["done"] or not self._wait(deadline):
                return bytes(got)

    def _wait(self, deadline) -> bool:
        """A read found too few bytes: False if it returns now (instant clock: the timeout
        spent on the simulated clock once; scaled: ``deadline`` passed), else True after a
        millisecond's sleep (look again)."""
        clock = self._ep.inst.clock
        if clock.instant:
            if self._timeout:
                clock.advance(self._timeout)
            return False
        if deadline is not None and time.monotonic() >= deadline:
            return False
        time.sleep(0.001)
        return True

    def readline(self, size=-1):
        """A line, its newline included, as io's ``readline`` gives it from ``read(1)``: see
        :meth:`read_until`."""
        return self.read_until(b"\n", None if size is None or size < 0 else size)

    def write(self, data):
        self._alive()
        data = bytes(data)
        self._ep.feed(data)
        return len(data)

    def reset_input_buffer(self):
        self._alive()
        self._ep.take_with(len)

    def reset_output_buffer(self):
        self._alive()

    @property
    def out_waiting(self):
        self._alive()
        return 0

    def cancel_read(self):
        pass

    def cancel_write(self):
        pass

    def _update_break_state(self):
        self._alive()

    def _update_rts_state(self):
        pass

    def _update_dtr_state(self):
        pass

    @property
    def cts(self):
        return True

    @property
    def dsr(self):
        return True

    @property
    def ri(self):
        return False

    @property
    def cd(self):
        return True

