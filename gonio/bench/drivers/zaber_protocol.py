"""Zaber ASCII protocol: the bytes of one command line and the parsing of one reply line.

Pure functions over bytes (no port): `lrc`, `format_command`, `parse_reply`,
`parse_continuation`, the `Reply` record, and the meanings of the warning flags and of the
rejection reasons. The wire format is that of ``shared/notes/protocols.md`` (Zaber ASCII
protocol manual: message format, checksums, message ids, "message continuation").
`gonio.bench.drivers.zaber.ZaberChain` sends and reads these lines on a port.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from gonio.core.errors import CommunicationError, GonioError

__all__ = ["FLAG_MEANINGS", "REJECT_MEANINGS", "Reply", "lrc", "format_command", "parse_reply",
           "parse_continuation", "MAX_COMMAND"]

#: Longest command line sent (characters, without the newline). The manual bounds a packet
#: (``comm.packet.size.max``, 80 on the simulator); the bench's commands are far shorter, so
#: this is a guard against a value gone wrong, not a protocol figure (the simulator refuses
#: longer lines too: ``gonio.sim.devices.zaber_chain.ZaberChain.MAX_LINE``).
MAX_COMMAND = 256
_NOT_PRINTABLE = re.compile("[^ -~]")

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

    Raises
    ------
    GonioError
        An address or message id out of range, a command that is not printable ASCII (a
        control character such as a newline would end the line and start another command), or
        a line longer than `MAX_COMMAND`.
    """
    for name, value in (("device", device), ("axis", axis), ("message id", msgid)):
        if value is not None and not 0 <= int(value) <= 99:
            raise GonioError(f"Zaber {name} {value!r} is out of range; give 0..99")
    command = str(command)
    bad = _NOT_PRINTABLE.search(command)
    if bad is not None:
        raise GonioError(f"Zaber command {command[:40]!r} holds {bad.group()!r}, not printable ASCII; "
                         "send one command of printable characters")
    body = f"{int(device)} {int(axis)}"
    if msgid is not None:
        body += f" {int(msgid):02d}"
    if command:
        body += f" {command}"
    if checksum:
        body += ":" + lrc(body.encode("ascii"))
    if 1 + len(body) > MAX_COMMAND:
        raise GonioError(f"Zaber command {command[:40]!r}... makes a line of {1 + len(body)} characters, "
                         f"more than {MAX_COMMAND}; send a shorter command")
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
