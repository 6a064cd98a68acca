"""Device 1 of the simulated chain: the 4-axis rotary controller's commands and settings.

Commands (Zaber ASCII manual): ``home``, ``move abs|rel POS [SPEED [ACCEL]]``,
``move min|max [SPEED [ACCEL]]``, ``move vel SPEED [ACCEL]``, ``stop``, ``estop``,
``warnings [clear]``, ``driver disable|enable``, ``tools parking park|unpark``, ``get``/``set``
of ``pos``, ``limit.min``, ``limit.max``, ``limit.cycle.dist``, ``maxspeed``, ``accel``,
``resolution``, ``peripheralid``/``peripheral.id``, ``parking.state``, ``driver.enabled``,
``encoder.pos``.
"""

# Speeds and accelerations are in Zaber's native units on the wire (manual, settings ``maxspeed``
# and ``accel``): ``maxspeed`` and ``move vel`` data = microsteps/s * 1.6384 (microsteps per
# 1.6384 s), ``accel`` data = microsteps/s^2 * 1.6384 / 10. The axes
# (:mod:`gonio.sim.physics.stages`) keep microsteps/s and microsteps/s^2; this module converts at
# the wire and rounds a reported value to the nearest integer (the simulator's defaults, 40000
# microsteps/s and 80000 microsteps/s^2, read 65536 and 13107). Behaviour chosen where the manual
# is silent: the comment below.

# The same unit factors are in zaber.serial-era clients.
#
# Chosen where the manual is silent (invented):
# - move abs/rel/min/max with SPEED [ACCEL] (the form zaber-motion 10.3 sends for
#   move_absolute(..., velocity=, acceleration=): "move abs 1000 20000 3000", "move max 5000"):
#   that move's speed limit and acceleration in native units, the axis's maxspeed/accel settings
#   unchanged; 0 keeps the setting, 1..1 000 000, else BADDATA (the bound is invented).
# - move vel N: |N| up to 1 000 000 native units (610 352 microsteps/s), else BADDATA; it needs a
#   homed axis like every other move; the axis comes to rest at the travel limit.
# - driver disable: the axis carries FD until driver enable; moves and homing are rejected with
#   DRIVERDISABLED (a reason zaber-motion 10.3 knows: DriverDisabledException).
# - A parked axis rejects motion with PARKED; it keeps its reference over a power cycle.
# - get encoder.pos: the simulated stages have no encoders; on axis 0 each axis reads NA (the
#   manual's value for a setting an axis does not have), on one axis BADCOMMAND.
# - Identification: an X-MCC4 (STAGE_IDENT, real ids), resolution 64 (the manual's default
#   microstep resolution), the peripheral id of ROTARY_PERIPHERALS whose microsteps per turn are
#   the axis's limit.cycle.dist, else 0. Zaber's device database, not the manual, maps ids to
#   products and their unit conversions; it is not on this machine (zaber-motion's offline source
#   is Zaber's devices-public.sqlite, fetched online), so the simulator's ids come from Zaber's
#   own test data, not from the database.

from __future__ import annotations

import contextlib

from gonio.sim.devices.zaber_common import Device, Reject, int_arg, sort_flags

__all__ = ["StageDevice", "NATIVE_PER_SPEED", "NATIVE_PER_ACCEL"]

#: An X-MCC4 four-axis controller: device id 30342 on firmware 7.38 build 15708, as Zaber's own
#: zaber-motion end-to-end tests describe one (public port: zabertech/motorZaberMotion's mock
#: devices, "xmcc4.ts"); the serial number is the simulator's.
STAGE_IDENT = {"deviceid": 30342, "system.serial": 91001, "version": "7.38",
               "version.build": 15708, "peripheralid": 0}
#: Rotary peripherals the simulator can be, by id: microsteps per turn at resolution 64. 46657 is
#: the rotary stage Zaber's zaber-motion tests put on an X-MCC4, converted at 6400 microsteps per
#: degree. An axis reports the peripheral whose microstep grid its ``limit.cycle.dist`` is, else
#: 0 ("no peripheral"): zaber-motion then offers native units only, never a conversion of
#: another product's (43211, which the simulator reported before issue 40, is Zaber's X-LHM
#: *linear* stage: millimetres from microsteps of a rotary axis).
ROTARY_PERIPHERALS = {46657: 2_304_000}
MAX_VEL = 1_000_000           # native units (invented bound)
MAX_ACCEL = 1_000_000         # native units (invented bound) of a move's own acceleration
#: native units per physical unit (Zaber ASCII manual): maxspeed/move vel per microstep/s,
#: accel per microstep/s^2
NATIVE_PER_SPEED = 1.6384
NATIVE_PER_ACCEL = 1.6384 / 10
_NATIVE = {"maxspeed": NATIVE_PER_SPEED, "accel": NATIVE_PER_ACCEL}
_ATTR = {"limit.min": "limit_min", "limit.max": "limit_max", "limit.cycle.dist": "cycle_dist",
         "maxspeed": "maxspeed", "accel": "accel"}


def peripheral_of(axis) -> int:
    """The peripheral id a simulated rotary axis reports (:data:`ROTARY_PERIPHERALS`; 0: none)."""
    return next((pid for pid, turn in ROTARY_PERIPHERALS.items() if turn == axis.cycle_dist), 0)


@contextlib.contextmanager
def _profile(scope, speed, accel):
    """The axes plan the moves started inside with this speed and acceleration (native units;
    None: the axis's setting); their settings are as before afterwards (a later ``stop``
    decelerates at ``accel``, as the settings say)."""
    saved = [(a.maxspeed, a.accel) for a in scope]
    try:
        for a in scope:
            if speed is not None:
                a.maxspeed = speed / NATIVE_PER_SPEED
            if accel is not None:
                a.accel = accel / NATIVE_PER_ACCEL
        yield
    finally:
        for a, (v, acc) in zip(scope, saved):
            a.maxspeed, a.accel = v, acc


class StageDevice(Device):
    """Device 1: the rotary axes of ``instrument.axes``."""

    def __init__(self, chain, number: int):
        super().__init__(chain, number, STAGE_IDENT)
        self._moving: set[int] = set()          # axes (1..n) whose motion end is to be alerted

    @property
    def axes(self):
        return self.inst.axes

    def axis_count(self) -> int:
        return len(self.axes)

    def scope(self, axis: int) -> list:
        return list(self.axes) if axis == 0 else [self.axes[axis - 1]]

    def status(self, axis: int) -> tuple[str, list]:
        t = self.now()
        scope = self.scope(axis if axis <= len(self.axes) else 0)
        busy = any(a.busy(t) for a in scope)
        flags = set()
        for a in scope:
            flags |= a.active_flags(t)
        return ("BUSY" if busy else "IDLE"), sort_flags(flags)

    def ended_alerts(self) -> list[str]:
        """``!01 A IDLE WARN`` for each axis whose motion ended (when ``comm.alert`` is 1)."""
        if not self._moving:
            return []
        t = self.now()
        done = sorted(i for i in self._moving if not self.axes[i - 1].busy(t))
        self._moving -= set(done)
        if not self.alert:
            return []
        return [self.chain.alert_line(self.number, i) for i in done]

    def next_alert_at(self) -> float | None:
        """When the first motion to be alerted ends (``comm.alert`` 1); None if none."""
        if not (self._moving and self.alert):
            return None
        t = self.now()
        ends = [self.axes[i - 1].end_time(t) for i in self._moving]
        return min(t if e is None else e for e in ends)

    def _started(self, scope) -> None:
        t = self.now()
        for a in scope:
            if a.busy(t):
                self._moving.add(self.axes.index(a) + 1)
            self._arm(a, t)

    def _arm(self, axis_obj, t: float) -> None:
        """Apply an armed stall/limit fault to the motion that just started."""
        halts = self.chain.armed_halts
        if not halts:
            return
        idx = self.axes.index(axis_obj) + 1
        for k, (ax, fraction, flag) in enumerate(halts):
            end = axis_obj.end_time(t)
            if (ax is None or ax == idx) and end is not None:
                axis_obj.schedule_halt(t + fraction * (end - t), flag)
                del halts[k]
                return

    @staticmethod
    def _can_move(scope) -> None:
        if any(not a.driver_enabled for a in scope):
            raise Reject("DRIVERDISABLED")
        if any(a.parked for a in scope):
            raise Reject("PARKED")

    # ------------------------------------------------------------------ commands
    def command(self, cmd) -> str:
        w, t = cmd.words, self.now()
        op = w[0]
        scope = self.scope(cmd.axis)
        if op == "home":
            if len(w) != 1:
                raise Reject("BADCOMMAND")
            self._can_move(scope)
            for a in scope:
                a.home(t)
            self._started(scope)
            return "0"
        if op == "move":
            return self._move(cmd, w, scope, t)
        if op in ("stop", "estop"):
            if len(w) != 1:
                raise Reject("BADCOMMAND")
            for a in scope:
                (a.stop if op == "stop" else a.estop)(t)
            return "0"
        if op == "warnings":
            if w[1:] not in ([], ["clear"]):
                raise Reject("BADCOMMAND")
            _, flags = self.status(cmd.axis)
            if len(w) == 2:
                for a in scope:
                    a.flags.clear()
            return " ".join([f"{len(flags):02d}"] + flags)
        if op == "driver":
            if len(w) != 2 or w[1] not in ("disable", "enable"):
                raise Reject("BADCOMMAND")
            if w[1] == "disable":
                for a in scope:
                    a.estop(t)
                    a.flags.discard("NI")
            for a in scope:
                a.driver_enabled = w[1] == "enable"
            return "0"
        if op == "tools":
            if len(w) != 3 or w[1] != "parking" or w[2] not in ("park", "unpark"):
                raise Reject("BADCOMMAND")
            if w[2] == "park" and any(a.busy(t) for a in scope):
                raise Reject("STATUSBUSY")
            for a in scope:
                a.parked = w[2] == "park"
            return "0"
        raise Reject("BADCOMMAND")

    def _move(self, cmd, w, scope, t) -> str:
        if len(w) < 2 or w[1] not in ("abs", "rel", "min", "max", "vel"):
            raise Reject("BADCOMMAND")
        if w[1] == "vel":
            if len(w) not in (3, 4):
                raise Reject("BADDATA")
            n = int_arg(w, 2)
            accel = self._profile_arg(w, 3, MAX_ACCEL) if len(w) == 4 else None
        else:
            first = 3 if w[1] in ("abs", "rel") else 2      # where the optional speed and accel are
            if not first <= len(w) <= first + 2:
                raise Reject("BADDATA")
            n = int_arg(w, 2) if first == 3 else 0
            speed = self._profile_arg(w, first, MAX_VEL) if len(w) > first else None
            accel = self._profile_arg(w, first + 1, MAX_ACCEL) if len(w) > first + 1 else None
        self._can_move(scope)
        if any(not a.homed for a in scope):
            raise Reject("BADDATA")
        if w[1] == "vel":
            if abs(n) > MAX_VEL:
                raise Reject("BADDATA")
            with _profile(scope, None, accel):
                for a in scope:
                    a.move_vel(t, n / NATIVE_PER_SPEED)
            self._started(scope)
            return "0"
        targets = []
        for a in scope:
            tgt = {"abs": lambda: n, "rel": lambda: a.position(t) + n,
                   "min": lambda: a.limit_min, "max": lambda: a.limit_max}[w[1]]()
            if not a.in_limits(tgt):
                raise Reject("BADDATA")
            targets.append(tgt)
        with _profile(scope, speed, accel):
            for a, tgt in zip(scope, targets):
                a.move_abs(t, tgt)
        self._started(scope)
        return "0"

    @staticmethod
    def _profile_arg(w, i, top) -> int | None:
        """An optional speed or acceleration of a move (native units): 0 keeps the axis's own
        ``maxspeed`` / ``accel`` (None), 1..``top`` is used for this move; else BADDATA."""
        v = int_arg(w, i)
        if not 0 <= v <= top:
            raise Reject("BADDATA")
        return v or None

    # ------------------------------------------------------------------ settings
    def get_axis(self, key: str, axis: int) -> str:
        if axis == 0:
            raise Reject("BADAXIS")
        a = self.axes[axis - 1]
        if key == "pos":
            return str(a.position(self.now()))
        if key in _NATIVE:
            return str(round(getattr(a, _ATTR[key]) * _NATIVE[key]))
        if key in _ATTR:
            return str(int(getattr(a, _ATTR[key])))
        if key == "resolution":
            return "64"
        if key in ("peripheralid", "peripheral.id"):
            return str(peripheral_of(a))
        if key == "parking.state":
            return "1" if a.parked else "0"
        if key == "driver.enabled":
            return "1" if a.driver_enabled else "0"
        if key == "encoder.pos":
            raise Reject("NA")          # turned into NA on axis 0, BADCOMMAND on one axis
        return super().get_axis(key, axis)

    def _values(self, cmd, key: str, axes) -> list[str]:
        if key == "encoder.pos":
            if cmd.axis != 0:
                raise Reject("BADCOMMAND")
            return ["NA"] * len(axes if axes is not None else self.axes_of(0))
        return super()._values(cmd, key, axes)

    def set_axis(self, key: str, value: str, axes: list) -> None:
        if key not in _ATTR:
            raise Reject("BADCOMMAND")
        try:
            v = int(value)
        except ValueError:
            raise Reject("BADDATA") from None
        t = self.now()
        scope = [self.axes[i - 1] for i in axes]
        if any(a.busy(t) for a in scope):
            raise Reject("STATUSBUSY")
        for a in scope:
            if key in ("maxspeed", "accel", "limit.cycle.dist") and v <= 0:
                raise Reject("BADDATA")
            if key == "limit.min" and v > a.limit_max:
                raise Reject("BADDATA")
            if key == "limit.max" and v < a.limit_min:
                raise Reject("BADDATA")
        for a in scope:
            setattr(a, _ATTR[key], v / _NATIVE[key] if key in _NATIVE else v)
