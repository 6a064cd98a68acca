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
            # how many settings one ``get`` reads is per firmware; 12 is what Zaber's own
            # zaber-motion end-to-end tests give an X-MCC4 on firmware 7.38
            return str(self.GET_SETTINGS_MAX)
        if key == "system.access":
            return "1"          # normal user access (value invented: the manual lists levels 1, 2)
        return str(self.number)     # comm.address

    def axes_of(self, axis: int) -> list[int]:
        return list(range(1, self.axis_count() + 1)) if axis == 0 else [axis]

    #: Most settings one ``get`` reads (``get.settings.max``; see :meth:`get_many`).
    GET_SETTINGS_MAX = 12

    def handle(self, cmd: Command) -> str:
        w = cmd.words
        if not w:
            return "0"
        if w[0] == "get":
            return self.get_many(cmd, w[1:])
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

    def get_many(self, cmd: Command, words: list) -> str:
        """``get`` of one or several settings (Zaber ASCII manual, ``get``; zaber-motion's
        ``get_many``/``get_synchronized`` on the wire).

        ``get S1 S2 ...`` reads each setting, on the addressed axis or, on axis 0, on every axis
        (a device setting: one value). On axis 0 a run of axis numbers reads the settings after
        it on those axes only, until the next run: zaber-motion 10.3 sends
        ``/1 0 get 1 maxspeed pos`` for one axis's ``get_many`` and ``/1 0 get pos 1 2 maxspeed``
        for ``pos`` of every axis and ``maxspeed`` of axes 1 and 2. The reply's data are the
        values in the order asked, setting by setting, axis by axis within a setting, the
        settings separated by ``;`` (zaber-motion 10.3 splits a multi-get reply at ``;`` and trims
        the spaces: ``@01 0 06 OK IDLE -- 30342 ; 91001``; one word of its own is the simulator's
        choice, so a continued reply never splits inside a separator). At most
        :data:`GET_SETTINGS_MAX` settings (``get.settings.max``), else ``BADDATA``; an axis number
        on an axis-scope ``get``, or one with no setting after it, ``BADCOMMAND``; axis 0 or one
        beyond ``system.axiscount`` in a run, ``BADAXIS``; a device setting after a run,
        ``DEVICEONLY``."""
        if not words:
            raise Reject("BADCOMMAND")
        groups: list[tuple[list | None, list]] = []      # (axes of the run or None, settings)
        axes, keys = None, []
        for tok in words:
            if tok.isdigit():
                if cmd.axis != 0:
                    raise Reject("BADCOMMAND")
                if keys or axes is None:
                    if keys:
                        groups.append((axes, keys))
                    axes, keys = [], []
                n = int(tok)
                if not 1 <= n <= self.axis_count():
                    raise Reject("BADAXIS")
                axes.append(n)
            else:
                keys.append(tok)
        if axes is not None and not keys:
            raise Reject("BADCOMMAND")
        groups.append((axes, keys))
        if sum(len(k) for _, k in groups) > self.GET_SETTINGS_MAX:
            raise Reject("BADDATA")
        return " ; ".join(" ".join(self._values(cmd, key, axes)) for axes, keys in groups for key in keys)

    def _values(self, cmd: Command, key: str, axes: list | None) -> list[str]:
        """The values of one setting: on ``axes`` (a run of axis numbers), else on the command's
        scope (axis 0: every axis; a device setting: its one value)."""
        if key in self._DEVICE_GET:
            if cmd.axis != 0 or axes is not None:
                raise Reject("DEVICEONLY")
            return [self.device_get(key)]
        return [self.get_axis(key, a) for a in (axes if axes is not None else self.axes_of(cmd.axis))]
