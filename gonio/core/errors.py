"""Errors a user can act on.

Every error the bench raises for a cause outside the code (a malformed plan, an unreachable
angle, a dead serial port, a missing file, a fault reported by a stage) is a `GonioError`
whose ``str`` is ONE line: what is wrong and what to do about it. The CLI prints that line on
stderr and exits with status 2, without a traceback.
"""

from __future__ import annotations

__all__ = [
    "GonioError",
    "PlanError",
    "DeviceError",
    "RejectedError",
    "FaultError",
    "CommunicationError",
    "UnreachableError",
    "SessionError",
]


class GonioError(Exception):
    """An error the user can fix; its message is one line (newlines are folded)."""

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


class PlanError(GonioError):
    """A plan file or preset is malformed or holds invalid angles."""


class UnreachableError(GonioError):
    """A configuration the instrument cannot reach (lamp blocks camera, stage limit, horizon)."""


class DeviceError(GonioError):
    """An instrument answered, but not as it should."""


class RejectedError(DeviceError):
    """A Zaber device rejected a command (``RJ``); ``reason`` holds the device's word."""

    def __init__(self, message: str, reason: str = ""):
        super().__init__(message)
        self.reason = reason


class FaultError(DeviceError):
    """A Zaber device reports a fault flag (F*); the run must stop."""

    def __init__(self, message: str, flags: tuple[str, ...] = ()):
        super().__init__(message)
        self.flags = tuple(flags)


class CommunicationError(DeviceError):
    """A port does not open, stays silent or keeps garbling replies after retries and a reconnect."""


class SessionError(GonioError):
    """A session folder is missing, inconsistent or corrupt."""
