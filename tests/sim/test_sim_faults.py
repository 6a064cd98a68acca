"""Every fault of the schedule shows on the wire when scheduled; same seed, same bytes."""

import hashlib

import pytest
import rawpy
import serial

import gonio.sim as gs
from sim_helpers import DIFFUSE


def _z(port, cmd):
    port.write(cmd.encode() + b"\r\n")
    return port.readline()


def _homed(make, faults, **kw):
    inst = make(faults=faults, **kw)
    inst.home_all()
    return inst, inst.open("zaber", timeout=0.2)


def test_toml_schedule_parses_and_validates(tmp_path):
    text = """
seed = 3
[[fault]]
kind = "timeout"
at_command = [2, 4]
[[fault]]
kind = "silence"
port = "meter"
at_time = 5.0
duration = 2.0
"""
    p = tmp_path / "faults.toml"
    p.write_text(text)
    for src in (str(p), text, p):
        s = gs.FaultSchedule.from_toml(src)
        assert s.seed == 3 and [f.kind for f in s.faults] == ["timeout", "silence"]
        assert s.faults[0].at_command == (2, 4)
    with pytest.raises(ValueError):
        gs.FaultSchedule([{"kind": "meteor", "at_command": 1}])
    with pytest.raises(ValueError):
        gs.FaultSchedule([{"kind": "again", "port": "meter", "at_command": 1}])
    with pytest.raises(ValueError):
        gs.FaultSchedule([{"kind": "timeout"}])


def test_timeout_on_nth_command(make):
    inst, z = _homed(make, [{"kind": "timeout", "at_command": [2, 3], "execute": True}])
    assert _z(z, "/1 0") == b"@01 0 OK IDLE -- 0\r\n"
    t0 = inst.clock.now()
    assert _z(z, "/1 0") == b""                       # readline ran into the timeout
    assert inst.clock.now() - t0 == pytest.approx(0.2 + inst.clock.latency)
    assert _z(z, "/1 1 move abs 1000") == b""         # lost reply, but the move happened
    assert _z(z, "/1 1") == b"@01 1 OK BUSY -- 0\r\n"
    assert _z(z, "/1 1 get pos") == b"@01 1 OK IDLE -- 1000\r\n"


def test_silence_for_a_while(make):
    inst, z = _homed(make, [{"kind": "silence", "at_command": 2, "duration": 1.0}])
    assert _z(z, "/1 0").startswith(b"@01")
    assert _z(z, "/1 0") == b""
    assert _z(z, "/1 0") == b""                       # 0.2 s timeouts: still silent
    inst.clock.advance(1.0)
    assert _z(z, "/1 0") == b"@01 0 OK IDLE -- 0\r\n"


def test_garbled_and_truncated_lines(make):
    inst, z = _homed(make, [{"kind": "garble", "at_command": 1},
                            {"kind": "truncate", "at_command": 2}])
    good = b"@01 0 OK IDLE -- 0 0 0 0\r\n"
    g = _z(z, "/1 0 get pos")
    assert g != good and len(g) == len(good) and g.endswith(b"\r\n")
    z.write(b"/1 0 get pos\r\n")
    t = z.read(100)                                    # no terminator: read runs out
    assert good.startswith(t) and len(t) < len(good) - 2
    assert _z(z, "/1 0 get pos") == good


def test_bad_reply_checksum(make):
    inst, z = _homed(make, [{"kind": "bad_checksum", "at_command": 1}])
    line = _z(z, "/1 0").decode().strip()
    body, cc = line[1:].split(":")
    assert body == "01 0 OK IDLE -- 0"
    assert (sum(body.encode()) + int(cc, 16)) % 256 != 0


def test_rj_again_does_not_execute(make):
    inst, z = _homed(make, [{"kind": "again", "at_command": 1}])
    assert _z(z, "/1 1 5 move abs 1000") == b"@01 1 05 RJ IDLE -- AGAIN\r\n"
    assert _z(z, "/1 1 get pos") == b"@01 1 OK IDLE -- 0\r\n"


@pytest.mark.parametrize("kind,flag", [("stall", "FS"), ("limit", "WL")])
def test_stall_and_unexpected_limit(make, kind, flag):
    inst, z = _homed(make, [{"kind": kind, "at_command": 1, "axis": 2, "fraction": 0.5}])
    assert _z(z, "/1 2 move abs 100000") == b"@01 2 OK BUSY -- 0\r\n"
    assert _z(z, "/1 2") == b"@01 2 OK BUSY -- 0\r\n"
    assert _z(z, "/1 2") == f"@01 2 OK IDLE {flag} 0\r\n".encode()
    pos = int(_z(z, "/1 2 get pos").split()[-1])
    assert 0 < pos < 100000
    assert _z(z, "/1 2 warnings clear") == f"@01 2 OK IDLE -- 01 {flag}\r\n".encode()


def test_power_cycle_loses_positions(make):
    inst, z = _homed(make, [{"kind": "power_cycle", "at_command": 3}])
    assert _z(z, "/1 3 move abs 20000") == b"@01 3 OK BUSY -- 0\r\n"
    assert _z(z, "/1 3") == b"@01 3 OK BUSY -- 0\r\n"
    assert _z(z, "/1 0 get pos") == b"@01 0 OK IDLE WR 0 0 0 0\r\n"     # counter lost
    assert _z(z, "/1 3 move abs 0") == b"@01 3 RJ IDLE WR BADDATA\r\n"
    assert inst.pose_microsteps()[2] == 20000                            # physically there
    _z(z, "/1 0 home"), _z(z, "/1 0")
    assert _z(z, "/1 0") == b"@01 0 OK IDLE -- 0\r\n"
    assert inst.pose_microsteps() == (0, 0, 0, 0)


def test_port_vanishes_and_comes_back(make):
    inst = make(faults=[{"kind": "vanish", "port": "meter", "at_command": 2, "duration": 1.0}])
    m = inst.open("meter", timeout=0.2)
    m.write(b"*IDN?\n")
    assert m.readline().startswith(b"Thorlabs")
    m.write(b"*IDN?\n")
    with pytest.raises(serial.SerialException):
        m.readline()
    with pytest.raises(serial.SerialException):
        m.write(b"*IDN?\n")                           # the old handle stays dead
    m.close()
    reopened = None
    for _ in range(30):                               # each failed open costs 0.1 s simulated
        try:
            reopened = inst.open("meter", timeout=0.2)
            break
        except serial.SerialException:
            pass
    assert reopened is not None and inst.clock.now() >= 1.0
    reopened.write(b"*IDN?\n")
    assert reopened.readline().startswith(b"Thorlabs")


@pytest.mark.parametrize("kind", ["camera_nothing", "camera_truncated"])
def test_camera_faults(make, tmp_path, kind):
    inst = make(sample=DIFFUSE, faults=[{"kind": kind, "at_command": 2}])
    inst.home_all()
    c = inst.open("camera", timeout=0.5)
    for i in range(3):
        c.write(f"EXPOSE 0.01 {tmp_path}/f{i}.dng\n".encode())
        ok, digest = c.readline().decode().split()
        assert ok == "OK"
        path = tmp_path / f"f{i}.dng"
        if i != 1:
            assert hashlib.sha256(path.read_bytes()).hexdigest() == digest
        elif kind == "camera_nothing":
            assert not path.exists()
        else:
            assert hashlib.sha256(path.read_bytes()).hexdigest() != digest
            with pytest.raises(Exception):
                with rawpy.imread(str(path)) as r:
                    r.raw_image_visible.copy()


def test_lamp_dies(make):
    inst = make(faults=[{"kind": "lamp_dies", "at_time": 10.0}])
    z, m = inst.open("zaber", timeout=0.2), inst.open("meter", timeout=0.2)
    _z(z, "/2 0 lamp on")
    m.write(b"MEAS:POW?\n")
    assert float(m.readline()) > 5e-4
    inst.clock.advance(20.0)
    m.write(b"MEAS:POW?\n")
    assert abs(float(m.readline())) < 1e-7
    # controller unaware (2 = on, as zaber-motion reads lamp.status; issue 17: was 1)
    assert _z(z, "/2 0 get lamp.status") == b"@02 0 OK IDLE -- 2\r\n"


def test_probability_faults_are_seeded(make):
    sched = [{"kind": "garble", "probability": 0.2}, {"kind": "again", "probability": 0.1}]

    def run():
        inst, z = _homed(make, sched)
        return b"".join(_z(z, f"/1 {1 + k % 4} get pos") for k in range(60))

    a, b = run(), run()
    assert a == b
    assert b"AGAIN" in a and a.count(b"\r\n") <= 60


SCHEDULE = """
[[fault]]
kind = "garble"
probability = 0.15
[[fault]]
kind = "truncate"
port = "meter"
at_command = [3, 7]
[[fault]]
kind = "stall"
at_command = 6
[[fault]]
kind = "camera_truncated"
at_command = 2
"""


def _session(make, folder):
    inst = make(sample=DIFFUSE, faults=SCHEDULE, seed=11)
    z, m, c = (inst.open(p, timeout=0.1) for p in ("zaber", "meter", "camera"))
    wire = []
    for cmd in ("/1 0 home", "/1 0", "/1 0", "/2 0 lamp on", "/1 4 move abs 60000",
                "/1 1 move abs -30000", "/1 0", "/1 0", "/1 0 warnings"):
        z.write(cmd.encode() + b"\r\n")
        wire.append(z.read(200))
    for k in range(3):
        m.write(b"MEAS:POW?\n")
        wire.append(m.read(100))
        c.write(f"EXPOSE 0.01 {folder}/f{k}.dng\n".encode())
        wire.append(c.readline())
    files = [(folder / f"f{k}.dng").read_bytes() for k in range(3)]
    return wire, files


def test_same_seed_and_schedule_give_identical_bytes_and_files(make, tmp_path):
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    wa, fa = _session(make, tmp_path / "a")
    wb, fb = _session(make, tmp_path / "b")
    assert wa == wb and fa == fb
    assert any(b"FS" in w for w in wa)                 # the stall showed up
