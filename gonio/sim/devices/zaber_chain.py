"""Zaber ASCII protocol server for the simulated daisy chain (grammar: shared/notes/protocols.md).

Device 1 is a rotary controller whose axes are ``RotaryAxis`` objects
(:mod:`gonio.sim.physics.stages`, commands in :mod:`.zaber_stage`); device 2 is the LED source
(:mod:`gonio.sim.physics.lamp`, commands in :mod:`.zaber_led`). This module parses, frames and
formats; identification and the ``comm.*`` settings every device shares are ``Device``
(:mod:`.zaber_common`).

Sources: Zaber's ASCII protocol manual (message format, reply/info/alert line types, message
ids, ``:CC`` checksums, message continuation, rejection reasons and warning flags) and what
zaber-motion 10.3 sends (observed on the wire: ``/0 0 00``, then per device
``get comm.packet.size.max``, ``get deviceid``, ``get version``, ... before anything else).
The behaviour chosen where the manual leaves room, which the bench relies on: the comment below.
"""

# Behaviour chosen where the manual leaves room (the bench relies on it):
# - Before an axis is homed (power-on, power cycle) it carries WR and WH and any move that
#   involves it is rejected: "RJ IDLE WR BADDATA". home clears both.
# - move abs / move rel beyond limit.min / limit.max -> RJ ... BADDATA. On axis 0 a move applies
#   to every axis.
# - A move sent while the axis moves replaces the running one (flag NI); stop decelerates, estop
#   halts at once, both latch NI; "warnings clear" clears latched flags (NI, FS, WL), never
#   WR/WH. A new move started from rest clears NI.
# - set on a moving axis -> RJ ... STATUSBUSY. Unknown command or setting, or a read-only
#   setting -> BADCOMMAND; device-only command or setting with an axis -> DEVICEONLY; axis
#   beyond system.axiscount -> BADAXIS; message id > 99 -> BADMESSAGEID; a bad :CC checksum ->
#   BADDATA (nothing executed).
# - Message ids are echoed as two digits ("@01 1 07 OK ...").
# - Replies carry a checksum only when comm.checksum is 1 (device setting, default 0).
# - maxspeed, move vel and accel in Zaber's native units (microsteps/s * 1.6384,
#   microsteps/s^2 * 1.6384 / 10; zaber_stage).
# - Alerts (set comm.alert 1): when an axis's motion ends the device sends "!DD A IDLE WARN"
#   (manual: alert message type "!", fields device, axis, status, warning flag); the simulator
#   sends one per axis that moved, after the reply of the command during which it ended, or from
#   the pty server's loop in real time.
# - Continuation (manual, "message continuation"): a reply longer than packet_size_max
#   characters ends in "\" right after its last data word and its data goes on in
#   "#DD A [ID] cont ..." lines (further ones end in "\" too). No space before the backslash:
#   zaber-motion 10.3 joins the parts with one space after dropping the backslash (observed:
#   "176000 \" came out as "176000  360000"). The manual does not say how a checksum combines
#   with the marker: the simulator puts :CC after it (invented), over the text between the
#   leading "@"/"#" and the colon.
# - A command line longer than MAX_LINE characters (the port endpoint keeps no more of it) or
#   one holding a control character (C0, DEL, C1) is executed by no device: the devices it
#   addresses (read from its first characters) answer "RJ ... BADDATA" (invented: the manual
#   names no reason for it).

from __future__ import annotations

from gonio.core.preflight import control_character
from gonio.sim.devices.zaber_common import (FLAG_PRIORITY, PACKET_SIZE_MAX, Command, Device, Reject, int_arg, lrc, parse, sort_flags)
from gonio.sim.devices.zaber_led import LedDevice
from gonio.sim.devices.zaber_stage import StageDevice

__all__ = ["ZaberChain", "Device", "lrc", "FLAG_PRIORITY", "Reject", "Command", "parse", "int_arg", "sort_flags"]


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
    #: longest command line (characters, without the terminator) a device reads
    MAX_LINE = 256

    def __init__(self, instrument):
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
        body = text.strip(" \r\n")
        if len(body) > self.MAX_LINE or control_character(body) is not None:
            cmd.error = "BADDATA"                 # nothing executed (see the notes above)
        return self._answer(cmd)

    def overlong(self, text: str) -> list[str]:
        """The answer to a line longer than ``MAX_LINE`` (``text``: its first characters):
        ``RJ ... BADDATA`` from the devices it addresses, nothing executed."""
        cmd = parse(text)
        if cmd is None:
            return []
        cmd.error = "BADDATA"
        return self._answer(cmd)

    def _answer(self, cmd: Command) -> list[str]:
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

    def next_alert_at(self) -> float | None:
        """Simulated time the next alert comes due (a motion of an alerting device ends); None
        when none will (the pty server sleeps until then, so the alert leaves on time)."""
        if self._pending_alerts:
            return self.inst.clock.now()
        return self.stage.next_alert_at()

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
