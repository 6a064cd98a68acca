"""Trapezoidal motion timing of the simulated stages."""

import math

import numpy as np
import pytest
import serial

import gonio.sim as gs
from gonio.sim.physics.stages import RotaryAxis, plan_trapezoid


def _axis(**kw):
    a = RotaryAxis(limit_min=-10**6, limit_max=10**6, cycle_dist=720000, **kw)
    a.homed = True
    return a


@pytest.mark.parametrize("dist", [1000, 20000, 72000, 500000])
def test_duration_matches_trapezoid(dist):
    vmax, acc = 40000.0, 80000.0
    segs = plan_trapezoid(0.0, 0.0, dist, vmax, acc)
    if dist >= vmax ** 2 / acc:
        expected = dist / vmax + vmax / acc
    else:
        expected = 2 * math.sqrt(dist / acc)
    assert segs[-1].t1 == pytest.approx(expected, rel=1e-12)
    assert segs[-1].x(segs[-1].t1) == pytest.approx(dist, abs=1e-6)


def test_position_follows_profile():
    a = _axis()
    a.move_abs(10.0, 72000)                 # accel 0.5 s, cruise 1.3 s, decel 0.5 s
    assert a.busy(10.0)
    assert a.position(10.25) == round(0.5 * 80000 * 0.25 ** 2)
    assert a.position(10.5) == 10000
    assert a.position(11.0) == 10000 + 20000
    assert a.velocity(11.0) == pytest.approx(40000)
    assert a.position(12.3 - 0.25) == round(72000 - 0.5 * 80000 * 0.25 ** 2)
    assert a.busy(12.2999)
    assert not a.busy(12.3)
    assert a.position(13.0) == 72000


def test_stop_decelerates_and_estop_halts():
    a = _axis()
    a.move_abs(0.0, 200000)
    a.stop(1.0)                             # at 40000 usteps/s: 0.5 s and 10000 usteps to rest
    assert a.end_time(1.0) == pytest.approx(1.5)
    assert a.position(2.0) == round(10000 + 40000 * 0.5 + 10000)
    assert "NI" in a.active_flags(2.0)
    b = _axis()
    b.move_abs(0.0, 200000)
    b.estop(1.0)
    assert not b.busy(1.0) and b.position(5.0) == 30000


def test_new_move_while_moving_reverses_smoothly():
    a = _axis()
    a.move_abs(0.0, 200000)
    a.move_abs(1.0, 0)                      # brake, then come back
    xs = [a.position_physical(t) for t in np.linspace(1.0, 3.0, 201)]
    assert max(xs) == pytest.approx(30000 + 10000, abs=1)
    assert a.position(10.0) == 0 and "NI" in a.active_flags(10.0)


def test_poll_loop_over_sim_url_takes_the_profile_time():
    """With jump_on_busy off, polling every 10 ms sees BUSY for exactly the trapezoid time."""
    clock = gs.SimClock("instant", latency=0.0, jump_on_busy=False)
    inst = gs.Instrument(seed=3, clock=clock).register("stage-timing")
    try:
        inst.home_all()
        z = serial.serial_for_url("sim://stage-timing/zaber", timeout=0.1)
        z.write(b"/1 1 move abs 120000\n")
        assert z.readline() == b"@01 1 OK BUSY -- 0\r\n"
        t0 = clock.now()
        polls = 0
        while True:
            z.write(b"/1 1\n")
            if b"IDLE" in z.readline():
                break
            clock.advance(0.01)
            polls += 1
        assert clock.now() - t0 == pytest.approx(120000 / 40000 + 0.5, abs=0.0101)
        z.write(b"/1 1 get pos\n")
        assert z.readline() == b"@01 1 OK IDLE -- 120000\r\n"
    finally:
        inst.unregister()


def test_power_cycle_loses_reference_and_homing_restores_it():
    a = _axis()
    a.move_abs(0.0, 50000)
    a.power_cycle(0.5)
    assert not a.homed and a.position(0.5) == 0 and {"WR", "WH"} <= a.active_flags(0.5)
    phys = a.position_physical(0.5)
    a.home(1.0)
    assert a.end_time(1.0) > 1.0
    assert a.position(100.0) == 0 and a.position_physical(100.0) == 0.0 and phys > 0
    assert not a.active_flags(100.0)
