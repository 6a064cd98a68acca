"""Zaber ASCII pieces shared by the simulated devices: line parsing, LRC checksums, warning
flags, rejections, and ``Device`` (identification and the ``comm.*``/``system.*`` settings
every device has). The chain that frames and routes them is :mod:`gonio.sim.devices.zaber_chain`; the stage and
LED commands are :mod:`gonio.sim.devices.zaber_stage` and :mod:`gonio.sim.devices.zaber_led` (behaviour: :mod:`gonio.sim.devices.zaber_chain`'s
notes).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Command", "Device", "FLAG_PRIORITY", "PACKET_SIZE_MAX", "Reject", "int_arg", "lrc", "parse", "sort_flags"]

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
