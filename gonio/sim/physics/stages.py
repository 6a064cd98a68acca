"""Rotary stage physics: trapezoidal motion in simulated time, homing, stops and faults.

State only; the Zaber ASCII grammar lives in :mod:`gonio.sim.devices.zaber_chain`. Units:
positions in integer microsteps (the value a ``get pos`` reports), speeds in microsteps/s,
accelerations in microsteps/s^2; the wire carries Zaber's native units (``maxspeed``
microsteps/s * 1.6384, ``accel`` microsteps/s^2 * 1.6384 / 10), converted in
:mod:`gonio.sim.devices.zaber_stage`. Angle (deg) = position * 360 / ``cycle_dist``.

Each axis keeps its *physical* angle apart from its position *counter*: the counter reads
``physical - offset``. At power-on (and after a power cycle) the counter reads 0 wherever the
axis physically is, and the axis carries WR and WH (no reference). ``home`` drives the axis to
its physical reference (physical 0) and then zeroes the counter. A motion is a list of
constant-acceleration segments planned at the start of the move; the position at any simulated
time follows from them, so no time-stepping is needed (``process(t)`` settles finished motions
and fires the scheduled halts).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = ["RotaryAxis", "plan_trapezoid", "DEFAULT_MAXSPEED", "DEFAULT_ACCEL"]

DEFAULT_MAXSPEED = 40000    # microsteps/s (20 deg/s at 720000 microsteps/rev)
DEFAULT_ACCEL = 80000       # microsteps/s^2 (40 deg/s^2)


@dataclass
class _Segment:
    t0: float     # s
    x0: float     # microsteps (physical)
    v0: float     # microsteps/s
    a: float      # microsteps/s^2
    t1: float     # end of segment, s

    def x(self, t: float) -> float:
        dt = t - self.t0
        return self.x0 + self.v0 * dt + 0.5 * self.a * dt * dt

    def v(self, t: float) -> float:
        return self.v0 + self.a * (t - self.t0)


def plan_trapezoid(x0: float, v0: float, target: float, vmax: float, accel: float,
                   t0: float = 0.0) -> list[_Segment]:
    """Plan a trapezoidal (or triangular) move.

    Parameters
    ----------
    x0, v0 : float
        Start position (microsteps) and velocity (microsteps/s).
    target : float
        End position, microsteps; the axis is at rest there at the end.
    vmax, accel : float
        Speed limit (microsteps/s) and acceleration = deceleration (microsteps/s^2), > 0.
    t0 : float
        Start time, s.

    Returns
    -------
    list of _Segment
        Constant-acceleration pieces covering [t0, t_end]; empty if already at rest at target.

    Notes
    -----
    From rest over a distance D: with ``D >= vmax^2 / a`` the profile accelerates for
    ``vmax / a``, cruises for ``(D - vmax^2/a) / vmax`` and decelerates for ``vmax / a``
    (duration ``D / vmax + vmax / a``); otherwise it is a triangle of duration
    ``2 sqrt(D / a)``. A moving axis whose stopping distance overshoots the target (or that
    moves away from it) first decelerates to rest, then starts a new profile.
    """
    segs: list[_Segment] = []
    t, x, v = t0, float(x0), float(v0)
    d = target - x
    if v != 0.0:
        s = math.copysign(1.0, v)
        stop_dist = v * v / (2 * accel)
        if s * d < stop_dist - 1e-9:
            # moving away, or cannot stop in time: brake to rest first
            tb = abs(v) / accel
            segs.append(_Segment(t, x, v, -s * accel, t + tb))
            x = segs[-1].x(t + tb)
            t, v = t + tb, 0.0
            d = target - x
    if abs(d) < 1e-9 and v == 0.0:
        return segs
    s = math.copysign(1.0, d) if d != 0 else math.copysign(1.0, v)
    dist = abs(d)
    u = abs(v)
    vpeak = max(vmax, u)
    d_acc = (vpeak * vpeak - u * u) / (2 * accel)
    d_dec = vpeak * vpeak / (2 * accel)
    if d_acc + d_dec <= dist:
        t_acc = (vpeak - u) / accel
        t_cru = (dist - d_acc - d_dec) / vpeak
    else:
        vpeak = math.sqrt(max(0.0, (2 * accel * dist + u * u) / 2))
        t_acc = max(0.0, (vpeak - u) / accel)
        t_cru = 0.0
    t_dec = vpeak / accel
    if t_acc > 0:
        segs.append(_Segment(t, x, s * u, s * accel, t + t_acc))
        x, t = segs[-1].x(t + t_acc), t + t_acc
    if t_cru > 0:
        segs.append(_Segment(t, x, s * vpeak, 0.0, t + t_cru))
        x, t = segs[-1].x(t + t_cru), t + t_cru
    segs.append(_Segment(t, x, s * vpeak, -s * accel, t + t_dec))
    return segs


@dataclass
class RotaryAxis:
    """One rotary axis of a Zaber controller.

    Parameters
    ----------
    limit_min, limit_max : int
        Travel limits of the counter, microsteps.
    cycle_dist : int
        Microsteps per revolution.
    maxspeed : int
        Speed limit, microsteps/s.
    accel : int
        Acceleration and deceleration, microsteps/s^2.
    physical : float
        Physical position at power-on, microsteps from the home reference.
    """

    limit_min: int
    limit_max: int
    cycle_dist: int
    maxspeed: int = DEFAULT_MAXSPEED
    accel: int = DEFAULT_ACCEL
    physical: float = 0.0
    offset: float = 0.0
    homed: bool = False
    flags: set = field(default_factory=set)     # latched flags (NI, FS, WL, ...)
    _segs: list = field(default_factory=list)
    _target: float = 0.0
    _homing: bool = False
    _halt: tuple | None = None                  # (time, flag) when the motion is cut short
    driver_enabled: bool = True                 # ``driver disable`` de-energises the motor (FD)
    parked: bool = False                        # ``tools parking park``: keeps the reference over a power cycle
    moves: int = 0                              # motions started that go somewhere (the error model's per-move draws)
    last_dir: int = 0                           # sign of the last motion (+1, -1; 0 before any): backlash

    # ---------------------------------------------------------------- state queries
    def process(self, t: float) -> None:
        """Settle a motion that ended (or was halted) by simulated time ``t`` (s)."""
        if not self._segs:
            return
        if self._halt is not None and t >= self._halt[0]:
            th, flag = self._halt
            self.physical = self._x_raw(th)
            self._segs, self._halt, self._homing = [], None, False
            self.flags.add(flag)
            return
        if t >= self._segs[-1].t1:
            self.physical = self._target
            self._segs = []
            if self._homing:
                self._homing = False
                self.homed = True
                self.offset = 0.0
                self.physical = 0.0

    def _x_raw(self, t: float) -> float:
        for s in self._segs:
            if t <= s.t1:
                return s.x(max(t, s.t0))
        return self._target

    def position_physical(self, t: float) -> float:
        """Physical position at time ``t`` (s), microsteps, float."""
        self.process(t)
        if not self._segs:
            return self.physical
        if self._halt is not None:
            t = min(t, self._halt[0])
        return self._x_raw(t)

    def position(self, t: float) -> int:
        """Counter reading (what ``get pos`` says) at time ``t``, integer microsteps."""
        return int(round(self.position_physical(t) - self.offset))

    def velocity(self, t: float) -> float:
        """Velocity at time ``t``, microsteps/s."""
        self.process(t)
        for s in self._segs:
            if t <= s.t1:
                return s.v(max(t, s.t0))
        return 0.0

    def busy(self, t: float) -> bool:
        """Whether the axis moves at time ``t``."""
        self.process(t)
        return bool(self._segs)

    def end_time(self, t: float) -> float | None:
        """When the current motion ends (or halts); None when idle."""
        self.process(t)
        if not self._segs:
            return None
        if self._halt is not None:
            return min(self._halt[0], self._segs[-1].t1)
        return self._segs[-1].t1

    def active_flags(self, t: float) -> set:
        """Latched flags plus the WR/WH conditions, at time ``t``."""
        self.process(t)
        f = set(self.flags)
        if not self.homed:
            f |= {"WR", "WH"}
        if not self.driver_enabled:
            f.add("FD")
        return f

    # ---------------------------------------------------------------- actions
    def _start(self, t: float, physical_target: float) -> None:
        x, v = self.position_physical(t), self.velocity(t)
        if self._segs:
            self.flags.add("NI")      # a new motion interrupts the running one
            self._homing = False
        else:
            self.flags.discard("NI")  # a move from rest clears the old interruption
        self._halt = None
        self.physical = x
        self._target = float(physical_target)
        if self._target != x:                  # a move to where the axis is does not move it
            self.moves += 1
            self.last_dir = 1 if self._target > x else -1
        self._segs = plan_trapezoid(x, v, self._target, self.maxspeed, self.accel, t)
        if not self._segs:
            self.physical = self._target

    def in_limits(self, counter_target: int) -> bool:
        """Whether a counter target lies within [limit_min, limit_max]."""
        return self.limit_min <= counter_target <= self.limit_max

    def move_abs(self, t: float, counter_target: int) -> None:
        """Start a move to counter position ``counter_target`` (microsteps) at time ``t``."""
        self._start(t, counter_target + self.offset)

    def move_vel(self, t: float, speed: float) -> None:
        """Move at ``speed`` (microsteps/s, signed) until a stop or the travel limit.

        The simulator plans it as a move to the limit in the direction of ``speed`` with
        ``|speed|`` as the speed limit: the axis comes to rest at the limit instead of running
        into it (a real controller stops at the limit too; its exact deceleration there is not
        published: invented).
        """
        if speed == 0:
            self.stop(t)
            return
        target = self.limit_max if speed > 0 else self.limit_min
        vmax = self.maxspeed
        self.maxspeed = abs(speed)
        try:
            self._start(t, target + self.offset)
        finally:
            self.maxspeed = vmax

    def home(self, t: float) -> None:
        """Start homing: drive to the physical reference (0), then zero the counter."""
        self._start(t, 0.0)
        self._homing = True
        if not self._segs:
            self._homing = False
            self.homed = True
            self.offset = 0.0
            self.physical = 0.0

    def stop(self, t: float) -> None:
        """Decelerate to rest at ``accel`` (sets NI if it was moving)."""
        if not self.busy(t):
            return
        x, v = self.position_physical(t), self.velocity(t)
        self.flags.add("NI")
        self._homing = False
        self._halt = None
        tb = abs(v) / self.accel
        a = -math.copysign(self.accel, v) if v else 0.0
        seg = _Segment(t, x, v, a, t + tb)
        self._segs = [seg]
        self._target = seg.x(t + tb)
        self.physical = x

    def estop(self, t: float) -> None:
        """Stop at once, no deceleration (sets NI if it was moving)."""
        if not self.busy(t):
            return
        self.physical = self.position_physical(t)
        self._segs, self._halt, self._homing = [], None, False
        self.flags.add("NI")

    def schedule_halt(self, t_halt: float, flag: str) -> None:
        """Cut the current motion short at ``t_halt`` (s) and latch ``flag`` (FS, WL)."""
        if self._segs and t_halt < self._segs[-1].t1:
            self._halt = (float(t_halt), flag)

    def power_cycle(self, t: float) -> None:
        """Lose power: stop where it is, counter reads 0, reference lost (WR, WH).

        A parked axis (``tools parking park``) keeps its counter and reference and comes back
        parked, as Zaber describes parking (the axis stays parked until ``unpark``).
        """
        self.physical = self.position_physical(t)
        self._segs, self._halt, self._homing = [], None, False
        self.driver_enabled = True
        if self.parked:
            self.flags.clear()
            return
        self.offset = self.physical
        self.homed = False
        self.flags.clear()
