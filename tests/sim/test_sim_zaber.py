"""Byte-exact Zaber ASCII exchanges against the simulated daisy chain."""

import serial

import gonio.sim  # noqa: F401 - registers sim://
from gonio.sim.devices.zaber_chain import lrc

from sim_helpers import exchange


def _homed(make, **kw):
    inst = make(**kw)
    z = serial.serial_for_url(inst.url("zaber"), timeout=0.5)
    exchange(z, [(b"/1 0 home", b"@01 0 OK BUSY WR 0\r\n"),
                 (b"/1 0", b"@01 0 OK BUSY WR 0\r\n"),      # instant clock jumps to the end
                 (b"/1 0", b"@01 0 OK IDLE -- 0\r\n")])
    return inst, z


def test_power_on_not_homed_and_broadcast(make):
    inst = make()
    z = serial.serial_for_url(inst.url("zaber"), timeout=0.5)
    exchange(z, [
        (b"/", b"@01 0 OK IDLE WR 0\r\n@02 0 OK IDLE -- 0\r\n"),
        (b"/0 0", b"@01 0 OK IDLE WR 0\r\n@02 0 OK IDLE -- 0\r\n"),
        (b"/1 0", b"@01 0 OK IDLE WR 0\r\n"),
        (b"/1 0 warnings", b"@01 0 OK IDLE WR 02 WR WH\r\n"),
        (b"/1 0 get pos", b"@01 0 OK IDLE WR 0 0 0 0\r\n"),
        (b"/1 2 move abs 1000", b"@01 2 RJ IDLE WR BADDATA\r\n"),
        (b"/1 0 warnings clear", b"@01 0 OK IDLE WR 02 WR WH\r\n"),
        (b"/1 0 warnings", b"@01 0 OK IDLE WR 02 WR WH\r\n"),
        (b"/9 0", b""),                                           # nobody there
    ])


def test_terminators_and_message_ids(make):
    inst, z = _homed(make)
    for end in (b"\r", b"\n", b"\r\n"):
        z.write(b"/1 0 get pos" + end)
        assert z.read(z.in_waiting) == b"@01 0 OK IDLE -- 0 0 0 0\r\n"
    exchange(z, [(b"/1 0 7 get pos", b"@01 0 07 OK IDLE -- 0 0 0 0\r\n"),
                 (b"/1 2 42 get pos", b"@01 2 42 OK IDLE -- 0\r\n"),
                 (b"/1 2 123 get pos", b"@01 2 RJ IDLE -- BADMESSAGEID\r\n")])


def test_move_get_set_and_rejections(make):
    inst, z = _homed(make)
    exchange(z, [
        (b"/1 2 move abs 64000", b"@01 2 OK BUSY -- 0\r\n"),
        (b"/1 2", b"@01 2 OK BUSY -- 0\r\n"),
        (b"/1 2 get pos", b"@01 2 OK IDLE -- 64000\r\n"),
        (b"/1 2 move rel -1000", b"@01 2 OK BUSY -- 0\r\n"),
        (b"/1 0", b"@01 0 OK BUSY -- 0\r\n"),
        (b"/1 0 get pos", b"@01 0 OK IDLE -- 0 63000 0 0\r\n"),
        (b"/1 0 get limit.cycle.dist", b"@01 0 OK IDLE -- 720000 720000 720000 720000\r\n"),
        (b"/1 0 get limit.min", b"@01 0 OK IDLE -- -190000 -176000 -360000 -350000\r\n"),
        (b"/1 4 get limit.max", b"@01 4 OK IDLE -- 350000\r\n"),
        (b"/1 0 get maxspeed", b"@01 0 OK IDLE -- 65536 65536 65536 65536\r\n"),  # 40000 microsteps/s * 1.6384
        (b"/1 1 set maxspeed 32768", b"@01 1 OK IDLE -- 0\r\n"),
        (b"/1 1 get maxspeed", b"@01 1 OK IDLE -- 32768\r\n"),
        (b"/1 1 set accel 1.5", b"@01 1 RJ IDLE -- BADDATA\r\n"),
        (b"/1 1 get accel", b"@01 1 OK IDLE -- 13107\r\n"),     # 80000 microsteps/s^2 * 0.16384
        (b"/1 0 get system.axiscount", b"@01 0 OK IDLE -- 4\r\n"),
        (b"/1 1 get system.axiscount", b"@01 1 RJ IDLE -- DEVICEONLY\r\n"),
        (b"/1 0 set system.axiscount 3", b"@01 0 RJ IDLE -- BADCOMMAND\r\n"),
        (b"/1 5 get pos", b"@01 5 RJ IDLE -- BADAXIS\r\n"),
        (b"/1 0 fly", b"@01 0 RJ IDLE -- BADCOMMAND\r\n"),
        (b"/1 0 get warp.factor", b"@01 0 RJ IDLE -- BADCOMMAND\r\n"),
        (b"/1 2 move abs 176001", b"@01 2 RJ IDLE -- BADDATA\r\n"),
        (b"/1 2 move abs ten", b"@01 2 RJ IDLE -- BADDATA\r\n"),
        (b"/1 2 move sideways 3", b"@01 2 RJ IDLE -- BADCOMMAND\r\n"),
        (b"/1 2 move abs 0", b"@01 2 OK BUSY -- 0\r\n"),
        (b"/1 2 set limit.max 1000", b"@01 2 RJ BUSY -- STATUSBUSY\r\n"),
        (b"/1 2 set accel 1000", b"@01 2 RJ BUSY -- STATUSBUSY\r\n"),
    ])


def test_checksums(make):
    inst, z = _homed(make)
    body = "1 0 get pos"
    cc = (256 - sum(body.encode()) % 256) % 256
    assert lrc(body) == cc
    exchange(z, [
        (f"/{body}:{cc:02X}".encode(), b"@01 0 OK IDLE -- 0 0 0 0\r\n"),
        (f"/{body}:{(cc + 1) % 256:02X}".encode(), b"@01 0 RJ IDLE -- BADDATA\r\n"),
        (f"/{body}:ZZ".encode(), b"@01 0 RJ IDLE -- BADDATA\r\n"),
        (b"/1 0 set comm.checksum 1", b"@01 0 OK IDLE -- 0:" + f"{lrc('01 0 OK IDLE -- 0'):02X}".encode() + b"\r\n"),
    ])
    z.write(b"/1 0 get pos\r\n")
    line = z.readline().decode().strip()
    body, cc = line[1:].split(":")
    assert body == "01 0 OK IDLE -- 0 0 0 0" and (sum(body.encode()) + int(cc, 16)) % 256 == 0


def test_stop_estop_and_ni(make):
    inst, z = _homed(make)
    exchange(z, [(b"/1 3 move abs 300000", b"@01 3 OK BUSY -- 0\r\n")])
    inst.clock.advance(1.0)     # at full speed: 0.5 s of deceleration ahead
    exchange(z, [
        (b"/1 3 stop", b"@01 3 OK BUSY NI 0\r\n"),      # decelerating
        (b"/1 3", b"@01 3 OK BUSY NI 0\r\n"),
        (b"/1 3", b"@01 3 OK IDLE NI 0\r\n"),
        (b"/1 0 warnings", b"@01 0 OK IDLE NI 01 NI\r\n"),
        (b"/1 0 warnings clear", b"@01 0 OK IDLE -- 01 NI\r\n"),  # lists what it cleared
        (b"/1 0 warnings", b"@01 0 OK IDLE -- 00\r\n"),
        (b"/1 1 move abs 100000", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/0 0 estop", b"@01 0 OK IDLE NI 0\r\n@02 0 OK IDLE -- 0\r\n"),
        (b"/1 1 move abs 0", b"@01 1 OK BUSY -- 0\r\n"),    # from rest: clears NI
        (b"/1 1", b"@01 1 OK BUSY -- 0\r\n"),
        (b"/1 1 get pos", b"@01 1 OK IDLE -- 0\r\n"),
    ])
    # the stop decelerated: the axis stopped short of the target, past where stop was sent
    z.write(b"/1 3 get pos\r\n")
    pos = int(z.readline().split()[-1])
    assert 0 < pos < 300000


def test_led_device(make):
    inst = make()
    z = serial.serial_for_url(inst.url("zaber"), timeout=0.5)
    exchange(z, [
        # issue 17: lamp.status 1 off / 2 on, as zaber-motion's IlluminatorChannel.is_on() reads
        # it (only 2 is "on"); these two lines used to assert 0 / 1
        (b"/2 0 get lamp.status", b"@02 0 OK IDLE -- 1\r\n"),
        (b"/2 0 lamp on", b"@02 0 OK IDLE -- 0\r\n"),
        (b"/2 0 get lamp.status", b"@02 0 OK IDLE -- 2\r\n"),
        (b"/2 0 set lamp.flux 0.8", b"@02 0 OK IDLE -- 0\r\n"),
        (b"/2 0 get lamp.flux", b"@02 0 OK IDLE -- 0.800\r\n"),
        (b"/2 0 set lamp.flux 1.5", b"@02 0 RJ IDLE -- BADDATA\r\n"),
        (b"/2 0 get lamp.temperature", b"@02 0 OK IDLE -- 25.0\r\n"),
        # issue 17: a channel is an axis (zaber-motion's Illuminator sends /2 1 lamp on);
        # this line used to assert DEVICEONLY, which the corrected protocol note refutes
        (b"/2 1 lamp on", b"@02 1 OK IDLE -- 0\r\n"),
        (b"/2 2 lamp on", b"@02 2 RJ IDLE -- BADAXIS\r\n"),
        (b"/2 0 lamp dim", b"@02 0 RJ IDLE -- BADDATA\r\n"),
        (b"/2 0 move abs 5", b"@02 0 RJ IDLE -- BADCOMMAND\r\n"),
        (b"/2 0 get system.axiscount", b"@02 0 OK IDLE -- 1\r\n"),
        (b"/2 0 lamp off", b"@02 0 OK IDLE -- 0\r\n"),
    ])
    assert inst.lamp.power(inst.clock.now()) == 0.0


def test_lamp_temperature_rises_over_minutes(make):
    inst = make()
    z = serial.serial_for_url(inst.url("zaber"), timeout=0.5)
    exchange(z, [(b"/2 0 lamp on", b"@02 0 OK IDLE -- 0\r\n")])
    inst.clock.advance(600.0)
    exchange(z, [(b"/2 0 get lamp.temperature", b"@02 0 OK IDLE -- 39.9\r\n")])


def test_readline_equals_pyserials_byte_by_byte_reads(make):
    """sim:// reads a line in one search of the buffer (protocol_sim.Serial.read_until); it
    must give the bytes and cost the simulated time of pyserial's own read_until, which reads
    one byte at a time (and of io's readline): whole lines, a line cut by ``size``, a
    terminator of two bytes, a partial line (no terminator: the timeout is spent once),
    an empty buffer, and a motion's alert that comes due while the host waits."""
    from serial.serialutil import SerialBase

    def session(read_until):
        inst = make()
        z = serial.serial_for_url(inst.url("zaber"), timeout=0.5)
        out = []

        def take(*a, **k):
            out.append((read_until(z, *a, **k), round(inst.clock.now(), 9)))

        z.write(b"/\r\n")                          # two lines waiting
        take()
        take(b"\r\n")
        z.write(b"/1 0 get pos\r\n")
        take(size=7)
        take(b"WR")
        take(b"\n", 3)
        take()
        take()                                     # nothing there: the timeout, once
        z.write(b"/1 0 home\r\n/1 set comm.alert 1\r\n")
        take(), take()
        take()                                     # waits: the alert comes due meanwhile
        z.write(b"/1 0 get pos\r\n")
        inst.ports["zaber"].out.extend(b"@01 0 partial")   # a line without its end
        for _ in range(4):
            take(b"\r\n")
        return out

    fast = session(lambda z, *a, **k: z.read_until(*a, **k))
    per_byte = session(lambda z, *a, **k: SerialBase.read_until(z, *a, **k))
    assert fast == per_byte, (fast, per_byte)
    assert fast[0][0] == b"@01 0 OK IDLE WR 0\r\n" and fast[1][0] == b"@02 0 OK IDLE -- 0\r\n"
    assert fast[2][0] == b"@01 0 O" and fast[6] == (b"", fast[5][1] + 0.5)
    assert any(b"!01" in line for line, _ in fast), fast       # the alert arrived through a read
    # readline(size) against io's, which also reads a byte at a time (terminator b"\n" only)
    import io

    lines = session(lambda z, *a, **k: z.readline(k.get("size", a[1] if len(a) > 1 else -1)))
    io_lines = session(lambda z, *a, **k: io.RawIOBase.readline(z, k.get("size", a[1] if len(a) > 1 else -1)))
    assert lines == io_lines and len({x[0] for x in lines}) > 4
