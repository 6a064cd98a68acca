"""gonio's stage driver and the simulator agree on Zaber's native speed unit."""

import math

import pytest

import gonio.sim as gs
from gonio.bench.settings import default_settings
from gonio.bench.drivers.stages import Goniometer
from gonio.bench.drivers.zaber import ZaberChain
from gonio.core.errors import GonioError


@pytest.fixture
def gonio(make):
    inst = make()
    inst.home_all()
    chain = ZaberChain(inst.url("zaber"))
    g = Goniometer(chain, default_settings(), sleep=inst.clock.advance, poll_interval_s=0.001)
    g.connect()
    yield inst, g
    chain.close()


def test_driver_reads_the_settings_motion_from_native_units(gonio):
    """The simulator's stages (40000 microsteps/s, 80000 microsteps/s^2 at 720000 per turn) read
    back as bench/instrument.toml's [motion] (20 deg/s, 40 deg/s^2) through the native units
    (accel 13107 is 80000 * 0.16384 rounded: 39.9994 deg/s^2)."""
    inst, g = gonio
    motion = default_settings()["motion"]
    for name, (v, a) in g.motion().items():
        assert v == pytest.approx(motion[name][0], rel=1e-12)
        assert a == pytest.approx(motion[name][1], rel=2e-5)


def test_driver_sets_native_units_and_the_move_takes_that_long(gonio):
    """set_motion(10 deg/s, 25 deg/s^2) gives the simulated axis 20000 microsteps/s and 50000
    microsteps/s^2, and a 90 deg move then takes d/v + v/a = 9.4 s of simulated time (within
    20 ms: the instant clock charges 1 ms per command line, the driver polls every 1 ms here)."""
    inst, g = gonio
    g.set_motion("lamp", 10.0, 25.0)
    ax = inst.axes[3]
    assert ax.maxspeed == pytest.approx(20000.0) and ax.accel == pytest.approx(50000.0)
    assert g.motion()["lamp"] == pytest.approx((10.0, 25.0))
    t0 = inst.clock.now()
    g.move_to({**g.positions(), "lamp": 90.0})
    assert inst.clock.now() - t0 == pytest.approx(90 / 10 + 10 / 25, abs=0.02)
    for bad in (0.0, -1.0, math.nan, math.inf, True, "5"):
        with pytest.raises(GonioError, match="positive number"):
            g.set_motion("lamp", bad)
