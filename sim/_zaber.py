"""Zaber ASCII protocol server for the simulated daisy chain (grammar: shared/notes/protocols.md).

Device 1 is a rotary controller whose axes are ``RotaryAxis`` objects (``_stages.py``,
commands in ``_zaber_stage.py``); device 2 is the LED source (``_lamp.py``, commands in
``_zaber_led.py``). This module parses, frames and formats; identification and the ``comm.*``
settings every device shares live here too (``Device``).

Sources: Zaber's ASCII protocol manual (message format, reply/info/alert line types, message
ids, ``:CC`` checksums, message continuation, rejection reasons and warning flags) and what
zaber-motion 10.3 sends (observed on the wire: ``/0 0 00``, then per device
``get comm.packet.size.max``, ``get deviceid``, ``get version``, ... before anything else).

Behaviour chosen where the manual leaves room (the bench relies on it):

- Before an axis is homed (power-on, power cycle) it carries ``WR`` and ``WH`` and any
  ``move`` that involves it is rejected: ``RJ IDLE WR BADDATA``. ``home`` clears both.
- ``move abs``/``move rel`` beyond ``limit.min``/``limit.max`` -> ``RJ ... BADDATA``.
  On axis 0 a move applies to every axis.
- A move sent while the axis moves replaces the running one (flag ``NI``); ``stop``
  decelerates, ``estop`` halts at once, both latch ``NI``; ``warnings clear`` clears latched
  flags (NI, FS, WL), never WR/WH. A new move started from rest clears NI.
- ``set`` on a moving axis -> ``RJ ... STATUSBUSY``. Unknown command or setting, or a
  read-only setting -> ``BADCOMMAND``; device-only command or setting with an axis ->
  ``DEVICEONLY``; axis beyond ``system.axiscount`` -> ``BADAXIS``; message id > 99 ->
  ``BADMESSAGEID``; a bad ``:CC`` checksum -> ``BADDATA`` (nothing executed).
- Message ids are echoed as two digits (``@01 1 07 OK ...``).
- Replies carry a checksum only when ``comm.checksum`` is 1 (device setting, default 0).
- ``maxspeed`` in microsteps/s, ``accel`` in microsteps/s^2 (not Zaber's native units).
- Alerts (``set comm.alert 1``): when an axis's motion ends the device sends
  ``!DD A IDLE WARN`` (manual: alert message type ``!``, fields device, axis, status,
  warning flag); the simulator sends one per axis that moved, after the reply of the command
  during which it ended, or from the pty server's loop in real time.
- Continuation (manual, "message continuation"): a reply longer than ``packet_size_max``
  characters ends in ``\\`` right after its last data word and its data goes on in
  ``#DD A [ID] cont ...`` lines (further ones end in ``\\`` too). No space before the
  backslash: zaber-motion 10.3 joins the parts with one space after dropping the backslash
  (observed: ``176000 \\`` came out as ``176000  360000``). The manual does not say how a
  checksum combines with the marker: the simulator puts ``:CC`` after it (invented), over
  the text between the leading ``@``/``#`` and the colon.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ZaberChain", "Device", "lrc", "FLAG_PRIORITY", "Reject"]

#: Warning flags, highest priority first (faults, warnings, notices).
FLAG_PRIORITY = ["FS", "FQ", "FH", "FE", "FD", "WL", "WR", "WH", "WS", "WM", "WT", "WV",
                 "NI", "NC", "NR", "NU"]

#: Longest reply line (characters, without ``:CC`` and terminator) before it continues.
#: zaber-motion reads ``comm.packet.size.max`` first; real controllers report values of this
#: order; 80 is the simulator's choice (invented: the manual gives no default).
PACKET_SIZE_MAX = 80


def lrc(text: str) -> int:
    """Zaber LRC: two's complement of the byte sum mod 256 of ``text``."""
    return (-sum(text.encode("ascii", "replace"))) & 0xFF


def sort_flags(flags) -> list[str]:
    order = {f: i for i, f in enumerate(FLAG_PRIORITY)}
    return sorted(set(flags), key=lambda f: (order.get(f, 99), f))


@dataclass
class Command:
    device: int
    axis: int
    msgid: int | None
    words: list
    error: str | None = None


def parse(text: str) -> Command | None:
    """Parse a command line (without terminator); None if it is not a command."""
    text = text.strip()
    if not text.startswith("/"):
        return None
    body = text[1:]
    err = None
    if ":" in body:
        body, cc = body.rsplit(":", 1)
        try:
            ok = len(cc) == 2 and (sum(body.encode("ascii", "replace")) + int(cc, 16)) % 256 == 0
        except ValueError:
            ok = False
        if not ok:
            err = "BADDATA"
    toks = body.split()
    nums = []
    while toks and len(nums) < 3 and toks[0].isdigit():
        nums.append(int(toks.pop(0)))
    device = nums[0] if nums else 0
    axis = nums[1] if len(nums) > 1 else 0
    msgid = nums[2] if len(nums) > 2 else None
    if msgid is not None and msgid > 99:
        err = err or "BADMESSAGEID"
        msgid = None
    return Command(device, axis, msgid, [t.lower() for t in toks], err)


class Reject(Exception):
    """The device answers ``RJ`` with ``reason`` (one of the manual's rejection reasons)."""

    def __init__(self, reason: str):
        self.reason = reason


def int_arg(words, i) -> int:
    try:
        return int(words[i])
    except (IndexError, ValueError):
        raise Reject("BADDATA") from None


class Device:
    """One device on the chain: identification and the ``comm.*``/``system.*`` settings.

    Subclasses implement ``axis_count``, ``status``, ``command`` (motion and the like) and
    the per-axis settings (``get_axis``/``set_axis``).

    Parameters
    ----------
    chain : ZaberChain
    number : int
        Device address.
    ident : dict
        ``deviceid``, ``system.serial``, ``version``, ``version.build`` (device settings) and
        ``peripheralid`` (per axis).
    """

    def __init__(self, chain, number: int, ident: dict):
        self.chain = chain
        self.number = number
        self.ident = dict(ident)
        self.checksum = 0
        self.alert = 0

    @property
    def inst(self):
        return self.chain.inst

    def now(self) -> float:
        return self.inst.clock.now()

    # -- to override ---------------------------------------------------------------------
    def axis_count(self) -> int:
        raise NotImplementedError

    def status(self, axis: int) -> tuple[str, list]:
        """``("BUSY"|"IDLE", sorted active flags)`` of an axis (0: the whole device)."""
        return "IDLE", []

    def command(self, cmd: Command) -> str:
        raise Reject("BADCOMMAND")

    def get_axis(self, key: str, axis: int) -> str:
        """One axis's value of a per-axis setting (``Reject("BADCOMMAND")`` if unknown)."""
        if key in ("peripheralid", "peripheral.id"):
            return str(self.ident["peripheralid"])
        raise Reject("BADCOMMAND")

    def set_axis(self, key: str, value: str, axes: list) -> None:
        raise Reject("BADCOMMAND")

    # -- shared ----------------------------------------------------------------------------
    #: Device settings: (name -> attribute or identification key). Read-only unless listed
    #: in ``_WRITABLE``.
    _DEVICE_GET = ("deviceid", "system.serial", "version", "version.build", "system.axiscount",
                   "comm.checksum", "comm.alert", "comm.packet.size.max", "get.settings.max",
                   "system.access", "comm.address")
    _WRITABLE = ("comm.checksum", "comm.alert")

    def device_get(self, key: str) -> str:
        if key in ("deviceid", "system.serial", "version", "version.build"):
            return str(self.ident[key])
        if key == "system.axiscount":
            return str(self.axis_count())
        if key == "comm.checksum":
            return str(self.checksum)
        if key == "comm.alert":
            return str(self.alert)
        if key == "comm.packet.size.max":
            return str(self.chain.packet_size_max)
        if key == "get.settings.max":
            # the manual documents several settings in one ``get``; how many a device takes
            # is per firmware: the simulator takes 6 (invented)
            return "6"
        if key == "system.access":
            return "1"          # normal user access (value invented: the manual lists levels 1, 2)
        return str(self.number)     # comm.address

    def axes_of(self, axis: int) -> list[int]:
        return list(range(1, self.axis_count() + 1)) if axis == 0 else [axis]

    def handle(self, cmd: Command) -> str:
        w = cmd.words
        if not w:
            return "0"
        if w[0] == "get":
            if len(w) < 2 or len(w) - 1 > 6:
                raise Reject("BADCOMMAND" if len(w) < 2 else "BADDATA")
            return " ".join(self._get_one(cmd, key) for key in w[1:])
        if w[0] == "set":
            if len(w) != 3:
                raise Reject("BADCOMMAND" if len(w) < 2 else "BADDATA")
            key, value = w[1], w[2]
            if key in self._DEVICE_GET:
                if key not in self._WRITABLE:
                    raise Reject("BADCOMMAND")
                if cmd.axis != 0:
                    raise Reject("DEVICEONLY")
                if value not in ("0", "1"):
                    raise Reject("BADDATA")
                setattr(self, "checksum" if key == "comm.checksum" else "alert", int(value))
                return "0"
            self.set_axis(key, value, self.axes_of(cmd.axis))
            return "0"
        return self.command(cmd)

    def _get_one(self, cmd: Command, key: str) -> str:
        if key in self._DEVICE_GET:
            if cmd.axis != 0:
                raise Reject("DEVICEONLY")
            return self.device_get(key)
        return " ".join(self.get_axis(key, a) for a in self.axes_of(cmd.axis))


class ZaberChain:
    """Zaber ASCII server of the instrument's daisy chain.

    Parameters
    ----------
    instrument : Instrument
        Owner of the clock, the stage axes (device 1) and the lamp (device 2).

    Attributes
    ----------
    packet_size_max : int
        Longest reply line before it continues (``comm.packet.size.max``).
    """

    STAGE_DEVICE = 1
    LED_DEVICE = 2

    def __init__(self, instrument):
        from ._zaber_led import LedDevice
        from ._zaber_stage import StageDevice

        self.inst = instrument
        self.packet_size_max = PACKET_SIZE_MAX
        self.armed_halts: list = []     # [(axis index or None, fraction, flag)] from faults
        self.stage = StageDevice(self, self.STAGE_DEVICE)
        self.led = LedDevice(self, self.LED_DEVICE)
        self.units = {self.STAGE_DEVICE: self.stage, self.LED_DEVICE: self.led}
        self._pending_alerts: list[str] = []

    # ------------------------------------------------------------------ compatibility
    @property
    def axes(self):
        return self.inst.axes

    @property
    def checksum(self) -> dict:
        """``comm.checksum`` of each device (read-only view)."""
        return {n: d.checksum for n, d in self.units.items()}

    # ------------------------------------------------------------------ formatting
    def _seal(self, device: int, lead: str, body: str) -> str:
        if self.units[device].checksum:
            body += f":{lrc(body):02X}"
        return lead + body

    def format(self, device: int, axis: int, msgid, ok: bool, data: str) -> list[str]:
        """The reply packet(s) of one answer (no terminators): one line, or continued."""
        status, flags = self.units[device].status(axis)
        warn = flags[0] if flags else "--"
        mid = f" {msgid:02d}" if msgid is not None else ""
        head = f"{device:02d} {axis}{mid} {'OK' if ok else 'RJ'} {status} {warn}"
        limit = max(24, int(self.packet_size_max))
        if 1 + len(head) + 1 + len(data) <= limit or " " not in data:
            return [self._seal(device, "@", f"{head} {data}")]
        lines, words = [], data.split(" ")
        lead, prefix = "@", head
        while words:
            body = prefix
            while words and (len(body) + 1 + len(words[0]) + 1 <= limit - 1 or body == prefix):
                body += " " + words.pop(0)
            if words:
                body += "\\"
            lines.append(self._seal(device, lead, body))
            lead, prefix = "#", f"{device:02d} {axis}{mid} cont"
        return lines

    def alert_line(self, device: int, axis: int) -> str:
        status, flags = self.units[device].status(axis)
        return self._seal(device, "!", f"{device:02d} {axis} {status} {flags[0] if flags else '--'}")

    def devices(self, cmd: Command) -> list[int]:
        if cmd.device == 0:
            return [self.STAGE_DEVICE, self.LED_DEVICE]
        if cmd.device in self.units:
            return [cmd.device]
        return []

    def axis_count(self, device: int) -> int:
        return self.units[device].axis_count()

    # ------------------------------------------------------------------ entry points
    def handle(self, text: str) -> list[str]:
        """Execute one command line; return the reply lines (no terminators).

        Alerts that came due before the command come first; alerts of motions that ended
        while it ran (an instant clock's jump) come after its replies.
        """
        cmd = parse(text)
        if cmd is None:
            return []
        out = self.alerts()
        for dev in self.devices(cmd):
            unit = self.units[dev]
            try:
                if cmd.error:
                    raise Reject(cmd.error)
                if cmd.axis > unit.axis_count():
                    raise Reject("BADAXIS")
                data = unit.handle(cmd)
                out += self.format(dev, cmd.axis, cmd.msgid, True, data)
            except Reject as rj:
                out += self.format(dev, cmd.axis, cmd.msgid, False, rj.reason)
        self._jump(cmd, out)
        return out + self.alerts()

    def alerts(self) -> list[str]:
        """Alert lines of motions that ended by now (``comm.alert 1`` devices only)."""
        out = self._pending_alerts
        self._pending_alerts = []
        return out + self.stage.ended_alerts()

    def again(self, text: str) -> list[str]:
        """Reply ``RJ ... AGAIN`` to a command without executing it (fault injection)."""
        cmd = parse(text)
        if cmd is None:
            return []
        out = []
        for d in self.devices(cmd):
            out += self.format(d, cmd.axis, cmd.msgid, False, "AGAIN")
        return out

    def _jump(self, cmd: Command, replies: list[str]) -> None:
        """Instant clock: a BUSY reply to a poll, ``get`` or ``warnings`` skips to the motion's end."""
        clock = self.inst.clock
        if not (clock.instant and clock.jump_on_busy):
            return
        if cmd.words and cmd.words[0] not in ("get", "warnings"):
            return
        if cmd.axis > len(self.axes) or not any(" BUSY " in r for r in replies):
            return
        t = self.inst.clock.now()
        scope = list(self.axes) if cmd.axis == 0 else [self.axes[cmd.axis - 1]]
        ends = [e for e in (a.end_time(t) for a in scope) if e is not None]
        if ends:
            clock.advance_to(max(ends))
