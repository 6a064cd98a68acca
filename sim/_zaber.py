"""Zaber ASCII protocol server for the simulated daisy chain (grammar: shared/notes/protocols.md).

Device 1 is a rotary controller whose axes are ``RotaryAxis`` objects (``_stages.py``);
device 2 is the LED source (``_lamp.py``). This module only parses and formats; the physics
stays in those modules.

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
- LED (device 2): ``lamp on|off``, ``set lamp.flux F`` (0..1), ``get lamp.flux`` (3
  decimals), ``get lamp.temperature`` (deg C, 1 decimal), ``get lamp.status`` (0/1).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ZaberChain", "lrc", "FLAG_PRIORITY"]

#: Warning flags, highest priority first (faults, warnings, notices).
FLAG_PRIORITY = ["FS", "FQ", "FH", "FE", "FD", "WL", "WR", "WH", "WS", "WM", "WT", "WV",
                 "NI", "NC", "NR", "NU"]
_MOTION = {"move", "home"}


def lrc(text: str) -> int:
    """Zaber LRC: two's complement of the byte sum mod 256 of ``text``."""
    return (-sum(text.encode("ascii", "replace"))) & 0xFF


def _sort_flags(flags) -> list[str]:
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


class _Reject(Exception):
    def __init__(self, reason: str):
        self.reason = reason


def _int_arg(words, i) -> int:
    try:
        s = words[i]
    except IndexError:
        raise _Reject("BADDATA") from None
    try:
        return int(s)
    except ValueError:
        raise _Reject("BADDATA") from None


class ZaberChain:
    """Zaber ASCII server of the instrument's daisy chain.

    Parameters
    ----------
    instrument : Instrument
        Owner of the clock, the stage axes (device 1) and the lamp (device 2).
    """

    STAGE_DEVICE = 1
    LED_DEVICE = 2

    def __init__(self, instrument):
        self.inst = instrument
        self.checksum = {self.STAGE_DEVICE: 0, self.LED_DEVICE: 0}
        self.armed_halts: list = []     # [(axis index or None, fraction, flag)] from faults

    # ------------------------------------------------------------------ helpers
    @property
    def axes(self):
        return self.inst.axes

    def _now(self) -> float:
        return self.inst.clock.now()

    def _scope(self, device: int, axis: int) -> list:
        """Axis objects a command addresses (device 1)."""
        return list(self.axes) if axis == 0 else [self.axes[axis - 1]]

    def _status(self, device: int, axis: int) -> tuple[str, str, list]:
        t = self._now()
        if device == self.LED_DEVICE:
            return "IDLE", "--", []
        scope = self._scope(device, axis if axis <= len(self.axes) else 0)
        busy = any(a.busy(t) for a in scope)
        flags = set()
        for a in scope:
            flags |= a.active_flags(t)
        flags = _sort_flags(flags)
        return ("BUSY" if busy else "IDLE"), (flags[0] if flags else "--"), flags

    def format(self, device: int, axis: int, msgid, ok: bool, data: str) -> str:
        """One reply line (no terminator)."""
        status, warn, _ = self._status(device, axis)
        mid = f" {msgid:02d}" if msgid is not None else ""
        body = f"{device:02d} {axis}{mid} {'OK' if ok else 'RJ'} {status} {warn} {data}"
        if self.checksum.get(device):
            body += f":{lrc(body):02X}"
        return "@" + body

    def devices(self, cmd: Command) -> list[int]:
        if cmd.device == 0:
            return [self.STAGE_DEVICE, self.LED_DEVICE]
        if cmd.device in (self.STAGE_DEVICE, self.LED_DEVICE):
            return [cmd.device]
        return []

    def axis_count(self, device: int) -> int:
        return len(self.axes) if device == self.STAGE_DEVICE else 1

    # ------------------------------------------------------------------ entry points
    def handle(self, text: str) -> list[str]:
        """Execute one command line; return the reply lines (no terminators)."""
        cmd = parse(text)
        if cmd is None:
            return []
        replies = []
        for dev in self.devices(cmd):
            try:
                if cmd.error:
                    raise _Reject(cmd.error)
                if cmd.axis > self.axis_count(dev):
                    raise _Reject("BADAXIS")
                if dev == self.STAGE_DEVICE:
                    data = self._stage(cmd)
                else:
                    data = self._led(cmd)
                replies.append(self.format(dev, cmd.axis, cmd.msgid, True, data))
            except _Reject as rj:
                replies.append(self.format(dev, cmd.axis, cmd.msgid, False, rj.reason))
        self._jump(cmd, replies)
        return replies

    def again(self, text: str) -> list[str]:
        """Reply ``RJ ... AGAIN`` to a command without executing it (fault injection)."""
        cmd = parse(text)
        if cmd is None:
            return []
        return [self.format(d, cmd.axis, cmd.msgid, False, "AGAIN") for d in self.devices(cmd)]

    def _jump(self, cmd: Command, replies: list[str]) -> None:
        """Instant clock: a BUSY reply to a poll, ``get`` or ``warnings`` skips to the motion's end."""
        clock = self.inst.clock
        if not (clock.instant and clock.jump_on_busy):
            return
        if cmd.words and cmd.words[0] not in ("get", "warnings"):
            return
        if cmd.axis > len(self.axes) or not any(" BUSY " in r for r in replies):
            return
        t = self._now()
        ends = [e for e in (a.end_time(t) for a in self._scope(1, cmd.axis)) if e is not None]
        if ends:
            clock.advance_to(max(ends))

    # ------------------------------------------------------------------ device 1
    def _stage(self, cmd: Command) -> str:
        w = cmd.words
        t = self._now()
        if not w:
            return "0"
        op = w[0]
        if op == "home":
            if len(w) != 1:
                raise _Reject("BADCOMMAND")
            for a in self._scope(1, cmd.axis):
                a.home(t)
                self._arm(a, t)
            return "0"
        if op == "move":
            if len(w) < 2 or w[1] not in ("abs", "rel", "min", "max"):
                raise _Reject("BADCOMMAND")
            scope = self._scope(1, cmd.axis)
            if w[1] in ("abs", "rel"):
                if len(w) != 3:
                    raise _Reject("BADDATA")
                n = _int_arg(w, 2)
            elif len(w) != 2:
                raise _Reject("BADDATA")
            if any(not a.homed for a in scope):
                raise _Reject("BADDATA")
            targets = []
            for a in scope:
                if w[1] == "abs":
                    tgt = n
                elif w[1] == "rel":
                    tgt = a.position(t) + n
                elif w[1] == "min":
                    tgt = a.limit_min
                else:
                    tgt = a.limit_max
                if not a.in_limits(tgt):
                    raise _Reject("BADDATA")
                targets.append(tgt)
            for a, tgt in zip(scope, targets):
                a.move_abs(t, tgt)
                self._arm(a, t)
            return "0"
        if op in ("stop", "estop"):
            if len(w) != 1:
                raise _Reject("BADCOMMAND")
            for a in self._scope(1, cmd.axis):
                (a.stop if op == "stop" else a.estop)(t)
            return "0"
        if op == "warnings":
            return self._warnings(cmd, w)
        if op == "get":
            if len(w) != 2:
                raise _Reject("BADCOMMAND")
            return self._get_stage(cmd, w[1], t)
        if op == "set":
            if len(w) != 3:
                raise _Reject("BADCOMMAND" if len(w) < 2 else "BADDATA")
            return self._set_stage(cmd, w[1], w[2], t)
        raise _Reject("BADCOMMAND")

    def _arm(self, axis_obj, t: float) -> None:
        """Apply an armed stall/limit fault to the motion that just started."""
        if not self.armed_halts:
            return
        idx = self.axes.index(axis_obj) + 1
        for k, (ax, fraction, flag) in enumerate(self.armed_halts):
            end = axis_obj.end_time(t)
            if (ax is None or ax == idx) and end is not None:
                axis_obj.schedule_halt(t + fraction * (end - t), flag)
                del self.armed_halts[k]
                return

    def _warnings(self, cmd: Command, w) -> str:
        if len(w) == 1:
            clear = False
        elif len(w) == 2 and w[1] == "clear":
            clear = True
        else:
            raise _Reject("BADCOMMAND")
        _, _, flags = self._status(1, cmd.axis)
        if clear:
            for a in self._scope(1, cmd.axis):
                a.flags.clear()
        return " ".join([f"{len(flags):02d}"] + flags)

    _AXIS_SETTINGS = {"pos", "limit.min", "limit.max", "limit.cycle.dist", "maxspeed", "accel"}

    def _get_stage(self, cmd: Command, key: str, t: float) -> str:
        if key == "system.axiscount":
            if cmd.axis != 0:
                raise _Reject("DEVICEONLY")
            return str(len(self.axes))
        if key == "comm.checksum":
            if cmd.axis != 0:
                raise _Reject("DEVICEONLY")
            return str(self.checksum[1])
        if key not in self._AXIS_SETTINGS:
            raise _Reject("BADCOMMAND")
        vals = []
        for a in self._scope(1, cmd.axis):
            if key == "pos":
                vals.append(a.position(t))
            elif key == "limit.min":
                vals.append(a.limit_min)
            elif key == "limit.max":
                vals.append(a.limit_max)
            elif key == "limit.cycle.dist":
                vals.append(a.cycle_dist)
            elif key == "maxspeed":
                vals.append(a.maxspeed)
            else:
                vals.append(a.accel)
        return " ".join(str(int(v)) for v in vals)

    def _set_stage(self, cmd: Command, key: str, value: str, t: float) -> str:
        if key == "comm.checksum":
            if cmd.axis != 0:
                raise _Reject("DEVICEONLY")
            if value not in ("0", "1"):
                raise _Reject("BADDATA")
            self.checksum[1] = int(value)
            return "0"
        if key == "system.axiscount" or key == "pos":
            raise _Reject("BADCOMMAND")
        if key not in self._AXIS_SETTINGS:
            raise _Reject("BADCOMMAND")
        try:
            v = int(value)
        except ValueError:
            raise _Reject("BADDATA") from None
        scope = self._scope(1, cmd.axis)
        if any(a.busy(t) for a in scope):
            raise _Reject("STATUSBUSY")
        for a in scope:
            if key in ("maxspeed", "accel", "limit.cycle.dist") and v <= 0:
                raise _Reject("BADDATA")
            if key == "limit.min" and v > a.limit_max:
                raise _Reject("BADDATA")
            if key == "limit.max" and v < a.limit_min:
                raise _Reject("BADDATA")
        attr = {"limit.min": "limit_min", "limit.max": "limit_max",
                "limit.cycle.dist": "cycle_dist", "maxspeed": "maxspeed", "accel": "accel"}[key]
        for a in scope:
            setattr(a, attr, v)
        return "0"

    # ------------------------------------------------------------------ device 2
    def _led(self, cmd: Command) -> str:
        w = cmd.words
        t = self._now()
        lamp = self.inst.lamp
        if not w:
            return "0"
        op = w[0]
        if op in ("stop", "estop") and len(w) == 1:
            return "0"
        if op == "warnings":
            if w[1:] not in ([], ["clear"]):
                raise _Reject("BADCOMMAND")
            return "00"
        device_only = {"lamp", "set", "get"}
        if op in device_only and cmd.axis != 0 and not (op == "get" and w[1:2] == ["system.axiscount"]):
            if op == "lamp" or (len(w) > 1 and w[1].startswith("lamp.")):
                raise _Reject("DEVICEONLY")
        if op == "lamp":
            if len(w) != 2 or w[1] not in ("on", "off"):
                raise _Reject("BADDATA" if len(w) == 2 else "BADCOMMAND")
            lamp.switch(t, w[1] == "on")
            return "0"
        if op == "get" and len(w) == 2:
            key = w[1]
            if key == "lamp.flux":
                return f"{lamp.flux:.3f}"
            if key == "lamp.temperature":
                return f"{lamp.temperature(t):.1f}"
            if key == "lamp.status":
                return "1" if lamp.on else "0"
            if key == "system.axiscount":
                return "1"
            if key == "comm.checksum":
                return str(self.checksum[2])
            raise _Reject("BADCOMMAND")
        if op == "set" and len(w) == 3:
            key, value = w[1], w[2]
            if key == "lamp.flux":
                try:
                    f = float(value)
                except ValueError:
                    raise _Reject("BADDATA") from None
                if not 0.0 <= f <= 1.0:
                    raise _Reject("BADDATA")
                lamp.set_flux(t, f)
                return "0"
            if key == "comm.checksum":
                if value not in ("0", "1"):
                    raise _Reject("BADDATA")
                self.checksum[2] = int(value)
                return "0"
            if key in ("lamp.temperature", "lamp.status", "system.axiscount"):
                raise _Reject("BADCOMMAND")
            raise _Reject("BADCOMMAND")
        raise _Reject("BADCOMMAND")
