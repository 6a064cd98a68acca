"""The rig's ports are declared once (gonio.core.devices): the bench's drivers, the simulator's
devices and the fault schedule all read that declaration, and a bench that fails half-way
through opening closes what it had opened."""

from __future__ import annotations

import pytest

import gonio.sim as gs
from gonio.bench.drivers import rig
from gonio.bench.settings import load_settings
from gonio.core.devices import OPTIONAL_PORTS, PORT_NAMES, PORTS, REQUIRED_PORTS, port_spec
from gonio.sim.instrument import OPTIONAL_SIM_DEVICES, SIM_DEVICES
from gonio.sim.physics.faults import FaultSchedule


def test_every_layer_serves_exactly_the_declared_ports():
    assert PORT_NAMES == ("zaber", "meter", "camera", "monochromator")
    assert (REQUIRED_PORTS, OPTIONAL_PORTS) == (("zaber", "meter", "camera"), ("monochromator",))
    assert tuple(rig.DRIVERS) == PORT_NAMES
    assert tuple(SIM_DEVICES) + tuple(OPTIONAL_SIM_DEVICES) == PORT_NAMES
    inst = gs.Instrument(seed=1)
    assert tuple(inst.ports) == REQUIRED_PORTS          # an optional device only where the settings declare it
    assert tuple(gs.Instrument({"monochromator": {}}, seed=1).ports) == PORT_NAMES
    assert all(p.option.startswith("--") and p.carries for p in PORTS)
    assert port_spec("meter").protocol.startswith("SCPI")
    with pytest.raises(ValueError, match="zaber, meter, camera, monochromator"):
        port_spec("lamp")


def test_a_fault_on_an_undeclared_port_names_the_ports():
    with pytest.raises(ValueError, match="unknown port 'lamp'; the rig's ports are zaber, meter, camera, monochromator"):
        FaultSchedule([{"kind": "timeout", "port": "lamp", "at_command": 1}])


def test_from_ports_needs_every_declared_port_and_no_other():
    with pytest.raises(ValueError, match="missing camera"):
        rig.Bench.from_ports({}, {"zaber": "sim://x/zaber", "meter": "sim://x/meter"})
    with pytest.raises(ValueError, match="unknown lamp"):
        rig.Bench.from_ports({}, {"zaber": "a", "meter": "b", "camera": "c", "lamp": "d"})


def test_a_bench_that_fails_while_opening_closes_what_it_opened(monkeypatch):
    inst = gs.Instrument(seed=2).register("ports-declared")
    try:
        closed = []

        class Recorder(rig.ZaberChain):
            def close(self):
                closed.append("zaber")
                super().close()

        def broken_meter(bench, url, kw):
            raise OSError("meter port gone")

        monkeypatch.setattr(rig, "ZaberChain", Recorder)
        monkeypatch.setitem(rig.DRIVERS, "meter", broken_meter)
        with pytest.raises(OSError, match="meter port gone"):
            rig.Bench.from_ports(load_settings(), {p: inst.url(p) for p in REQUIRED_PORTS})
        assert closed == ["zaber"]
    finally:
        inst.unregister()
