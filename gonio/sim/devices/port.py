"""Byte-stream endpoint of one simulated port: line framing, fault injection, reply buffer.

Shared by the ``sim://`` transport (``protocol_sim.py``) and the pseudo-terminal server
(``_pty.py``). A host writes bytes; each complete line costs ``clock.latency`` of simulated
time (instant clock), passes the fault schedule and reaches the protocol server; its reply
lines are queued for reading.

Both buffers are bounded, as a device's are. An input line longer than the server's
``MAX_LINE`` bytes (``DEFAULT_MAX_LINE`` if it has none) is not buffered: its first
``MAX_LINE`` bytes are kept, the rest is dropped up to the terminator, and the server's
``overlong(prefix)`` answers it (its protocol's error; nothing is executed). Replies wait for
the host in at most ``MAX_OUT`` bytes: a reply line that does not fit is dropped whole (a
host that writes without reading loses answers, as with a full tty buffer, and the process's
memory stays bounded); ``overrun`` counts the lines dropped.
"""

# Each port is its own device (issue 40): ``lock`` serialises that port's lines (a device answers
# one command at a time), the instrument's lock guards only the physics the devices share while a
# line executes, and a device that takes time (a meter averaging, a camera exposing) lets go of
# the instrument's lock while it waits (``Instrument``'s clock sleeps through
# :meth:`Instrument.wait`): one device's slow answer never holds another's. The reply buffer has a
# lock of its own that guards nothing else (readers of one port never wait for another's line).
# Lock order: a port's ``lock``, then the instrument's, then a reply buffer's.

from __future__ import annotations

import math
import re
import string
import threading

__all__ = ["PortEndpoint", "PortVanished"]

_GARBLE_CHARS = (string.ascii_letters + string.digits + "#@/:.- ").encode()
_END_LF = re.compile(b"\n")
_END_CR_LF = re.compile(b"[\r\n]")

#: longest input line (bytes, without the terminator) of a server that declares no ``MAX_LINE``
DEFAULT_MAX_LINE = 4096
#: most reply bytes waiting for the host
MAX_OUT = 1 << 16


class PortVanished(Exception):
    """The port is gone (fault ``vanish``); handles opened before stay dead."""


class PortEndpoint:
    """One port of the instrument.

    Parameters
    ----------
    instrument : Instrument
        Owner (clock, lock, fault schedule).
    name : {"zaber", "meter", "camera"}
        Port name.
    server : object
        Protocol server with ``handle(text) -> list[str]``.
    reply_end : bytes
        Terminator appended to each reply line.
    split_cr : bool
        Whether a lone ``\\r`` also ends an input line (Zaber).
    """

    def __init__(self, instrument, name: str, server, reply_end: bytes, split_cr: bool):
        self.inst = instrument
        self.name = name
        self.server = server
        self.reply_end = reply_end
        self.split_cr = split_cr
        self.commands = 0                 # command lines received (fault counter)
        self.generation = 0               # bumped when the port vanishes
        self.vanished_until: float | None = None
        self.silent_until = -math.inf
        self.on_vanish = []               # callbacks(endpoint, duration) for the pty server
        self.max_line = int(getattr(server, "MAX_LINE", DEFAULT_MAX_LINE))
        self.overrun = 0                  # reply lines dropped: the host did not read them
        self._in = bytearray()            # the line being received (at most max_line bytes)
        self._long = False                # it is longer than max_line: the rest is dropped
        self._in_generation = 0           # the generation ``_in`` was received in
        self.out = bytearray()
        self.lock = threading.RLock()     # one line at a time on this port
        self.out_lock = threading.Lock()  # ``out`` only (a leaf: nothing is taken while held)

    # ------------------------------------------------------------------ presence
    def present(self) -> bool:
        """Whether the port exists now (reappears once its vanish time is over)."""
        if self.vanished_until is None:
            return True
        if self.inst.clock.now() >= self.vanished_until:
            self.vanished_until = None
            return True
        return False

    def vanish(self, duration: float) -> None:
        """Make the port disappear for ``duration`` simulated seconds (the line being received
        is dropped by the port's next ``feed``: another port's fault may vanish this one)."""
        self.generation += 1
        self.vanished_until = self.inst.clock.now() + float(duration)
        with self.out_lock:
            self.out.clear()
        for cb in list(self.on_vanish):
            cb(self, duration)

    def check(self, generation: int) -> None:
        """Raise PortVanished unless a handle of ``generation`` is still connected."""
        if generation != self.generation or not self.present():
            raise PortVanished(self.name)

    # ------------------------------------------------------------------ bytes in
    def feed(self, data: bytes) -> None:
        """Bytes from the host; complete lines are executed at once. At most ``max_line`` bytes
        of a line are kept (see the module's note)."""
        data = bytes(data)
        end = _END_CR_LF if self.split_cr else _END_LF
        encoding = getattr(self.server, "encoding", "ascii")
        with self.lock:
            if self._in_generation != self.generation:      # vanished since: a fresh line
                self._in.clear()
                self._long = False
                self._in_generation = self.generation
            start = 0
            while start < len(data):
                m = end.search(data, start)
                stop = m.start() if m else len(data)
                if not self._long:
                    room = self.max_line - len(self._in)
                    self._in += data[start:min(stop, start + room)]
                    self._long = stop - start > room
                if m is None:
                    break
                start = stop + 1
                line, long_ = bytes(self._in), self._long
                self._in.clear()
                self._long = False
                generation = self.generation
                with self.inst.lock:
                    self._line(line.decode(encoding, "replace").strip(" \r\n"), long_)
                if self.generation != generation:
                    self._in_generation = self.generation
                    break                 # the port vanished: the rest of the write is lost

    def _line(self, text: str, overlong: bool = False) -> None:
        if not text:
            return
        inst = self.inst
        inst.clock.tick()
        self.commands += 1
        n = self.commands
        t = inst.clock.now()
        seed = inst.fault_seed
        execute, drop, again, post = True, False, False, []
        for f in inst.faults.due(self.name, n, t, seed):
            k = f.kind
            if k == "timeout":
                drop, execute = True, f.execute
            elif k == "silence":
                port = inst.ports[f.port]
                port.silent_until = t + f.duration
            elif k in ("garble", "truncate", "bad_checksum"):
                post.append(f)
            elif k == "again":
                again = True
            elif k in ("stall", "limit"):
                inst.zaber.armed_halts.append((f.axis, f.fraction, "FS" if k == "stall" else "WL"))
            elif k == "power_cycle":
                inst.power_cycle(f.device)
            elif k == "vanish":
                inst.ports[f.port].vanish(f.duration)
                if f.port == self.name:
                    return
            elif k in ("camera_nothing", "camera_truncated"):
                inst.camera.armed.append(k.split("_", 1)[1])
            elif k == "lamp_dies":
                inst.lamp.die(f.at_time if f.at_time is not None else t)
        if t < self.silent_until:
            return
        if again:
            replies = self.server.again(text)
        elif execute and overlong:
            refuse = getattr(self.server, "overlong", None)
            replies = refuse(text) if refuse is not None else []
        elif execute:
            replies = self.server.handle(text)
        else:
            replies = []
        if drop or not replies:
            return
        ends = [self.reply_end] * len(replies)
        for f in post:
            rng = f.rng(seed, n)
            line = replies[0]
            if f.kind == "bad_checksum":
                body = line[1:].split(":", 1)[0]
                good = (-sum(body.encode())) & 0xFF
                replies[0] = f"@{body}:{(good + 1) & 0xFF:02X}"
            elif f.kind == "garble":
                chars = bytearray(line.encode("ascii", "replace"))
                k = max(1, len(chars) // 10)
                pos = rng.choice(len(chars), size=min(k, len(chars)), replace=False)
                for p in pos:
                    chars[p] = _GARBLE_CHARS[rng.integers(len(_GARBLE_CHARS))]
                replies[0] = chars.decode("ascii")
            else:       # truncate
                replies[0] = line[: int(rng.integers(1, max(2, len(line))))]
                ends[0] = b""
        for r, e in zip(replies, ends):
            self._queue(r.encode("ascii", "replace") + e)

    def _queue(self, line: bytes) -> None:
        """Queue one reply line for the host, or drop it whole where ``MAX_OUT`` would be passed."""
        with self.out_lock:
            if len(self.out) + len(line) > MAX_OUT:
                self.overrun += 1
                return
            self.out += line

    def poll(self) -> int:
        """Queue the spontaneous lines (Zaber alerts) that came due by now; return how many.

        Called by the pty server's loop and by ``sim://`` reads, so an alert of a motion that
        ends in (scaled) real time reaches the host without a command.
        """
        alerts = getattr(self.server, "alerts", None)
        if alerts is None:
            return 0
        with self.inst.lock:
            if not self.present() or self.inst.clock.now() < self.silent_until:
                return 0
            lines = alerts()
            for line in lines:
                self._queue(line.encode("ascii", "replace") + self.reply_end)
            return len(lines)

    def next_due(self) -> float | None:
        """Wall seconds until the next spontaneous line (an alert of a motion that ends) may be
        due; None when none is pending or the clock is instant (nothing comes due by itself).
        The pty server sleeps no longer than this, so an alert leaves when the motion ends."""
        due = getattr(self.server, "next_alert_at", None)
        clock = self.inst.clock
        if due is None or clock.instant:
            return None
        with self.inst.lock:
            t = due()
            now = clock.now()
        return None if t is None else max(0.0, (t - now) / clock.scale)

    # ------------------------------------------------------------------ bytes out
    def pending(self) -> int:
        """Reply bytes waiting for the host."""
        with self.out_lock:
            return len(self.out)

    def take(self, size: int) -> bytes:
        """Remove and return up to ``size`` reply bytes."""
        with self.out_lock:
            data = bytes(self.out[:size])
            del self.out[:size]
            return data

    def take_with(self, take) -> bytes:
        """Remove and return the reply bytes ``take(waiting)`` counts (under the buffer's lock,
        so the count and the removal see the same bytes)."""
        with self.out_lock:
            n = take(self.out)
            data = bytes(self.out[:n])
            del self.out[:n]
            return data
