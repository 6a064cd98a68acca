"""The stage driver waits for a move by the simulator's alerts (``set comm.alert 1`` ->
``!01 A IDLE --`` when an axis's motion ends), not by polling every ``poll_interval_s``."""

import time

import pytest

from gonio.bench.settings import default_settings
from gonio.bench.drivers.stages import Goniometer
from gonio.bench.drivers.zaber import ZaberChain


class Counting(ZaberChain):
    """The chain, counting the status polls (``/1 0`` with no command) it sends."""

    polls = 0

    def request(self, device, axis, command="", **kw):
        if not command:
            self.polls += 1
        return super().request(device, axis, command, **kw)


def _gonio(inst, alerts, sleep):
    inst.home_all()
    chain = Counting(inst.url("zaber"))
    g = Goniometer(chain, default_settings(), sleep=sleep, alerts=alerts)
    g.connect()
    return chain, g


def test_instant_clock_move_waits_by_alert_with_exact_motion_time(make):
    inst = make()
    slept = []
    chain, g = _gonio(inst, True, lambda s: (slept.append(s), inst.clock.advance(s)))
    try:
        assert inst.zaber.stage.alert == 1 and chain.alerting == {1}
        t0 = inst.clock.now()
        g.move_to({**g.positions(), "lamp": 90.0})
        assert inst.clock.now() - t0 == pytest.approx(90 / 20 + 20 / 40, abs=0.02)   # [motion] lamp 20 deg/s, 40 deg/s^2
        assert g.positions()["lamp"] == pytest.approx(90.0, abs=1e-3)
        assert set(slept) <= {0} and chain.polls == 2                # BUSY (the clock jumps), alert, IDLE
    finally:
        chain.close()


@pytest.mark.timeout(60)
def test_real_time_move_is_seen_when_its_alert_comes(make):
    """Scaled clock (5x real time, a 0.7 s move): the standstill is seen soon after the motion
    ends and with a few polls (BUSY, then one per axis's alert), where polling every 0.05 s
    sends one per interval (about 14 here)."""
    inst = make(clock="scaled:5")
    chain, g = _gonio(inst, True, time.sleep)
    try:
        g.move_to({**g.positions(), "lamp": 60.0}, wait=False)
        t = inst.clock.now()
        t_end = max(e for e in (a.end_time(t) for a in inst.axes) if e is not None)
        polls = chain.polls
        g.finish_move({"lamp": 60.0})
        late = inst.clock.now() - t_end
        assert 0 <= late < 5 * 0.2                                    # simulated seconds: < 0.2 s wall
        assert chain.polls - polls <= 3
    finally:
        chain.close()
