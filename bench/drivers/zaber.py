"""Zaber ASCII protocol driver: the stages and the LED source on one daisy chain.

The wire format is that of ``shared/notes/protocols.md``. Only ``serial.serial_for_url`` opens
the port, so a ``sim://NAME/zaber`` URL, a pseudo-terminal path and ``/dev/ttyUSB0`` are the
same to this module.

Layers, bottom up:

* `lrc`, `format_command`, `parse_reply`: pure functions over bytes.
* `ZaberChain`: one port; message ids, checksums, bounded retries on a silent or garbled
  reply, then a reconnect; `RJ` raises `RejectedError`, fault flags raise `FaultError`.
* `Goniometer`: the four rotary axes of device 1 in degrees, soft limits checked before any
  move, shortest-way moves, homing, BUSY polling.
* `LedSource`: device 2, the lamp, one channel an axis, as Zaber's own library drives it.

What real controllers may send besides the reply (Zaber ASCII protocol manual, message
types and "message continuation"; zaber-motion 10.3 on the wire): info lines ``#..`` and
alerts ``!..`` anywhere, before or between replies; a reply whose data ends in ``\\`` goes on
in ``#DD A [ID] cont ...`` lines of the same device, axis and message id; ``NA`` for an axis
that lacks a setting in an axis-0 ``get``. `ZaberChain` skips the first, joins the second
and reads ``NA`` as NaN (`Reply.values`), which the callers refuse by name.

Retries resend the same command. That is safe for every command this module sends (absolute
moves, homing, gets, sets, lamp on/off) and would not be for ``move rel``, which it never sends.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Mapping

import serial

from ._serial import SerialDevice
from ._settings import AXES
from .errors import CommunicationError, DeviceError, FaultError, GonioError, RejectedError, UnreachableError

__all__ = [
    "FLAG_MEANINGS",
    "REJECT_MEANINGS",
    "Reply",
    "lrc",
    "format_command",
    "parse_reply",
    "ZaberChain",
    "Goniometer",
    "MoveError",
    "LedSource",
    "shortest_equivalent",
    "emergency_stop",
]

FLAG_MEANINGS = {
    "FS": "stalled and stopped",
    "FQ": "encoder error",
    "FH": "hardware emergency stop",
    "FE": "limit error",
    "FD": "driver disabled",
    "FT": "excessive temperature, driver shut down",
    "FO": "overdrive limit exceeded",
    "FB": "stream bounds error",
    "FP": "interpolated path deviation",
    "FM": "peripheral inactive",
    "WL": "unexpected limit switch",
    "WR": "no reference position (not homed)",
    "WH": "device not homed",
    "WS": "stalled with recovery",
    "WM": "displaced when stationary",
    "WT": "controller hot",
    "WV": "voltage out of range",
    "NI": "movement interrupted",
    "NC": "manual control",
    "NR": "value rounded",
    "NU": "setting update pending",
}

REJECT_MEANINGS = {
    "BADCOMMAND": "unknown command or setting",
    "BADDATA": "bad or out-of-range value",
    "BADAXIS": "no such axis",
    "BADMESSAGEID": "bad message id",
    "DEVICEONLY": "command must be sent to axis 0",
    "AGAIN": "device busy, send again",
    "PARKED": "axis is parked",
    "STATUSBUSY": "cannot change this while moving",
    "NOACCESS": "insufficient access level",
}


class _NoReply(Exception):
    """No complete line before the port's timeout."""


class _Garbled(Exception):
    """A line arrived but could not be parsed (or its checksum is wrong)."""


def lrc(payload: bytes) -> str:
    """Zaber's longitudinal redundancy check of ``payload``.

    Parameters
    ----------
    payload : bytes
        The bytes after the leading ``/`` (or ``@``) up to, not including, the colon.

    Returns
    -------
    str
        Two upper-case hex digits: the two's complement of ``sum(payload) mod 256``.
    """
    return f"{(-sum(payload)) & 0xFF:02X}"


def format_command(device: int, axis: int, command: str = "", msgid: int | None = None,
                   checksum: bool = False) -> bytes:
    """Encode one command line, e.g. ``b"/1 2 07 move abs 64000:3A\\n"``.

    Parameters
    ----------
    device : int
        Address 0..99 (0: every device).
    axis : int
        0 for the whole device, 1..n for one axis.
    command : str
        Command words and arguments; empty for a plain status poll.
    msgid : int, optional
        Message id 0..99, echoed in the reply.
    checksum : bool
        Append ``:CC`` (LRC).
    """
    body = f"{int(device)} {int(axis)}"
    if msgid is not None:
        body += f" {int(msgid):02d}"
    if command:
        body += f" {command}"
    if checksum:
        body += ":" + lrc(body.encode("ascii"))
    return ("/" + body + "\n").encode("ascii")


@dataclass(frozen=True)
class Reply:
    """A parsed ``@`` reply line.

    Attributes
    ----------
    device, axis : int
    msgid : int or None
    flag : str
        ``"OK"`` or ``"RJ"``.
    status : str
        ``"BUSY"`` or ``"IDLE"``.
    warning : str
        The highest-priority active flag, ``"--"`` if none.
    data : str
        Everything after the warning field (the reason after ``RJ``).
    """

    device: int
    axis: int
    msgid: int | None
    flag: str
    status: str
    warning: str
    data: str

    @property
    def ok(self) -> bool:
        return self.flag == "OK"

    @property
    def busy(self) -> bool:
        return self.status == "BUSY"

    @property
    def continued(self) -> bool:
        """The data goes on in ``cont`` lines (it ends in a backslash)."""
        return self.data.endswith("\\")

    @property
    def values(self) -> list[float]:
        """The data as numbers (one per axis for an axis-0 ``get``); ``NA`` reads as NaN."""
        try:
            return [math.nan if v == "NA" else float(v) for v in self.data.split()]
        except ValueError:
            raise CommunicationError(f"device {self.device} sent non-numeric data {self.data!r}; "
                                     "check that the port talks to a Zaber device") from None


def parse_continuation(line: bytes | str) -> tuple[int, int, int | None, str]:
    """Parse one continuation line ``#DD A [ID] cont DATA[:CC]``: ``(device, axis, msgid, data)``.

    Raises
    ------
    ValueError
        Not a continuation line, or a bad checksum.
    """
    if isinstance(line, bytes):
        line = line.decode("ascii")
    line = line.strip()
    if not line.startswith("#"):
        raise ValueError(f"not a continuation line: {line!r}")
    body = line[1:]
    if len(body) >= 3 and body[-3] == ":":
        body, cc = body[:-3], body[-2:]
        if lrc(body.encode("ascii")) != cc.upper():
            raise ValueError(f"bad checksum in {line!r}")
    tok = body.split(" ")
    if len(tok) < 3 or not (tok[0].isdigit() and tok[1].isdigit()):
        raise ValueError(f"malformed continuation {line!r}")
    msgid = None
    if tok[2].isdigit():
        msgid = int(tok[2])
        tok = tok[:2] + tok[3:]
    if len(tok) < 3 or tok[2] != "cont":
        raise ValueError(f"not a continuation line: {line!r}")
    return int(tok[0]), int(tok[1]), msgid, " ".join(tok[3:])


def parse_reply(line: bytes | str) -> Reply:
    """Parse one reply line ``@DD A [ID] FLAG STATUS WARN DATA[:CC]``.

    Raises
    ------
    ValueError
        The line is not a well-formed reply or its checksum does not match.
    """
    if isinstance(line, bytes):
        line = line.decode("ascii")
    line = line.strip()
    if not line.startswith("@"):
        raise ValueError(f"not a reply line: {line!r}")
    body = line[1:]
    if len(body) >= 3 and body[-3] == ":":
        body, cc = body[:-3], body[-2:]
        if lrc(body.encode("ascii")) != cc.upper():
            raise ValueError(f"bad checksum in {line!r}")
    tok = body.split()
    if len(tok) < 5:
        raise ValueError(f"short reply {line!r}")
    device, axis = int(tok[0]), int(tok[1])
    msgid = None
    if tok[2].isdigit():
        msgid = int(tok[2])
        tok = tok[:2] + tok[3:]
        if len(tok) < 5:
            raise ValueError(f"short reply {line!r}")
    flag, status, warning = tok[2], tok[3], tok[4]
    if flag not in ("OK", "RJ") or status not in ("BUSY", "IDLE") or len(warning) != 2:
        raise ValueError(f"malformed reply {line!r}")
    return Reply(device, axis, msgid, flag, status, warning, " ".join(tok[5:]))


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
        self._msgid = -1
        self.open()

    # -- one exchange --------------------------------------------------------------------
    def _next_msgid(self) -> int:
        self._msgid = (self._msgid + 1) % 100
        return self._msgid

    def _readline(self) -> bytes:
        try:
            line = self._port.readline()
        except (serial.SerialException, OSError) as exc:
            raise _NoReply(str(exc)) from None
        if not line.endswith(b"\n"):
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

    def wait_idle(self, device: int, timeout_s: float = 120.0, poll_interval_s: float = 0.05,
                  sleep: Callable[[float], None] = time.sleep) -> Reply:
        """Poll ``/D 0`` until IDLE.

        The budget is counted in polls (``timeout_s / poll_interval_s``) rather than in wall
        time, so it is the same whether ``sleep`` really sleeps or a simulated clock advances.

        Raises
        ------
        CommunicationError
            Still BUSY after the budget.
        """
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


def shortest_equivalent(target_deg: float, current_deg: float, lo_deg: float, hi_deg: float) -> float:
    """The angle equivalent to ``target_deg`` (mod 360) inside [lo, hi] nearest ``current_deg``.

    Returns ``target_deg`` itself where no other equivalent is inside the limits. On a rotary
    axis whose range spans a full turn this makes every move the shortest way round.
    """
    best = target_deg
    k0 = math.floor((lo_deg - target_deg) / 360.0)
    for k in range(k0, k0 + 4):
        cand = target_deg + 360.0 * k
        if lo_deg - 1e-9 <= cand <= hi_deg + 1e-9:
            if not (lo_deg - 1e-9 <= best <= hi_deg + 1e-9) or abs(cand - current_deg) < abs(best - current_deg):
                best = cand
    return best


@dataclass
class _Axis:
    name: str
    device: int
    axis: int
    lo_deg: float
    hi_deg: float
    cycle_dist: int = 0


class MoveError(DeviceError):
    """An axis stopped short of its goal (stall, unexpected limit switch)."""

    def __init__(self, message: str, flags=()):
        super().__init__(message)
        self.flags = tuple(flags)


class Goniometer:
    """The rotary axes of the gonioreflectometer in degrees (interfaces.md section 3).

    Parameters
    ----------
    chain : ZaberChain
    settings : dict
        Instrument settings (``axes`` table: ``name = [device, axis, min_deg, max_deg]``).
    poll_interval_s : float
        Seconds between BUSY polls.
    sleep : callable
        Called between polls; ``time.sleep`` on hardware.

    Notes
    -----
    ``connect`` reads ``limit.cycle.dist`` (microsteps per revolution) of each axis, so
    degrees = microsteps * 360 / cycle_dist, and narrows the soft limits of the settings to
    the device's own ``limit.min``/``limit.max``.
    """

    POSITION_TOLERANCE_STEPS = 2

    def __init__(self, chain: ZaberChain, settings: Mapping, *, poll_interval_s: float = 0.05,
                 sleep: Callable[[float], None] = time.sleep, move_timeout_s: float = 300.0):
        self.chain = chain
        self.poll_interval_s = poll_interval_s
        self.sleep = sleep
        self.move_timeout_s = move_timeout_s
        self.axes = {}
        for name in AXES:
            dev, ax, lo, hi = settings["axes"][name]
            self.axes[name] = _Axis(name, int(dev), int(ax), float(lo), float(hi))
        self.devices = sorted({a.device for a in self.axes.values()})
        self.connected = False
        self._position: dict[str, float] | None = None   # cache of the last confirmed angles
        self._reconnects_seen = chain.reconnects

    def connect(self, clear_faults: bool = False) -> list[str]:
        """Read flags, cycle distances and limits; return the active flags of the stage devices.

        Parameters
        ----------
        clear_faults : bool
            Clear latched flags first (``warnings clear``: FS after a stall, NI, WL), as a
            resume does once the operator has looked at the cause.

        Raises
        ------
        FaultError
            A fault flag is (still) active.
        """
        active = []
        for dev in self.devices:
            flags = self.chain.flags(dev)
            if clear_faults and any(f[0] in "FNW" and f not in ("WR", "WH") for f in flags):
                self.chain.clear_flags(dev)
                flags = self.chain.flags(dev)
            faults = [f for f in flags if f.startswith("F")]
            if faults:
                text = "; ".join(f"{f} {FLAG_MEANINGS.get(f, 'fault')}" for f in faults)
                raise FaultError(f"Zaber device {dev} reports a fault: {text}; clear the cause, "
                                 "then run the session again with --resume", tuple(faults))
            active += flags
        for dev in self.devices:
            axes = [a for a in self.axes.values() if a.device == dev]
            cyc = self.chain.get(dev, 0, "limit.cycle.dist")
            lo = self.chain.get(dev, 0, "limit.min")
            hi = self.chain.get(dev, 0, "limit.max")
            for a in axes:
                i = a.axis - 1
                if i >= len(cyc) or i >= len(lo) or i >= len(hi):
                    raise GonioError(f"Zaber device {dev} has no axis {a.axis} for {a.name}; "
                                     "check the [axes] table of the settings")
                if not all(math.isfinite(v[i]) for v in (cyc, lo, hi)):
                    raise GonioError(f"Zaber device {dev} axis {a.axis} ({a.name}) answers NA for its "
                                     "limits: no rotary stage there; check the [axes] table of the settings")
                a.cycle_dist = int(cyc[i])
                if a.cycle_dist <= 0:
                    raise GonioError(f"axis {a.name} reports limit.cycle.dist {cyc[i]:g}: not a rotary "
                                     "axis; check the [axes] table of the settings")
                a.lo_deg = max(a.lo_deg, lo[i] * 360.0 / a.cycle_dist)
                a.hi_deg = min(a.hi_deg, hi[i] * 360.0 / a.cycle_dist)
        self.connected = True
        self._position = None
        return active

    def flags(self) -> list[str]:
        """Active flags of all stage devices."""
        out = []
        for dev in self.devices:
            out += self.chain.flags(dev)
        return out

    def needs_homing(self) -> bool:
        """True where a device lost its reference (WR) or was never homed (WH)."""
        return any(f in ("WR", "WH") for f in self.flags())

    def deg_to_steps(self, name: str, deg: float) -> int:
        """Degrees -> integer microsteps on axis ``name``."""
        return int(round(deg * self.axes[name].cycle_dist / 360.0))

    def steps_to_deg(self, name: str, steps: float) -> float:
        """Microsteps -> degrees on axis ``name``."""
        return steps * 360.0 / self.axes[name].cycle_dist

    def positions(self) -> dict[str, float]:
        """Current stage angles in degrees."""
        out = {}
        for dev in self.devices:
            pos = self.chain.get(dev, 0, "pos")
            for a in self.axes.values():
                if a.device == dev:
                    if a.axis > len(pos) or not math.isfinite(pos[a.axis - 1]):
                        raise CommunicationError(f"Zaber device {dev} gave no position for axis {a.axis} "
                                                 f"({a.name}); check the [axes] table and the stage cable")
                    out[a.name] = self.steps_to_deg(a.name, pos[a.axis - 1])
        self._position = dict(out)
        return out

    def check_limits(self, target_deg: Mapping[str, float]) -> None:
        """Raise `UnreachableError` if any target is outside its axis's soft limits."""
        for name, deg in target_deg.items():
            a = self.axes[name]
            if not (math.isfinite(deg) and a.lo_deg - 1e-9 <= deg <= a.hi_deg + 1e-9):
                raise UnreachableError(f"{name} = {deg:.3f} deg is outside its limits "
                                       f"[{a.lo_deg:g}, {a.hi_deg:g}] deg; remove the point from the plan")

    def move_to(self, target_deg: Mapping[str, float], *, wait: bool = True,
                current: Mapping[str, float] | None = None) -> dict[str, float]:
        """Move the named axes to absolute angles (degrees), all at once, the shortest way.

        Every target is checked against the soft limits before any axis moves.

        Returns
        -------
        dict
            The commanded angles (degrees), after choosing the shortest equivalent.
        """
        if not self.connected:
            self.connect()
        if self.chain.reconnects != self._reconnects_seen:   # the port was reopened: re-query
            self._reconnects_seen = self.chain.reconnects
            self._position = None
        if current is None:
            current = self._position if self._position is not None else self.positions()
        goal = {}
        for name, deg in target_deg.items():
            a = self.axes[name]
            deg = float(deg)
            if math.isfinite(deg):
                deg = shortest_equivalent(deg, current.get(name, 0.0), a.lo_deg, a.hi_deg)
            goal[name] = deg
        self.check_limits(goal)
        self._position = None                      # unknown until the move is confirmed
        for name, deg in goal.items():
            a = self.axes[name]
            self.chain.request(a.device, a.axis, f"move abs {self.deg_to_steps(name, deg)}")
        self._moving_from = dict(current)
        if wait:
            self.finish_move(goal)
        return goal

    def finish_move(self, goal: Mapping[str, float]) -> None:
        """Wait for a move (``move_to(..., wait=False)``, which returned ``goal``) to end and verify
        it, as ``move_to`` does: the stages move on their own while the host works meanwhile.

        Raises
        ------
        MoveError
            An axis fell short (a limit switch, a stall).
        """
        self.wait_idle()
        self._verify(goal)
        self._position = {**getattr(self, "_moving_from", {}), **goal}

    def _verify(self, goal: Mapping[str, float]) -> None:
        """Check that every axis reached its goal (a stall or a limit switch stops it short).

        Raises
        ------
        DeviceError
            An axis is more than `POSITION_TOLERANCE_STEPS` microsteps off, with the active flags.
        """
        pos = self.positions()
        off = {n: pos[n] for n, g in goal.items()
               if abs(self.deg_to_steps(n, pos[n]) - self.deg_to_steps(n, g)) > self.POSITION_TOLERANCE_STEPS}
        if off:
            flags = self.flags()
            text = ", ".join(f"{n} at {pos[n]:.3f} deg instead of {goal[n]:.3f}" for n in off)
            why = "; ".join(f"{f} {FLAG_MEANINGS.get(f, '')}".strip() for f in flags) or "no flag"
            raise MoveError(f"move fell short: {text} ({why}); check the stage, then resume the session", flags)

    def wait_idle(self) -> None:
        """Poll every stage device until IDLE (faults raise)."""
        for dev in self.devices:
            self.chain.wait_idle(dev, self.move_timeout_s, self.poll_interval_s, self.sleep)

    def home(self) -> None:
        """Home every axis (``/D 0 home``) and wait; clears WR/WH."""
        self._position = None
        for dev in self.devices:
            self.chain.request(dev, 0, "home")
        self.wait_idle()

    def stop(self) -> None:
        """Decelerate and stop every stage device."""
        self._position = None
        for dev in self.devices:
            self.chain.request(dev, 0, "stop", check=False)


class LedSource:
    """The LED source, a Zaber-protocol device (device 2 by default), driven as zaber-motion's
    Illuminator API drives it (observed with zaber-motion 10.3 on the wire):

    * a channel is an axis: ``/2 1 lamp on``, ``/2 1 get lamp.flux.max``,
      ``/2 1 set lamp.flux F`` with ``F = fraction * lamp.flux.max``;
    * ``off`` is ``/2 0 lamp off``, every channel (the safe stop, as ``Illuminator.turn_off``).

    Parameters
    ----------
    chain : ZaberChain
    device : int
        Address of the LED controller.
    channel : int
        The channel (axis) the LED is on, 1..n.
    """

    def __init__(self, chain: ZaberChain, device: int = 2, channel: int = 1):
        if not (isinstance(channel, int) and 1 <= channel <= 9):
            raise GonioError(f"lamp channel {channel!r} is invalid; fix [lamp] channel (1..9) in the settings")
        self.chain = chain
        self.device = device
        self.channel = channel
        self._flux_max: float | None = None

    def on(self) -> None:
        """Switch the channel on (``/D C lamp on``)."""
        self.chain.request(self.device, self.channel, "lamp on")

    def off(self) -> None:
        """Switch every channel off (``/D 0 lamp off``)."""
        self.chain.request(self.device, 0, "lamp off")

    def flux_max(self) -> float:
        """``lamp.flux.max`` of the channel (read once)."""
        if self._flux_max is None:
            v = self.chain.get(self.device, self.channel, "lamp.flux.max")
            if len(v) != 1 or not (math.isfinite(v[0]) and v[0] > 0):
                raise DeviceError(f"Zaber device {self.device} channel {self.channel} reports lamp.flux.max "
                                  f"{v!r}; check that [lamp] device and channel name an LED")
            self._flux_max = v[0]
        return self._flux_max

    def set_flux(self, flux: float) -> None:
        """Set the flux as a fraction (0..1) of the channel's ``lamp.flux.max``."""
        if not (isinstance(flux, (int, float)) and math.isfinite(flux) and 0.0 <= flux <= 1.0):
            raise GonioError(f"lamp flux {flux!r} is outside [0, 1]; fix [lamp] flux in the settings")
        self.chain.set(self.device, self.channel, "lamp.flux", f"{flux * self.flux_max():.6g}")

    def temperature(self) -> float:
        """LED temperature (degrees Celsius)."""
        v = self.chain.get(self.device, self.channel, "lamp.temperature")
        if not v or not math.isfinite(v[0]):
            raise DeviceError(f"Zaber device {self.device} channel {self.channel} gives no lamp.temperature")
        return v[0]
