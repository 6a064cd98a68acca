"""Camera port server (docs/interfaces.md section 4): line-based ASCII, ``\\n`` terminated.

| command | reply |
|---|---|
| ``*IDN?`` | ``gonio,SimCamera,SIM00001,0.1.0`` |
| ``SENSOR?`` | ``<width> <height> <bits> <black> <white> <cfa>`` |
| ``EXPOSE <seconds> <path>`` | ``OK <sha256>`` once the DNG is at ``<path>``; ``ERR <reason>`` |
| ``FLAT <seconds> <path>`` | as ``EXPOSE``, of the flat-field source (integrating sphere) |
| ``CHART <seconds> <path>`` | as ``EXPOSE``, of the ColorChecker in the holder's chart slot (colour calibration) |

The exposure physics lives in ``Instrument.capture``; this module parses and formats, and
refuses what could reach outside its folder: lines over ``MAX_LINE`` bytes, control
characters, paths outside ``root`` (the rules below).
"""

# Exposures from 1 us to 60 s are accepted; the path is the rest of the line (spaces allowed),
# its folder must exist. Errors: ``ERR bad exposure``, ``ERR missing path``,
# ``ERR no such directory``, ``ERR disk full`` (ENOSPC or EDQUOT: the client stops resumably),
# ``ERR write failed``, ``ERR unknown command``.
#
# A line is at most ``MAX_LINE`` bytes (UTF-8, without the newline; a longer one is answered
# ``ERR line too long`` and discarded) and holds no control character (C0, DEL, C1, U+2028,
# U+2029; ``ERR control character``): a path never carries a second command. The camera writes
# only inside the folder it serves (``root``; None: any folder): the path is resolved (symbolic
# links followed) and must lie in ``root``; a path with a ``..`` component is refused whatever
# ``root`` is (``ERR path outside the camera folder``).

from __future__ import annotations

import errno
import hashlib
import os

from gonio.core.preflight import control_character
from gonio.sim.physics.sensor import CFA, write_dng

__all__ = ["CameraPort"]


class CameraPort:
    """Camera protocol server; ``armed`` holds pending camera faults (``nothing``, ``truncated``).

    ``root``: the folder the camera serves (it writes nowhere else); None: any folder, a path
    with a ``..`` component still refused.
    """

    IDN = "gonio,SimCamera,SIM00001,0.1.0"
    #: command lines are UTF-8: the path of an exposure may hold any character but a control
    #: character (Zaber and SCPI are ASCII)
    encoding = "utf-8"
    #: longest command line (bytes, without the newline): ``EXPOSE``, the exposure and a path of
    #: up to 4096 bytes (PATH_MAX); the port endpoint keeps no more of a line
    MAX_LINE = 4200

    def __init__(self, instrument, root: str | os.PathLike | None = None):
        self.inst = instrument
        self.armed: list[str] = []
        self.root = root

    def overlong(self, text: str) -> list[str]:
        """The answer to a line longer than ``MAX_LINE`` (``text``: its first bytes)."""
        return ["ERR line too long"]

    def handle(self, text: str) -> list[str]:
        text = text.strip(" \r\n")
        if not text:
            return []
        if len(text.encode(self.encoding, "replace")) > self.MAX_LINE:
            return self.overlong(text)
        if control_character(text) is not None:
            return ["ERR control character"]
        parts = text.split(None, 2)
        cmd = parts[0].upper()
        if cmd == "*IDN?" and len(parts) == 1:
            return [self.IDN]
        if cmd == "SENSOR?" and len(parts) == 1:
            s = self.inst.sensor
            return [f"{s.width} {s.height} {s.bits} {s.black} {s.white} {CFA}"]
        if cmd in ("EXPOSE", "FLAT", "CHART"):
            return [self._expose(parts[1:], {"FLAT": "flat", "CHART": "chart"}.get(cmd, "scene"))]
        return ["ERR unknown command"]

    def _expose(self, args, source="scene") -> str:
        try:
            seconds = float(args[0])
        except (IndexError, ValueError):
            return "ERR bad exposure"
        if not 1e-6 <= seconds <= 60.0:
            return "ERR bad exposure"
        if len(args) < 2 or not args[1].strip():
            return "ERR missing path"
        path = args[1].strip()
        if not self._inside(path):
            return "ERR path outside the camera folder"
        path = os.path.join(self.root, path) if self.root is not None else path
        folder = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(folder):
            return "ERR no such directory"
        data = self.inst.capture(seconds, source)
        fault = self.armed.pop(0) if self.armed else None
        try:
            if fault == "nothing":
                digest = hashlib.sha256(data).hexdigest()
            elif fault == "truncated":
                write_dng(path, data[: len(data) // 2])
                digest = hashlib.sha256(data).hexdigest()
            else:
                digest = write_dng(path, data)
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                return "ERR disk full"
            return "ERR write failed"
        return f"OK {digest}"

    def _inside(self, path: str) -> bool:
        """Whether the camera may write ``path``: no ``..`` component, and with a ``root``,
        the resolved path (relative ones taken from ``root``, symbolic links followed, a link
        at the file's own name too) inside the resolved ``root``."""
        if ".." in path.split("/"):
            return False
        if self.root is None:
            return True
        root = os.path.realpath(self.root)
        target = os.path.realpath(os.path.join(root, path))
        return os.path.commonpath([root, target]) == root and target != root
