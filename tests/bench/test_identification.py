"""Every device's identification (Zaber device id, serial, firmware, axes; the meter's and the
camera's *IDN?) is recorded in the session's journal by a capture, and a device's hostile
answer is kept as short printable text."""

import json

import numpy as np
import pytest

from gonio.bench.drivers import identify as _identify
from gonio.bench._journal import Journal
from gonio.bench.plans import Plan
from gonio.bench.session_runner import capture_sim

pytestmark = pytest.mark.timeout(300)


def test_capture_journals_the_identification(tmp_path):
    plan = Plan("one", np.array([[30.0, 0.0, 30.0, 180.0]]))
    settings = None
    summary = capture_sim(tmp_path / "s", sample={"model": "diffuse", "params": {"reflectance": 0.5}}, plan=plan,
                          seed=1, settings=settings, progress=False)
    assert summary.complete
    j = Journal(tmp_path / "s" / "journal.sqlite")
    try:
        found = [json.loads(text) for _, kind, text in j.events() if kind == "identification"]
    finally:
        j.close()
    assert len(found) == 1
    ident = found[0]
    stage, led = ident["zaber"]
    assert (stage["address"], stage["device_id"], stage["serial"], stage["firmware"], stage["build"], stage["axes"]) \
        == (1, "30342", "91001", "7.38", "18426", 4)
    assert stage["peripheral_ids"] == ["43211"] * 4
    assert (led["address"], led["device_id"], led["serial"], led["axes"]) == (2, "30311", "92001", 1)
    assert ident["meter"] == "gonio,SimPowerMeter,SIM00001,0.1.0"
    assert ident["camera"] == "gonio,SimCamera,SIM00001,0.1.0"
    assert ident["zaber_port"].startswith("sim://")


def test_hostile_device_text_is_cleaned():
    assert _identify.clean("ab\x1b[31mc\r\n\x00d") == "ab[31mcd"
    assert len(_identify.clean("x" * 10_000)) == 64 + 3


def test_every_driver_identifies_itself(tmp_path):
    """The device layer's common face: each driver's ``identify()`` gives what the simulated device
    declares (the Zaber ids of sim/_zaber_device's table, the meter's and camera's *IDN?), and a
    camera object without ``identify`` is named by its class."""
    import gonio.sim as gs
    from gonio.bench._settings import default_settings
    from gonio.bench.drivers import Goniometer, LedSource, PowerMeter, SimCamera, WatchedFolderCamera, ZaberChain

    inst = gs.Instrument(seed=1).register("ident-drivers")
    try:
        settings = default_settings()
        with ZaberChain(inst.url("zaber")) as chain, PowerMeter(inst.url("meter")) as meter:
            stages, led = Goniometer(chain, settings), LedSource(chain, 2)
            (stage,) = stages.identify()
            assert (stage["address"], stage["device_id"], stage["serial"], stage["axes"]) == (1, "30342", "91001", 4)
            assert led.identify() == chain.identify(2) and led.identify()["device_id"] == "30311"
            assert meter.identify() == "gonio,SimPowerMeter,SIM00001,0.1.0"
        cam = SimCamera(inst.url("camera"))
        try:
            assert cam.identify() == "gonio,SimCamera,SIM00001,0.1.0" == _identify.camera_text(cam)
        finally:
            cam.close()
    finally:
        inst.unregister()
    folder = WatchedFolderCamera(tmp_path)
    assert folder.identify() == f"WatchedFolderCamera {tmp_path}"
    assert _identify.camera_text(object()) == "object"
