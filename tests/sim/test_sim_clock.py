"""The simulated clock: instant and scaled modes, specs; serve() in another process."""

import os
import signal
import subprocess
import sys

import pytest
import serial

import gonio.sim as gs
from gonio.sim.physics import clock as _clock


def test_instant_clock_never_sleeps(monkeypatch):
    monkeypatch.setattr(_clock.time, "sleep", lambda s: pytest.fail("slept"))
    c = gs.SimClock("instant", latency=0.002)
    c.advance(5.0)
    c.tick()
    c.advance_to(4.0)                 # the past: no-op
    assert c.now() == pytest.approx(5.002)


def test_scaled_clock_follows_wall_time(monkeypatch):
    wall = [100.0]
    slept = []
    monkeypatch.setattr(_clock.time, "monotonic", lambda: wall[0])
    monkeypatch.setattr(_clock.time, "sleep", lambda s: slept.append(s))
    c = gs.SimClock("scaled", scale=10.0)
    wall[0] += 2.0
    assert c.now() == pytest.approx(20.0)
    c.advance(5.0)
    assert slept == [pytest.approx(0.5)]


@pytest.mark.parametrize("spec,mode,scale", [(None, "instant", 1.0), ("instant", "instant", 1.0),
                                             ("real", "scaled", 1.0), ("scaled:25", "scaled", 25.0),
                                             (4, "scaled", 4.0)])
def test_clock_specs(spec, mode, scale):
    c = gs.SimClock.coerce(spec)
    assert c.mode == mode and c.scale == scale
    with pytest.raises(ValueError):
        gs.SimClock.coerce("sundial")


def test_serve_in_another_process(tmp_path):
    code = ("import gonio.sim as gs; "
            f"gs.serve(seed=2, clock='scaled:100', link_dir={str(tmp_path)!r})")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        lines = [proc.stdout.readline().split() for _ in range(3)]
        paths = {ln[0]: ln[1] for ln in lines}
        assert set(paths) == {"zaber", "meter", "camera"}
        z = serial.Serial(paths["zaber"], 115200, timeout=5)
        z.write(b"/1 0 get system.axiscount\r\n")
        assert z.readline() == b"@01 0 OK IDLE WR 4\r\n"
        z.close()
        c = serial.Serial(paths["camera"], timeout=5)
        c.write(b"SENSOR?\n")
        assert c.readline() == b"64 48 14 512 16383 RGGB\n"
        c.close()
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert not os.path.exists(paths["zaber"])          # links removed on exit
