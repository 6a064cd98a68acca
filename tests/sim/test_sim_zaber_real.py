"""Byte-exact exchanges of what issue 17 added to the simulated Zaber chain.

Formats from Zaber's ASCII protocol manual (reply, alert ``!DD A STATUS WARN``, continuation
``...\\`` + ``#DD A [ID] cont ...``, ``NA``); values from gonio/sim/devices/zaber_stage.py and
gonio/sim/devices/zaber_led.py (several invented where the documents are silent, marked there).
"""

import serial

import gonio.sim  # noqa: F401 - registers sim://
from gonio.sim.devices.zaber_chain import lrc

from sim_helpers import exchange


def _homed(make, **kw):
    inst = make(**kw)
    inst.home_all()
    return inst, serial.serial_for_url(inst.url("zaber"), timeout=0.5)


def test_identification(make):
    inst = make()
    z = serial.serial_for_url(inst.url("zaber"), timeout=0.5)
    exchange(z, [
        (b"/1 0 01 get comm.packet.size.max:CF", b"@01 0 01 OK IDLE WR 80\r\n"),
        (b"/1 0 get deviceid", b"@01 0 OK IDLE WR 30342\r\n"),
        (b"/1 0 get system.serial", b"@01 0 OK IDLE WR 91001\r\n"),
        (b"/1 0 get version", b"@01 0 OK IDLE WR 7.38\r\n"),
        (b"/1 0 get version.build", b"@01 0 OK IDLE WR 15708\r\n"),
        (b"/1 0 get get.settings.max", b"@01 0 OK IDLE WR 12\r\n"),
        (b"/1 2 get resolution", b"@01 2 OK IDLE WR 64\r\n"),
        (b"/1 0 get peripheralid", b"@01 0 OK IDLE WR 0 0 0 0\r\n"),      # no product has 720000/turn
        (b"/1 1 get peripheral.id", b"@01 1 OK IDLE WR 0\r\n"),
        (b"/1 1 get deviceid", b"@01 1 RJ IDLE WR DEVICEONLY\r\n"),
        (b"/1 0 set deviceid 5", b"@01 0 RJ IDLE WR BADCOMMAND\r\n"),
        (b"/1 1 get pos limit.max maxspeed", b"@01 1 OK IDLE WR 0 ; 190000 ; 65536\r\n"),
        # issue 40: multi-get as zaber-motion sends it (axis runs on axis 0), settings split by ";"
        (b"/1 0 get 2 maxspeed pos", b"@01 0 OK IDLE WR 65536 ; 0\r\n"),
        (b"/1 0 get deviceid 1 2 limit.max 4 pos", b"@01 0 OK IDLE WR 30342 ; 190000 176000 ; 0\r\n"),
        (b"/1 0 get 5 pos", b"@01 0 RJ IDLE WR BADAXIS\r\n"),
        (b"/1 0 get pos 2", b"@01 0 RJ IDLE WR BADCOMMAND\r\n"),
        (b"/1 1 get 2 pos", b"@01 1 RJ IDLE WR BADCOMMAND\r\n"),
        (b"/1 0 get 2 deviceid", b"@01 0 RJ IDLE WR DEVICEONLY\r\n"),
        (b"/1 1 get " + b"pos " * 12 + b"pos", b"@01 1 RJ IDLE WR BADDATA\r\n"),
        (b"/2 0 get deviceid", b"@02 0 OK IDLE -- 30311\r\n"),
        (b"/0 0 get system.serial", b"@01 0 OK IDLE WR 91001\r\n@02 0 OK IDLE -- 92001\r\n"),
    ])


def test_led_channels(make):
    inst = make(lamp={"flux_max": 2.5})
    z = serial.serial_for_url(inst.url("zaber"), timeout=0.5)
    exchange(z, [
        (b"/2 1 get lamp.status", b"@02 1 OK IDLE -- 1\r\n"),
        (b"/2 1 lamp on", b"@02 1 OK IDLE -- 0\r\n"),
        (b"/2 1 get lamp.status", b"@02 1 OK IDLE -- 2\r\n"),
        (b"/2 1 get lamp.flux.max", b"@02 1 OK IDLE -- 2.500\r\n"),
        (b"/2 1 set lamp.flux 1.000000000", b"@02 1 OK IDLE -- 0\r\n"),
        (b"/2 1 get lamp.flux", b"@02 1 OK IDLE -- 1.000\r\n"),
        (b"/2 1 set lamp.flux 2.6", b"@02 1 RJ IDLE -- BADDATA\r\n"),
        (b"/2 1 set lamp.flux nan", b"@02 1 RJ IDLE -- BADDATA\r\n"),
        (b"/2 1 set lamp.flux -0.1", b"@02 1 RJ IDLE -- BADDATA\r\n"),
        (b"/2 1 set lamp.flux.max 3", b"@02 1 RJ IDLE -- BADCOMMAND\r\n"),
        (b"/2 2 lamp on", b"@02 2 RJ IDLE -- BADAXIS\r\n"),
        (b"/2 0 lamp off", b"@02 0 OK IDLE -- 0\r\n"),
        (b"/2 1 get lamp.status", b"@02 1 OK IDLE -- 1\r\n"),
    ])
    assert inst.lamp.flux == 0.4 and not inst.lamp.on


def test_alerts_when_enabled(make):
    inst, z = _homed(make)
    exchange(z, [(b"/1 2 move abs 1000", b"@01 2 OK BUSY -- 0\r\n"),
                 (b"/1 2", b"@01 2 OK BUSY -- 0\r\n"),          # alerts off: nothing else
                 (b"/1 0 set comm.alert 1", b"@01 0 OK IDLE -- 0\r\n"),
                 (b"/1 1 set comm.alert 1", b"@01 1 RJ IDLE -- DEVICEONLY\r\n"),
                 (b"/1 0 set comm.alert 2", b"@01 0 RJ IDLE -- BADDATA\r\n"),
                 (b"/1 2 move abs 2000", b"@01 2 OK BUSY -- 0\r\n"),
                 (b"/1 2", b"@01 2 OK BUSY -- 0\r\n!01 2 IDLE --\r\n"),      # the jump ends the move
                 (b"/1 0 home", b"@01 0 OK BUSY -- 0\r\n"),        # only axis 2 is off home
                 (b"/1 0 stop", b"@01 0 OK BUSY NI 0\r\n"),
                 # the deceleration ended before this poll: its alert comes before the reply
                 (b"/1 0", b"!01 2 IDLE NI\r\n@01 0 OK IDLE NI 0\r\n")])
    z.write(b"/1 0 set comm.checksum 1\r\n"), z.read(z.in_waiting)
    inst.zaber.stage.alert = 1
    z.write(b"/1 3 move abs 5000\r\n/1 3\r\n")
    lines = z.read(1000).split(b"\r\n")
    body = "01 3 IDLE --"
    assert lines[2] == f"!{body}:{lrc(body):02X}".encode()


def test_continued_reply(make):
    inst, z = _homed(make)
    inst.zaber.packet_size_max = 40
    exchange(z, [(b"/1 0 07 get limit.max", b"@01 0 07 OK IDLE -- 190000 176000\\\r\n#01 0 07 cont 360000 350000\r\n"),
                 (b"/1 0 get pos", b"@01 0 OK IDLE -- 0 0 0 0\r\n")])
    inst.zaber.packet_size_max = 24              # the floor: one word per packet
    z.write(b"/1 0 get limit.max\r\n")
    assert z.read(z.in_waiting) == (b"@01 0 OK IDLE -- 190000\\\r\n#01 0 cont 176000\\\r\n"
                                    b"#01 0 cont 360000\\\r\n#01 0 cont 350000\r\n")


def test_na_vel_driver_parking(make):
    inst, z = _homed(make)
    exchange(z, [
        (b"/1 0 get encoder.pos", b"@01 0 OK IDLE -- NA NA NA NA\r\n"),
        (b"/1 1 get encoder.pos", b"@01 1 RJ IDLE -- BADCOMMAND\r\n"),
        (b"/1 1 move vel 20000", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1 stop", b"@01 1 OK BUSY NI 0\r\n"),
        (b"/1 1 move vel 1000001", b"@01 1 RJ IDLE NI BADDATA\r\n"),    # stopped 1 ms after the start
        (b"/1 1 move vel fast", b"@01 1 RJ IDLE NI BADDATA\r\n"),
        (b"/1 1", b"@01 1 OK IDLE NI 0\r\n"),
        (b"/1 1 move vel -40000", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1 get pos", b"@01 1 OK IDLE -- -190000\r\n"),         # came to rest at limit.min
        (b"/1 2 driver disable", b"@01 2 OK IDLE FD 0\r\n"),
        (b"/1 2 move abs 10", b"@01 2 RJ IDLE FD DRIVERDISABLED\r\n"),
        (b"/1 2 get driver.enabled", b"@01 2 OK IDLE FD 0\r\n"),
        (b"/1 2 driver on", b"@01 2 RJ IDLE FD BADCOMMAND\r\n"),
        (b"/1 2 driver enable", b"@01 2 OK IDLE -- 0\r\n"),
        (b"/1 3 tools parking park", b"@01 3 OK IDLE -- 0\r\n"),
        (b"/1 3 get parking.state", b"@01 3 OK IDLE -- 1\r\n"),
        (b"/1 3 move abs 10", b"@01 3 RJ IDLE -- PARKED\r\n"),
        (b"/1 3 tools parking", b"@01 3 RJ IDLE -- BADCOMMAND\r\n"),
    ])
    inst.power_cycle(1)                           # a parked axis keeps its reference
    exchange(z, [(b"/1 3 tools parking unpark", b"@01 3 OK IDLE -- 0\r\n"),   # axis 3 kept its reference
                 (b"/1 3 warnings", b"@01 3 OK IDLE -- 00\r\n"),
                 (b"/1 1 warnings", b"@01 1 OK IDLE WR 02 WR WH\r\n")])


def test_move_with_speed_and_acceleration_bounds(make):
    """Issue 40: ``move abs|rel POS [SPEED [ACCEL]]``, ``move min|max [SPEED [ACCEL]]``,
    ``move vel SPEED [ACCEL]`` (native units; 0 keeps the axis's setting); a negative or
    too-large value, or a word too many, is BADDATA and nothing moves."""
    inst, z = _homed(make)
    exchange(z, [(b"/1 2 move abs 1000 -5", b"@01 2 RJ IDLE -- BADDATA\r\n"),
                 (b"/1 2 move abs 1000 5 1000001", b"@01 2 RJ IDLE -- BADDATA\r\n"),
                 (b"/1 2 move abs 1000 5 5 5", b"@01 2 RJ IDLE -- BADDATA\r\n"),
                 (b"/1 2 move max 5 5 5", b"@01 2 RJ IDLE -- BADDATA\r\n"),
                 (b"/1 2 get pos", b"@01 2 OK IDLE -- 0\r\n"),
                 (b"/1 2 move rel 1000 0 0", b"@01 2 OK BUSY -- 0\r\n")])
    a = inst.axes[1]
    assert (a.maxspeed, a.accel) == (40000, 80000)
