"""gonio.sim: a simulated gonioreflectometer that speaks the real instrument's bytes.

Physics (:mod:`.physics`: stages, lamp, sensor, scene and sample, the meter's in
``devices.scpi_meter``) is kept apart from the protocol servers (:mod:`.devices`: Zaber chain,
SCPI meter, camera port) and the transports (``protocol_sim`` for ``sim://`` URLs,
``pty_server`` for pseudo-terminals). Importing this package registers the ``sim://`` scheme
with pyserial (``serial.protocol_handler_packages``); ``serve`` exposes the same ports on
pseudo-terminals for another process::

    import serial, gonio.sim
    inst = gonio.sim.Instrument(seed=1).register("bench")
    zaber = serial.serial_for_url("sim://bench/zaber", timeout=1)
    zaber.write(b"/1 0 home\\r\\n"); zaber.readline()    # b"@01 0 OK BUSY WR 0\\r\\n"

What a driver must know (homing, native units, the clock, checksums, camera, meter): below.
"""

# What a driver must know
# * Axes power on un-homed (WR, WH) at a seeded position within 20 deg of home; every move is
#   rejected (RJ IDLE WR BADDATA) until home.
# * maxspeed and move vel are in Zaber's native unit, microsteps/s * 1.6384 (default
#   65536 = 40000 microsteps/s = 20 deg/s), accel in microsteps/s^2 * 1.6384 / 10 (default
#   13107 = 80000 microsteps/s^2); limit.cycle.dist 720000; deg = pos * 360 / cycle_dist.
# * Instant clock (default): each command line costs 1 ms of simulated time; a BUSY reply to a
#   poll, get or warnings moves the clock to the end of the motion, so the next poll reads IDLE;
#   an exposure advances the clock by its duration; a read that waits for missing bytes advances
#   it by the port timeout. Nothing sleeps. SimClock("scaled", scale=s) runs in (scaled) wall
#   time.
# * Several settings in one get (zaber-motion's get_many / get_synchronized): "/1 0 get 2 maxspeed
#   pos" -> "@01 0 OK IDLE -- 65536 ; 0", the settings' values separated by ";" (get.settings.max
#   12); moves take their own speed and acceleration: "move abs POS SPEED ACCEL".
# * Each port is its own device: one device's slow answer (meter averaging, camera exposing)
#   never delays another's; with a scaled clock an alert leaves when its motion ends.
# * Replies carry :CC only after "set comm.checksum 1" (and in the bad_checksum fault); a command
#   with a wrong :CC gets RJ ... BADDATA.
# * Camera: SENSOR? -> "64 48 14 512 16383 RGGB"; gain 2 e-/DN, read noise 3 e-, dark current
#   20 e-/s, DSNU 1.5 e-, PRNU 1 %; a white Lambertian at normal incidence fills half the well
#   (15871 e-) in 10 ms at full flux.
# * Power meter: MEAS:POW? = lamp power * 0.1 * 550 nm / wavelength setting + noise (5e-4
#   relative, 2e-9 W absolute, / sqrt(average count)); full flux about 1e-3 W.

import serial as _serial

from gonio.sim.physics.clock import SimClock
from gonio.sim.physics.errors import PRESETS as ERROR_PRESETS
from gonio.sim.physics.errors import ErrorModel, error_model
from gonio.sim.physics.faults import FaultSchedule
from gonio.sim.instrument import DEFAULT_REFERENCE, DEFAULT_SAMPLE, DEFAULT_SETTINGS, Instrument, lookup
from gonio.sim.physics.kinematics import forward
from gonio.sim.physics.lamp import Lamp
from gonio.sim.pty_server import PtyServer, serve
from gonio.sim.physics.sample import SampleTruth, mitsuba_variant
from gonio.sim.physics.sensor import SensorModel
from gonio.sim.physics.stages import RotaryAxis, plan_trapezoid

if "gonio.sim" not in _serial.protocol_handler_packages:
    _serial.protocol_handler_packages.append("gonio.sim")


__all__ = [
    "DEFAULT_REFERENCE", "DEFAULT_SAMPLE", "DEFAULT_SETTINGS", "ERROR_PRESETS", "ErrorModel", "FaultSchedule",
    "Instrument", "error_model",
    "Lamp", "PtyServer", "RotaryAxis", "SampleTruth", "SensorModel", "SimClock", "forward", "lookup",
    "mitsuba_variant", "plan_trapezoid", "serve",
]
