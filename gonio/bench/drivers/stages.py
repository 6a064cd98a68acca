"""The goniometer's stages: the four rotary axes of Zaber device 1, in degrees.

Soft limits checked before any move (the settings' ``[axes]`` narrowed to each device's own
``limit.min``/``limit.max``), shortest-way moves, homing, BUSY polling, the position check
after a move (interfaces.md section 3). The bytes go through `gonio.bench.drivers.zaber.ZaberChain`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Mapping

from gonio.bench.settings import AXES
from gonio.core.errors import CommunicationError, DeviceError, FaultError, GonioError, UnreachableError
from gonio.bench.drivers.zaber import ZaberChain
from gonio.bench.drivers.zaber_protocol import FLAG_MEANINGS

__all__ = ["Goniometer", "MoveError", "shortest_equivalent", "NATIVE_PER_SPEED", "NATIVE_PER_ACCEL"]

#: Zaber's native units (ASCII protocol manual, ``maxspeed``, ``move vel`` and ``accel``): speed
#: data = microsteps/s * 1.6384 (microsteps per 1.6384 s), acceleration data = microsteps/s^2 *
#: 1.6384 / 10
NATIVE_PER_SPEED = 1.6384
NATIVE_PER_ACCEL = 1.6384 / 10


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
    alerts : bool
        ``connect`` turns each stage device's alerts on (``set comm.alert 1``) and moves are
        waited for by their alerts (`ZaberChain.wait_idle`); a device that rejects it is polled.

    Notes
    -----
    ``connect`` reads ``limit.cycle.dist`` (microsteps per revolution) of each axis, so
    degrees = microsteps * 360 / cycle_dist, and narrows the soft limits of the settings to
    the device's own ``limit.min``/``limit.max``.
    """

    POSITION_TOLERANCE_STEPS = 2

    def __init__(self, chain: ZaberChain, settings: Mapping, *, poll_interval_s: float = 0.05,
                 sleep: Callable[[float], None] = time.sleep, move_timeout_s: float = 300.0,
                 alerts: bool = False):
        self.chain = chain
        self.alerts = alerts
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
            if self.alerts:
                self.chain.enable_alerts(dev)
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

    def identify(self) -> list[dict]:
        """The identification of each stage device (`ZaberChain.identify`), by address."""
        return [self.chain.identify(dev) for dev in self.devices]

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

    def motion(self) -> dict[str, tuple[float, float]]:
        """Each axis's speed limit and acceleration as its controller holds them: ``{name: (deg/s,
        deg/s^2)}`` from ``maxspeed`` and ``accel`` in native units (needs `connect`)."""
        out = {}
        for dev in self.devices:
            vmax, acc = self.chain.get(dev, 0, "maxspeed"), self.chain.get(dev, 0, "accel")
            for a in (a for a in self.axes.values() if a.device == dev):
                deg = 360.0 / a.cycle_dist
                out[a.name] = (vmax[a.axis - 1] / NATIVE_PER_SPEED * deg, acc[a.axis - 1] / NATIVE_PER_ACCEL * deg)
        return out

    def set_motion(self, name: str, deg_s: float, deg_s2: float | None = None) -> None:
        """Set axis ``name``'s speed limit (deg/s) and, if given, its acceleration (deg/s^2), in
        the controller's native units (rounded to the nearest integer; an axis must be idle)."""
        a = self.axes[name]
        for value, key, per, unit in ((deg_s, "maxspeed", NATIVE_PER_SPEED, "deg/s"),
                                      (deg_s2, "accel", NATIVE_PER_ACCEL, "deg/s^2")):
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
                raise GonioError(f"{key} of {name}: {value!r} {unit} is not a positive number; give one")
            native = round(value * a.cycle_dist / 360.0 * per)
            self.chain.set(a.device, a.axis, key, max(1, native))

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
