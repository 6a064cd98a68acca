"""The pseudo-terminal server: same bytes as sim://, survives reconnects, vanishing ports."""

import os
import time

import pytest
import serial

import gonio.sim as gs
from gonio.sim.pty_server import PtyServer


def _ask(port, cmd, end=b"\r\n"):
    port.write(cmd + end)
    return port.readline()


@pytest.fixture
def server(tmp_path):
    srv = gs.serve(seed=1, clock=gs.SimClock("instant"), link_dir=str(tmp_path / "ports"),
                   block=False, echo=None)
    yield srv
    srv.stop()


def test_ports_answer_and_survive_reconnect(server):
    assert set(server.paths) == {"zaber", "meter", "camera"}
    for name, path in server.paths.items():
        assert os.path.islink(path) and os.readlink(path).startswith("/dev/pts/")
    z = serial.Serial(server.paths["zaber"], 115200, timeout=2)
    assert _ask(z, b"/1 0") == b"@01 0 OK IDLE WR 0\r\n"
    assert _ask(z, b"/1 0 home") == b"@01 0 OK BUSY WR 0\r\n"
    z.close()                                           # client goes away mid-session
    z = serial.Serial(server.paths["zaber"], 9600, timeout=2)
    assert _ask(z, b"/1 0") == b"@01 0 OK BUSY WR 0\r\n"
    assert _ask(z, b"/1 0") == b"@01 0 OK IDLE -- 0\r\n"
    z.close()
    m = serial.Serial(server.paths["meter"], timeout=2)
    assert _ask(m, b"*IDN?", b"\n") == b"Thorlabs,PM100D,P0000001,2.8.0\n"
    m.close()


def test_vanishing_port_comes_back_under_a_new_device(tmp_path):
    inst = gs.Instrument(seed=1, faults=[{"kind": "vanish", "port": "meter", "at_command": 2,
                                          "duration": 0.3}])
    with PtyServer(inst, str(tmp_path / "p")).start() as srv:
        path = srv.paths["meter"]
        m = serial.Serial(path, timeout=0.5)
        assert _ask(m, b"*IDN?", b"\n").startswith(b"Thorlabs")
        m.write(b"*IDN?\n")
        with pytest.raises(serial.SerialException):
            for _ in range(50):
                m.read(1)
                time.sleep(0.01)
        m.close()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not os.path.exists(path):
            time.sleep(0.02)
        assert os.path.exists(path)
        m = serial.Serial(path, timeout=1)
        assert _ask(m, b"*IDN?", b"\n").startswith(b"Thorlabs")
        m.close()


def test_camera_exposes_through_the_pty(server, tmp_path):
    import hashlib

    c = serial.Serial(server.paths["camera"], timeout=10)
    reply = _ask(c, f"EXPOSE 0.01 {tmp_path}/frame.dng".encode(), b"\n").decode().split()
    assert reply[0] == "OK"
    assert hashlib.sha256((tmp_path / "frame.dng").read_bytes()).hexdigest() == reply[1]
    c.close()


def test_a_client_that_never_reads_does_not_stop_the_other_ports(server):
    """Issue 36, probe 4: a client floods the Zaber port and never reads its replies. The
    server kept retrying its write to that pty and stopped serving every other port; now it
    writes what the pty takes, keeps at most MAX_PENDING bytes for that client (the oldest
    whole lines dropped, counted) and the meter answers at once."""
    import gonio.sim.pty_server as ps

    z = serial.Serial(server.paths["zaber"], 115200, timeout=2, write_timeout=5)
    m = serial.Serial(server.paths["meter"], timeout=5)    # an answer within 5 s: served, not stuck
    for _ in range(100):                       # 10000 commands: ~250 kB of replies, never read
        z.write(b"/1 0\r\n" * 100)
    deadline = time.monotonic() + 10.0
    while getattr(server, "dropped", {}).get("zaber", 0) == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _ask(m, b"*IDN?", b"\n").startswith(b"Thorlabs,PM100D,"), "the meter did not answer while the flood waited"
    assert server.dropped.get("zaber", 0) > 0, "the flood never overran the client's buffer"
    assert len(server._pending.get("zaber", b"")) <= ps.MAX_PENDING
    z.reset_input_buffer()
    z.close()
    m.close()
