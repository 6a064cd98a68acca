"""Seeded fault schedules (TOML) for the simulated instrument.

A schedule is a list of ``[[fault]]`` tables (every key and kind: the comment below)::

    seed = 7                  # optional; default: the instrument seed
    [[fault]]
    kind = "timeout"          # see KINDS
    port = "zaber"            # whose command counter triggers it (zaber | meter | camera)
    at_command = 5            # the n-th command line on that port (1-based), or a list

Kinds: ``timeout``, ``silence``, ``garble``, ``truncate``, ``bad_checksum``, ``again``,
``stall``, ``limit``, ``power_cycle``, ``vanish``, ``camera_nothing``, ``camera_truncated``,
``lamp_dies``. Random choices (probability triggers, garble positions, truncation length) come
from ``default_rng([seed, 0xFA17, fault index, command number])``: the same seed and schedule
give the same bytes.
"""

# The other keys of a [[fault]] table:
#     # at_time = 12.5          # or: the first command (any port) at or after this time, s
#     # probability = 0.01      # or: each command on ``port`` with this probability (seeded)
#     duration = 2.0            # silence, vanish: simulated seconds
#     axis = 2                  # stall, limit: axis of device 1 (default: the next moving one)
#     fraction = 0.5            # stall, limit: stop after this fraction of the move's duration
#     execute = false           # timeout: whether the command whose reply is lost took effect
#     device = 1                # power_cycle: 1 (stages) or 2 (LED)
#
# How each kind shows on the wire:
# timeout           the command gets no reply (and has no effect unless execute)
# silence           every line received for duration s is ignored, no replies
# garble            the reply has some characters replaced (terminator kept)
# truncate          the reply is cut short, without its terminator
# bad_checksum      (zaber) the reply ends with a wrong :CC
# again             (zaber) RJ <status> <warn> AGAIN, command not executed
# stall             (zaber) the next move stops part-way: BUSY, then IDLE with FS
# limit             (zaber) same with WL (unexpected limit switch)
# power_cycle       device 1: positions lost (counter reads 0), WR/WH, moves rejected until
#                   home; device 2: lamp off, flux 1
# vanish            the port raises SerialException (sim://) or disappears (pty) for duration
#                   s, then can be opened again; open handles stay dead
# camera_nothing    EXPOSE replies OK <sha> but writes no file
# camera_truncated  EXPOSE writes half the file, replies the full file's sha
# lamp_dies         the LED emits nothing from then on (the controller still says on)

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from gonio.core.devices import PORT_NAMES

__all__ = ["Fault", "FaultSchedule", "KINDS"]

KINDS = {
    "timeout", "silence", "garble", "truncate", "bad_checksum", "again", "stall", "limit",
    "power_cycle", "vanish", "camera_nothing", "camera_truncated", "lamp_dies",
}
_ZABER_ONLY = {"bad_checksum", "again", "stall", "limit", "power_cycle"}
_LINE_KINDS = {"timeout", "garble", "truncate", "bad_checksum", "again"}


@dataclass
class Fault:
    """One scheduled fault (fields as in the TOML table)."""

    kind: str
    index: int
    port: str = "zaber"
    at_command: tuple = ()
    at_time: float | None = None
    probability: float | None = None
    duration: float = 1.0
    axis: int | None = None
    fraction: float = 0.5
    execute: bool = False
    device: int = 1
    fired: set = field(default_factory=set)

    def rng(self, seed: int, n: int) -> np.random.Generator:
        """Generator for the random choices of this fault at command ``n``."""
        return np.random.default_rng([int(seed) & 0xFFFFFFFF, 0xFA17, self.index, n])


class FaultSchedule:
    """A parsed fault schedule.

    Parameters
    ----------
    faults : list of dict
        ``[[fault]]`` tables.
    seed : int or None
        Seed of the random choices; None: the instrument's seed.
    """

    def __init__(self, faults: list | None = None, seed: int | None = None):
        self.seed = seed
        self.faults: list[Fault] = []
        for i, d in enumerate(faults or []):
            d = dict(d)
            kind = d.pop("kind", None)
            if kind not in KINDS:
                raise ValueError(f"fault {i}: unknown kind {kind!r}")
            port = d.pop("port", "camera" if kind.startswith("camera_") else "zaber")
            if port not in PORT_NAMES:
                raise ValueError(f"fault {i}: unknown port {port!r}; the rig's ports are {', '.join(PORT_NAMES)}")
            if kind in _ZABER_ONLY and port != "zaber" and kind != "power_cycle":
                raise ValueError(f"fault {i}: {kind} only applies to the zaber port")
            at = d.pop("at_command", ())
            at = (at,) if isinstance(at, int) else tuple(int(x) for x in at)
            f = Fault(kind=kind, index=i, port=port, at_command=at, **d)
            if not at and f.at_time is None and f.probability is None:
                raise ValueError(f"fault {i}: give at_command, at_time or probability")
            self.faults.append(f)

    @classmethod
    def from_toml(cls, source: str | os.PathLike) -> "FaultSchedule":
        """Read a schedule from a TOML file path or a TOML string."""
        from gonio.core.tomlfile import parse_toml, read_toml

        text = os.fspath(source)
        if "\n" not in text and os.path.exists(text):
            data = read_toml(text, "fault schedule")
        else:
            data = parse_toml(text, "fault schedule")
        return cls(data.get("fault", []), data.get("seed"))

    @classmethod
    def coerce(cls, obj) -> "FaultSchedule":
        """Accept None, a schedule, a list of dicts, a dict with ``fault``, a path or TOML text."""
        if obj is None:
            return cls()
        if isinstance(obj, FaultSchedule):
            return obj
        if isinstance(obj, list):
            return cls(obj)
        if isinstance(obj, dict):
            return cls(obj.get("fault", []), obj.get("seed"))
        return cls.from_toml(obj)

    def due(self, port: str, n: int, t: float, seed: int) -> list[Fault]:
        """Faults that fire on command ``n`` of ``port`` received at simulated time ``t``."""
        out = []
        for f in self.faults:
            if f.at_time is not None:
                if (t >= f.at_time and "t" not in f.fired
                        and (f.kind not in _LINE_KINDS or f.port == port)):
                    f.fired.add("t")
                    out.append(f)
                continue
            if f.port != port:
                continue
            if n in f.at_command and n not in f.fired:
                f.fired.add(n)
                out.append(f)
            elif f.probability is not None and f.rng(seed, n).random() < f.probability:
                out.append(f)
        return out
