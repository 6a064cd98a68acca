"""Zaber ASCII chain: one serial port, the devices daisy-chained on it.

The wire format is that of ``shared/notes/protocols.md``; the bytes of one line are
`gonio.bench.drivers.zaber_protocol`'s. Only ``serial.serial_for_url`` opens the port, so a
``sim://NAME/zaber`` URL, a pseudo-terminal path and ``/dev/ttyUSB0`` are the same here. The
devices on the chain have their own modules: `gonio.bench.drivers.stages.Goniometer` (device
1) and `gonio.bench.drivers.led.LedSource` (device 2).

`ZaberChain`: message ids, checksums, bounded retries on a silent or garbled reply, then a
reconnect; `RJ` raises `RejectedError`, fault flags raise `FaultError`; `broadcast` and
`emergency_stop` address every device at once. Info lines and alerts are skipped, continued
replies joined and ``NA`` read as NaN; `ZaberChain.wait_idle` waits for a move by polling or by
the devices' IDLE alerts. Retries resend the same command: safe for every command the drivers
send (they never send ``move rel``).
"""

# What real controllers may send besides the reply (Zaber ASCII protocol manual, message types
# and "message continuation"; zaber-motion 10.3 on the wire): info lines #.. and alerts !..
# anywhere, before or between replies; a reply whose data ends in \ goes on in
# "#DD A [ID] cont ..." lines of the same device, axis and message id; NA for an axis that
# lacks a setting in an axis-0 get. ZaberChain skips the first, joins the second and reads NA
# as NaN (Reply.values), which the callers refuse by name.
#
# wait_idle: by polling /D 0 every poll_interval_s, or, on a device whose alerts enable_alerts
# turned on (set comm.alert 1; a device that rejects it is polled), by the alert
# "!DD A IDLE WARN" each axis sends when its motion ends: one poll, then, while it says BUSY, a
# wait for the device's next alert (an alert read meanwhile, between the replies of other
# commands, is kept for it) and a poll to confirm; a silent port for the port's timeout also
# polls (an alert lost on the line only delays the wait).
#
# Settings the driver changes on a device are given back when it closes the port: comm.alert
# (enable_alerts) goes back to what the device had: a device keeps the setting when the host
# closes its port, and the next program on the chain would read alerts among its replies.
#
# Resending is safe for absolute moves, homing, gets, sets and lamp on/off; it would not be
# for move rel, which the drivers never send.

from __future__ import annotations

import math
import time
from typing import Callable

import serial

from gonio.core.errors import CommunicationError, FaultError, GonioError, RejectedError
from gonio.bench.drivers.identify import zaber_device
from gonio.bench.drivers.serialport import SerialDevice
from gonio.bench.drivers.zaber_protocol import (FLAG_MEANINGS, REJECT_MEANINGS, Reply, format_command, parse_continuation, parse_reply)

__all__ = ["ZaberChain", "emergency_stop"]


class _NoReply(Exception):
    """No complete line before the port's timeout."""


class _Garbled(Exception):
    """A line arrived but could not be parsed (or its checksum is wrong)."""


class ZaberChain(SerialDevice):
    """One Zaber ASCII daisy chain on one serial port.

    Parameters
    ----------
    port_url : str
        Anything ``serial.serial_for_url`` opens: ``sim://lab/zaber``, ``/dev/ttyUSB0``, a pty.
    baudrate : int
        9600 or 115200 on real devices.
    timeout : float
        Seconds to wait for one reply line.
    checksum : bool
        Send LRC checksums (the device then rejects corrupted commands).
    retries : int
        Resends after a silent or garbled reply before reconnecting; after the reconnect the
        command gets one more round of ``retries + 1`` tries, then `CommunicationError`.
    on_warning : callable, optional
        Called with ``(device, flag, meaning)`` for each new W*/N* flag seen in a reply.

    Notes
    -----
    Message ids run 0..99 and wrap; a reply whose id does not match (a late answer to an
    earlier, retried command) is discarded, which is how the chain resyncs after a garbled
    or lost line.
    """

    what, flag = "stage", "--port"

    def __init__(self, port_url: str, baudrate: int = 115200, timeout: float = 1.0, *,
                 checksum: bool = True, retries: int = 2,
                 on_warning: Callable[[int, str, str], None] | None = None):
        super().__init__(port_url, baudrate, timeout)
        self.checksum = checksum
        self.retries = retries
        self.on_warning = on_warning
        self.retries_used = 0                 # resends after a silent or garbled reply (all time)
        self.warnings_seen: list[tuple[int, str]] = []
        # (sets of device numbers; not annotated set[int]: in this class `set` is the method below,
        # and the API reference's pdoc reads the annotation in the class's namespace)
        self.alerting = set()                 # devices whose alerts are on (`enable_alerts`)
        self._alerted = set()                 # devices an alert was read from since their last poll
        self._partial = b""                   # a line cut by an alert window's end, completed next read
        self._restore: dict[int, str] = {}    # device -> the comm.alert it had before enable_alerts
        self._reconnecting = False
        self._msgid = -1
        self.open()

    def reconnect(self) -> None:
        self._partial = b""                   # a cut line of the old port is never completed
        self._reconnecting = True             # the devices keep their settings over a reconnect
        try:
            super().reconnect()
        finally:
            self._reconnecting = False

    def close(self) -> None:
        """Give each device back the ``comm.alert`` it had before `enable_alerts` turned it on
        (a device keeps the setting after the port closes: the next program on the chain would
        get alerts among its replies), then close the port. One try per device, no retries: a
        device that does not answer keeps alerting, and the port closes all the same."""
        if not self._reconnecting:
            for device, value in list(self._restore.items()):
                try:
                    self._exchange(device, 0, f"set comm.alert {value}")
                except (_NoReply, _Garbled, GonioError):
                    pass
                self.alerting.discard(device)
            self._restore.clear()
        super().close()

    # -- one exchange --------------------------------------------------------------------
    def _next_msgid(self) -> int:
        self._msgid = (self._msgid + 1) % 100
        return self._msgid

    def _readline(self, keep_partial: bool = False) -> bytes:
        """One line; `_NoReply` on a timeout. ``keep_partial``: a line cut by the timeout is kept
        and completed by the next read (waiting for an alert in short windows)."""
        try:
            line = self._port.readline()
        except (serial.SerialException, OSError) as exc:
            self._partial = b""
            raise _NoReply(str(exc)) from None
        line, self._partial = self._partial + line, b""
        if not line.endswith(b"\n"):
            if keep_partial and len(line) < 4096:
                self._partial = line
            raise _NoReply("timeout")
        return line

    def _exchange(self, device: int, axis: int, command: str) -> Reply:
        if self._port is None:
            raise _NoReply("port closed")
        msgid = self._next_msgid()
        try:
            self._port.write(format_command(device, axis, command, msgid, self.checksum))
        except (serial.SerialException, OSError) as exc:
            raise _NoReply(str(exc)) from None
        while True:
            line = self._readline()
            if line[:1] in (b"#", b"!"):        # info lines and alerts
                self._note_alert(line)
                continue
            try:
                reply = parse_reply(line)
            except (ValueError, UnicodeDecodeError) as exc:
                raise _Garbled(str(exc)) from None
            if reply.msgid != msgid or (device != 0 and reply.device != device):
                continue                          # a late reply to an earlier try
            return self._complete(reply)

    #: Most continuation lines one reply may take (a hostile or broken device cannot keep
    #: the driver reading forever).
    MAX_CONTINUATIONS = 64

    def _complete(self, reply: Reply) -> Reply:
        """Join the ``cont`` lines of a continued reply (same device, axis, message id)."""
        parts = [reply.data]
        n = 0
        while parts[-1].endswith("\\"):
            parts[-1] = parts[-1][:-1].rstrip()
            n += 1
            if n > self.MAX_CONTINUATIONS:
                raise _Garbled(f"reply of device {reply.device} continued over {self.MAX_CONTINUATIONS} lines")
            while True:
                line = self._readline()
                if line[:1] == b"!":
                    self._note_alert(line)
                    continue                      # an alert between the packets
                if line[:1] != b"#":
                    raise _Garbled(f"continuation expected after {reply.data!r}, got {line!r}")
                try:
                    dev, ax, mid, data = parse_continuation(line)
                except (ValueError, UnicodeDecodeError):
                    continue                      # an info line of another kind
                if (dev, ax, mid) == (reply.device, reply.axis, reply.msgid):
                    parts.append(data)
                    break
        if n == 0:
            return reply
        data = " ".join(p for p in parts if p)
        return Reply(reply.device, reply.axis, reply.msgid, reply.flag, reply.status, reply.warning, data)

    def request(self, device: int, axis: int, command: str = "", *, check: bool = True) -> Reply:
        """Send one command and return its reply.

        Parameters
        ----------
        device, axis : int
            Address (device 1..99; a broadcast is `broadcast`'s job) and axis.
        command : str
            E.g. ``"get pos"``, ``"move abs 64000"``; empty to poll.
        check : bool
            Raise on ``RJ`` and on fault flags (F*); W*/N* flags are always reported.

        Raises
        ------
        RejectedError
            The device answered ``RJ``; the message names the reason.
        FaultError
            The reply carries a fault flag (the message gives all active flags' meanings).
        CommunicationError
            No valid reply after the retries, a reconnect and the retries again.
        """
        last = ""
        for round_ in range(2):
            if round_ or self._port is None:     # (a reconnect failed earlier: try again now)
                try:
                    self.reconnect()
                except CommunicationError as exc:
                    last = str(exc)
                    break
            for _ in range(self.retries + 1):
                try:
                    reply = self._exchange(device, axis, command)
                except (_NoReply, _Garbled) as exc:
                    last = str(exc)
                    self.retries_used += 1
                    continue
                if reply.flag == "RJ" and reply.data.split()[:1] == ["AGAIN"]:
                    last = "device busy (AGAIN)"      # the device asks for the command again
                    self.retries_used += 1
                    continue
                return self._checked(reply, command, check)
        raise CommunicationError(f"no valid reply from Zaber device {device} to {command or 'poll'!r} "
                                 f"on {self.port_url} after {2 * (self.retries + 1)} tries and a reconnect "
                                 f"({last}); check power and cable, then resume the session")

    def broadcast(self, command: str, n_devices: int) -> list[Reply]:
        """Send ``command`` to every device (address 0) and collect up to ``n_devices`` replies.

        No retries: used for ``estop`` and ``stop``, where speed matters more than an answer.
        Replies are matched by message id, one per device (alerts, info lines, garbage and
        late replies to earlier commands are skipped); reading stops at ``n_devices`` replies
        or the first silent timeout, then whatever else is already waiting is read away, so
        the next command starts on an empty buffer.
        """
        by_device: dict[int, Reply] = {}
        msgid = self._next_msgid()
        try:
            self._port.write(format_command(0, 0, command, msgid, self.checksum))
        except (serial.SerialException, OSError):
            return []
        skipped = 0
        while len(by_device) < n_devices and skipped <= 16 * n_devices + 16:
            try:
                line = self._readline()
            except _NoReply:
                break
            try:
                reply = parse_reply(line) if line[:1] == b"@" else None
            except (ValueError, UnicodeDecodeError):
                reply = None
            if reply is None or reply.msgid != msgid or reply.device in by_device:
                self._note_alert(line)
                skipped += 1
                continue
            try:
                by_device[reply.device] = self._complete(reply)
            except (_NoReply, _Garbled):
                by_device[reply.device] = reply
        self._drain()
        return [by_device[d] for d in sorted(by_device)]

    def _drain(self) -> None:
        """Read away what is already waiting (alerts after a stop, replies of extra devices)."""
        try:
            for _ in range(256):
                if not self._port.in_waiting:
                    break
                self._port.readline()
        except (serial.SerialException, OSError, AttributeError, NotImplementedError):
            pass

    def _checked(self, reply: Reply, command: str, check: bool) -> Reply:
        if reply.flag == "RJ" and check:
            reason = reply.data.split()[0] if reply.data else "?"
            meaning = REJECT_MEANINGS.get(reason, "unknown reason")
            raise RejectedError(f"Zaber device {reply.device} axis {reply.axis} rejected {command!r}: "
                                f"{reason} ({meaning})", reason)
        w = reply.warning
        if w != "--":
            if w[0] == "F" and check:
                flags = self.flags(reply.device)
                faults = [f for f in flags if f.startswith("F")] or [w]
                text = "; ".join(f"{f} {FLAG_MEANINGS.get(f, 'fault')}" for f in faults)
                raise FaultError(f"Zaber device {reply.device} reports a fault: {text}; clear the cause, "
                                 "then run the session again with --resume", tuple(faults))
            if w[0] in "WN" and (reply.device, w) not in self.warnings_seen:
                self.warnings_seen.append((reply.device, w))
                if self.on_warning is not None:
                    self.on_warning(reply.device, w, FLAG_MEANINGS.get(w, "warning"))
        return reply

    # -- helpers ---------------------------------------------------------------------------
    def identify(self, device: int) -> dict:
        """Device id, serial, firmware, build, axes and peripheral ids of one device on the chain
        (`gonio.bench.drivers.identify.zaber_device`: what a device does not answer is None)."""
        return zaber_device(self, device)

    def flags(self, device: int) -> list[str]:
        """All active warning flags of ``device`` (``/D 0 warnings``)."""
        reply = self.request(device, 0, "warnings", check=False)
        tok = reply.data.split()
        return tok[1:] if tok and tok[0].isdigit() else tok

    def clear_flags(self, device: int) -> None:
        """Clear the device's clearable warning flags."""
        self.request(device, 0, "warnings clear", check=False)

    def get(self, device: int, axis: int, setting: str) -> list[float]:
        """``get <setting>``: one value, or one per axis for axis 0."""
        return self.request(device, axis, f"get {setting}").values

    def set(self, device: int, axis: int, setting: str, value) -> None:
        """``set <setting> <value>``."""
        self.request(device, axis, f"set {setting} {value}")

    # -- alerts ------------------------------------------------------------------------------
    def _note_alert(self, line: bytes) -> None:
        """Remember that ``line``, if an alert ``!DD A ...`` of an alerting device, came."""
        if line[:1] != b"!":
            return
        head = line[1:4].split(b" ")[0]
        if head.isdigit() and int(head) in self.alerting:
            self._alerted.add(int(head))

    def enable_alerts(self, device: int) -> bool:
        """``set comm.alert 1``: the device then sends ``!DD A IDLE WARN`` when a motion of an
        axis ends, which `wait_idle` waits for. False (the device is polled) where it rejects it
        or does not answer. The value the device had (``get comm.alert``) is given back by
        `close`."""
        try:
            before = self.request(device, 0, "get comm.alert", check=False)
            reply = self.request(device, 0, "set comm.alert 1", check=False)
        except CommunicationError:
            reply = None
        if reply is not None and reply.ok:
            self.alerting.add(device)
            was = before.data.strip() if before.ok else "0"
            if was != "1" and device not in self._restore:
                self._restore[device] = "0"
        else:
            self.alerting.discard(device)
        return device in self.alerting

    #: With alerts on, the port is read for an alert in windows this long, with a safe point
    #: (``sleep(0)``: a stop asked for is acted on) between them.
    ALERT_WINDOW_S = 0.1

    def _await_alert(self, device: int, patience: float, sleep: Callable[[float], None]) -> tuple[bool, float]:
        """Read until an alert of ``device`` comes: ``(True, seconds silent)``; ``(False, seconds
        silent)`` once the port was silent for ``patience`` (counted in read windows, not wall
        time). Other lines (late replies, info lines, other devices' alerts) are skipped; a line
        cut by a window's end is kept and completed by the next read."""
        if device in self._alerted:              # read meanwhile, between other replies
            return True, 0.0
        port = self._port
        window = max(1e-3, min(self.ALERT_WINDOW_S, patience))
        try:
            old, port.timeout = port.timeout, window
        except (serial.SerialException, OSError, ValueError, AttributeError):
            return False, patience               # poll instead
        silent = 0.0
        try:
            for _ in range(64 + math.ceil(patience / window)):
                try:
                    line = self._readline(keep_partial=True)
                except _NoReply:
                    silent += window
                    if silent >= patience - 1e-9:
                        return False, silent
                    sleep(0)                      # a safe point between windows
                    continue
                self._note_alert(line)
                if device in self._alerted:
                    return True, silent
            return False, silent
        finally:
            try:
                port.timeout = old
            except (serial.SerialException, OSError, ValueError):
                pass        # the port is gone (unplugged mid-wait): the error that follows says so, not this

    def wait_idle(self, device: int, timeout_s: float = 120.0, poll_interval_s: float = 0.05,
                  sleep: Callable[[float], None] = time.sleep) -> Reply:
        """Poll ``/D 0`` until IDLE; on an alerting device (`enable_alerts`) poll once, then when
        its alerts say an axis's motion ended, or after the port was silent for its timeout.

        The budget is counted in polls (``timeout_s / poll_interval_s``) rather than in wall
        time, so it is the same whether ``sleep`` really sleeps or a simulated clock advances;
        with alerts each poll counts one poll interval and each silent read window its length.

        Raises
        ------
        CommunicationError
            Still BUSY after the budget.
        """
        if device in self.alerting:
            left = timeout_s
            while True:
                reply = self.request(device, 0)
                if not reply.busy:
                    return reply
                self._alerted.discard(device)    # this BUSY is newer than any alert read so far
                if left <= 1e-9:
                    break
                came, silent = self._await_alert(device, min(left, max(self.timeout, poll_interval_s)), sleep)
                left -= silent + poll_interval_s     # (a device that only sends other lines is bounded too)
                sleep(0)                          # a safe point before the next poll
            raise CommunicationError(f"Zaber device {device} still moving after {timeout_s:g} s; "
                                     "check for a jammed stage, then resume the session")
        n = max(1, math.ceil(timeout_s / poll_interval_s))
        for _ in range(n):
            reply = self.request(device, 0)
            if not reply.busy:
                return reply
            sleep(poll_interval_s)
        raise CommunicationError(f"Zaber device {device} still moving after {timeout_s:g} s; "
                                 "check for a jammed stage, then resume the session")


def emergency_stop(port_url: str, baudrate: int = 115200, n_devices: int = 2) -> int:
    """Send the emergency stop to every device on the chain at once (``/0 0 estop``).

    Bypasses everything else: no retries, no checks, a fresh port. Returns the number of
    devices that answered (a stop is sent whether or not they do).
    """
    chain = ZaberChain(port_url, baudrate, timeout=0.5, retries=0)
    try:
        return len(chain.broadcast("estop", n_devices))
    finally:
        chain.close()
