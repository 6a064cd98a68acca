"""Every device's identification (Zaber device id, serial, firmware, axes; the meter's and the
camera's *IDN?) is recorded in the session's journal by a capture, and a device's hostile
answer is kept as short printable text."""

import json

import numpy as np
import pytest

from gonio.bench.drivers import identify as _identify
from gonio.bench.session.journal import Journal
from gonio.bench.plan.plans import Plan
from gonio.cli.capture import capture_sim

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
        == (1, "30342", "91001", "7.38", "15708", 4)
    assert stage["peripheral_ids"] == ["0"] * 4           # no rotary product has the settings' 720000/turn
    assert (led["address"], led["device_id"], led["serial"], led["axes"]) == (2, "30311", "92001", 1)
    assert ident["meter"] == "Thorlabs,PM100D,P0000001,2.8.0"
    assert ident["camera"] == "gonio,SimCamera,SIM00001,0.1.0"
    assert ident["zaber_port"].startswith("sim://")


def test_hostile_device_text_is_cleaned():
    assert _identify.clean("ab\x1b[31mc\r\n\x00d") == "ab[31mcd"
    assert len(_identify.clean("x" * 10_000)) == 64 + 3


def test_every_driver_identifies_itself(tmp_path):
    """The device layer's common face: each driver's ``identify()`` gives what the simulated device
    declares (the Zaber ids of gonio/sim/devices/zaber_common's table, the meter's and camera's *IDN?), and a
    camera object without ``identify`` is named by its class."""
    import gonio.sim as gs
    from gonio.bench.settings import default_settings
    from gonio.bench.drivers import Goniometer, LedSource, PowerMeter, SimCamera, WatchedFolderCamera, ZaberChain

    inst = gs.Instrument(seed=1).register("ident-drivers")
    try:
        settings = default_settings()
        with ZaberChain(inst.url("zaber")) as chain, PowerMeter(inst.url("meter")) as meter:
            stages, led = Goniometer(chain, settings), LedSource(chain, 2)
            (stage,) = stages.identify()
            assert (stage["address"], stage["device_id"], stage["serial"], stage["axes"]) == (1, "30342", "91001", 4)
            assert led.identify() == chain.identify(2) and led.identify()["device_id"] == "30311"
            assert meter.identify() == "Thorlabs,PM100D,P0000001,2.8.0"
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


# -- session.toml's [devices] (issue 17) ---------------------------------------------------------

ONE = Plan("one", np.array([[30.0, 0.0, 30.0, 180.0]]))


@pytest.fixture
def sim_instrument():
    import gonio.sim as gs
    from gonio.bench.settings import default_settings

    made = []

    def make(name):
        inst = gs.Instrument(default_settings(), sample={"model": "diffuse", "params": {"reflectance": 0.5}},
                             seed=1).register(name)
        made.append(inst)
        return inst
    yield make
    for inst in made:
        inst.unregister()


def _capture(inst, folder):
    from gonio.bench.session.capture import capture
    from gonio.bench.settings import default_settings

    return capture(folder, ONE, default_settings(), inst.url("zaber"), inst.url("meter"), inst.url("camera"),
                   seed=1, progress=False, sleep=inst.clock.advance)


def _events(folder, kind):
    with Journal(folder / "journal.sqlite") as j:
        return [text for _, k, text in j.events() if k == kind]


def test_session_toml_records_every_devices_identification(sim_instrument, tmp_path):
    """A capture identifies the devices before it writes session.toml: its [devices] table is the
    identification the journal records for that run (docs/interfaces.md section 5)."""
    from gonio.bench.session.journal import read_session

    inst = sim_instrument("ident-toml")
    folder = tmp_path / "s"
    assert _capture(inst, folder).complete
    dev = read_session(folder)["devices"]
    assert dev["meter"] == "Thorlabs,PM100D,P0000001,2.8.0"
    assert dev["camera"] == "gonio,SimCamera,SIM00001,0.1.0"
    assert dev["zaber_port"] == inst.url("zaber") and dev["meter_port"] == inst.url("meter")
    assert dev["zaber"]["1"] == {"address": 1, "device_id": "30342", "serial": "91001", "firmware": "7.38",
                                 "build": "15708", "axes": 4, "peripheral_ids": ["0"] * 4}
    assert (dev["zaber"]["2"]["device_id"], dev["zaber"]["2"]["serial"], dev["zaber"]["2"]["axes"]) == ("30311", "92001", 1)
    (journalled,) = _events(folder, "identification")          # asked once, before session.toml
    assert _identify.session_devices(json.loads(journalled)) == dev


def test_a_hostile_idn_reply_cannot_break_or_inject_into_session_toml(sim_instrument, tmp_path):
    """Quotes, backslashes, carriage returns, control characters and TOML syntax in a ``*IDN?``
    reply: session.toml still parses, holds the cleaned text as the meter's one string, and
    nothing of the reply becomes a key or a table."""
    import tomllib

    inst = sim_instrument("ident-hostile")
    hostile = 'Evil"Corp\\",\r[session]\tseed = 666,\x00\x1b[2J\x7f""",SN\nzaber = "x",1.0\r'
    inst.scpi.IDN = hostile.replace("\n", " ")                 # one reply line, as a device sends it
    folder = tmp_path / "s"
    assert _capture(inst, folder).complete
    text = (folder / "session.toml").read_text()
    doc = tomllib.loads(text)
    assert doc["devices"]["meter"] == _identify.clean(hostile.replace("\n", " "))
    assert doc["devices"]["meter"] == 'Evil"Corp\\",[session]seed = 666,[2J""",SN zaber = "x",1.0'
    assert doc["session"]["seed"] == 1 and "zaber" not in doc and set(doc["devices"]) == {
        "zaber_port", "meter_port", "meter", "camera", "zaber"}
    assert not any(ch in text for ch in "\r\x00\x1b\x7f")


def test_the_toml_writer_escapes_what_toml_forbids():
    """Whatever text reaches session.toml's writer (control characters, DEL, quotes, a key that
    is not a bare key) reads back as it was."""
    import tomllib

    from gonio.bench.session.journal import session_text

    doc = {"devices": {"meter": 'a"b\\c\x7fd\x00e\nf\rg\th\x1b', "zaber": {"1": {"serial": "9]\n[x"}}},
           "odd keys": {"k.e y\x7f": "v"}}
    assert tomllib.loads(session_text(doc)) == doc


def test_resume_on_other_hardware_is_said_and_reported(sim_instrument, tmp_path):
    """session.toml stays as written; a resume on the same hardware says nothing; a resume with a
    stage controller of another serial journals its identification, says the difference (a
    console line: the summary's notes and ``notify``) and the report shows session.toml's devices
    and that difference."""
    from gonio.bench.report.inputs import Folder
    from gonio.bench.report.meta import _devices
    from gonio.bench.session.capture import resume

    inst = sim_instrument("ident-resume")
    folder = tmp_path / "s"
    assert _capture(inst, folder).complete
    before = (folder / "session.toml").read_bytes()
    said = []
    kw = dict(progress=False, sleep=inst.clock.advance, notify=said.append)
    same = resume(folder, remeasure="0", **kw)
    assert same.complete and not [n for n in same.notes + said if "hardware" in n]
    assert _events(folder, "hardware") == []
    inst.zaber.stage.ident["system.serial"] = 91099            # another controller on the same port
    other = resume(folder, remeasure="0", **kw)
    assert other.complete
    (line,) = [n for n in other.notes if "other hardware" in n]
    assert "Zaber device 1 serial 91001 -> 91099" in line and [n for n in said if "hardware" in n] == [line]
    assert _events(folder, "hardware") == [line]
    assert (folder / "session.toml").read_bytes() == before    # write-once: the original stays
    assert json.loads(_events(folder, "identification")[-1])["zaber"][0]["serial"] == "91099"
    rows = {d["role"]: d["text"] for d in _devices(Folder(folder), folder / "journal.sqlite")}
    assert "serial 91001" in rows["Zaber device 1"]            # session.toml's, not the resume's
    assert "Zaber device 1 serial 91001 -> 91099" in rows["Hardware on resume"]
