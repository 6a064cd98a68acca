"""Nothing from outside reaches a protocol or a file name unchecked (issue 36, item 1).

A newline in ``--out`` went into the simulated camera's line protocol as a second command
(``EXPOSE <s> DIR/victim`` then garbage) and overwrote a file outside the session folder with a
DNG. Here: every output path a user gives is refused in one line with exit status 2 when it
holds a control character, before anything is written; the drivers refuse a control character
in a value they would send (the simulated devices' side: tests/sim/test_sim_bounds.py).

Runs ``main()`` in this process, as tests/bench/test_cli_env_errors.py does.
"""

import itertools
import shutil

import pytest

import gonio.sim as gs
from gonio.core.errors import GonioError

from cli_refusal import listing, quick_session, refused

pytestmark = pytest.mark.timeout(600)

#: newline, carriage return, NUL, ESC (starts a terminal escape), NEL (C1 next line)
CONTROLS = ["\n", "\r", "\x00", "\x1b", "\x85"]
IDS = ["LF", "CR", "NUL", "ESC", "NEL"]
_names = itertools.count()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A quick simulated session, its dataset.nc and a diffuse fit of it."""
    return quick_session(tmp_path_factory.mktemp("injdata"))


# --------------------------------------------------------------------------- the original exploit
def test_newline_in_capture_out_writes_nothing_outside(capsys, tmp_path):
    victim = tmp_path / "victim"
    victim.write_text("precious")
    # before the fix: exit 3, `victim` overwritten with a DNG, a folder "victim\nX" created
    refused(capsys, "capture", "--sim", "--plan", "quick", "--quiet", "--out", f"{victim}\nX",
            needles=("control character", "'\\n'"))
    assert victim.read_text() == "precious"
    assert listing(tmp_path) == ["victim"]


def test_newline_in_resumed_session_writes_nothing_outside(capsys, data, tmp_path):
    victim = tmp_path / "victim"
    victim.write_text("precious")
    session = tmp_path / "victim\nY"
    shutil.copytree(data["session"], session)
    before = [p for p in listing(tmp_path) if not p.endswith(".lock")]     # the session's lock comes and goes
    # before the fix: the re-measured point's frame went to `victim` through the injected line
    refused(capsys, "capture", "--resume", session, "--remeasure", "0", "--quiet", needles=("control character",))
    assert victim.read_text() == "precious"
    assert [p for p in listing(tmp_path) if not p.endswith(".lock")] == before


# --------------------------------------------------------------------------- every --out
@pytest.mark.parametrize("ch", CONTROLS, ids=IDS)
def test_capture_out(capsys, tmp_path, ch):
    refused(capsys, "capture", "--sim", "--plan", "quick", "--quiet", "--out", tmp_path / f"s{ch}x")
    assert listing(tmp_path) == []


@pytest.mark.parametrize("option", ["--sample-id", "--operator", "--sample-description"])
@pytest.mark.parametrize("ch", CONTROLS, ids=IDS)
def test_session_text_options(capsys, tmp_path, option, ch):
    """They go into session.toml and the report: one line of printable text (refused before the
    fix too; kept here so that no control character reaches a file)."""
    refused(capsys, "capture", "--sim", "--plan", "quick", "--quiet", "--out", tmp_path / "s", option, f"a{ch}b")
    assert listing(tmp_path) == []


@pytest.mark.parametrize("ch", CONTROLS, ids=IDS)
def test_calibrate_out(capsys, tmp_path, monkeypatch, ch):
    import gonio.bench.calibrate as cal

    monkeypatch.setattr(cal, "run_calibration", lambda *a, **k: pytest.fail("calibrated before checking --out"))
    refused(capsys, "calibrate", "--sim", "--out", tmp_path / f"c{ch}.toml")
    assert listing(tmp_path) == []


@pytest.mark.parametrize("ch", [c for c in CONTROLS if c != "\x00"],        # no folder holds a NUL
                         ids=[i for i in IDS if i != "NUL"])
def test_export_of_a_session_folder(capsys, data, tmp_path, ch):
    """export writes SESSION/dataset.nc: a session folder named with a control character is refused."""
    session = tmp_path / f"s{ch}x"
    shutil.copytree(data["session"], session)
    (session / "dataset.nc").unlink()                  # the fixture exported the session already
    before = listing(tmp_path)
    refused(capsys, "export", session)
    assert listing(tmp_path) == before and not (session / "dataset.nc").exists()


@pytest.mark.parametrize("ch", CONTROLS, ids=IDS)
def test_fit_out(capsys, data, tmp_path, ch):
    refused(capsys, "fit", data["dataset"], "--model", "diffuse", "--out", tmp_path / f"f{ch}.json")
    refused(capsys, "fit", "--batch", data["dataset"], "--model", "diffuse", "--out", tmp_path / f"b{ch}")
    assert listing(tmp_path) == []


@pytest.mark.parametrize("ch", CONTROLS, ids=IDS)
def test_render_out(capsys, data, tmp_path, ch):
    refused(capsys, "render", data["fit"], "--dataset", data["dataset"], "--out", tmp_path / f"r{ch}")
    assert listing(tmp_path) == []


@pytest.mark.parametrize("ch", CONTROLS, ids=IDS)
def test_report_out(capsys, data, tmp_path, ch):
    refused(capsys, "report", data["root"], "--out", tmp_path / f"r{ch}.html")
    assert listing(tmp_path) == []


@pytest.mark.parametrize("ch", CONTROLS, ids=IDS)
def test_convert_out(capsys, data, tmp_path, ch):
    refused(capsys, "convert", data["fit"], "--to", "mitsuba-xml", "--out", tmp_path / f"x{ch}.xml")
    refused(capsys, "convert", data["dataset"], "--to", "csv", "--out", tmp_path / f"x{ch}.csv")
    assert listing(tmp_path) == []


def test_demo_out(capsys, tmp_path, monkeypatch):
    import gonio.cli.capture as sr

    monkeypatch.setattr(sr, "capture_sim", lambda *a, **k: pytest.fail("captured before checking --out"))
    for ch in CONTROLS:
        refused(capsys, "demo", "--out", tmp_path / f"d{ch}", "--plan", "quick")
    assert listing(tmp_path) == []


def test_the_refusal_names_the_character_in_one_line(capsys, data, tmp_path):
    for ch, shown in zip(CONTROLS, ["'\\n'", "'\\r'", "NUL", "'\\x1b'", "'\\x85'"]):
        line = refused(capsys, "fit", data["dataset"], "--model", "diffuse", "--out", tmp_path / f"f{ch}x.json")
        assert shown in line and ch not in line, line


# --------------------------------------------------------------------------- the drivers
def one_line(exc_info):
    msg = str(exc_info.value)
    assert msg and not any(c in msg for c in CONTROLS), msg
    return msg


@pytest.mark.parametrize("ch", CONTROLS, ids=IDS)
def test_format_command_refuses_control_characters(ch):
    from gonio.bench.drivers.zaber_protocol import format_command

    with pytest.raises(GonioError) as e:
        format_command(1, 0, f"get pos{ch}/1 0 estop", 5, checksum=True)
    assert "printable" in one_line(e)


def test_format_command_bounds():
    from gonio.bench.drivers.zaber_protocol import MAX_COMMAND, format_command

    assert format_command(1, 2, "move abs 64000", 7) == b"/1 2 07 move abs 64000\n"
    with pytest.raises(GonioError) as e:
        format_command(1, 0, "set maxspeed " + "9" * MAX_COMMAND)
    assert str(MAX_COMMAND) in one_line(e)
    for bad in ((100, 0, None), (1, -1, None), (1, 0, 100)):
        with pytest.raises(GonioError):
            format_command(bad[0], bad[1], "get pos", bad[2])


@pytest.fixture
def inst():
    i = gs.Instrument(seed=1).register(f"inj{next(_names)}")
    yield i
    i.unregister()


@pytest.mark.parametrize("ch", CONTROLS, ids=IDS)
def test_meter_refuses_control_characters(inst, ch):
    from gonio.bench.drivers.meter import PowerMeter

    meter = PowerMeter(inst.url("meter"), timeout=0.2)
    try:
        sent = inst.ports["meter"].commands
        with pytest.raises(GonioError) as e:
            meter.command(f"SENS:CORR:WAV 700{ch}*RST")
        one_line(e)
        with pytest.raises(GonioError):
            meter.query(f"MEAS:POW?{ch}")
        assert inst.ports["meter"].commands == sent          # nothing reached the wire
        with pytest.raises(GonioError):
            meter.command("SENS:CORR:WAV 700;*RST")          # ';' chains a second command
        with pytest.raises(GonioError):
            meter.query("MEAS:POW?" + " " * 300)
        assert inst.ports["meter"].commands == sent
        meter.configure(633.0, 10)                            # plain commands still go through
        assert meter.wavelength() == pytest.approx(633.0)
    finally:
        meter.close()


@pytest.mark.parametrize("ch", CONTROLS, ids=IDS)
def test_sim_camera_refuses_control_characters(inst, tmp_path, ch):
    from gonio.bench.drivers.camera import SimCamera

    victim = tmp_path / "victim"
    victim.write_text("precious")
    folder = tmp_path / f"victim{ch}X"
    if ch != "\x00":                                             # no folder holds a NUL
        folder.mkdir()
    camera = SimCamera(inst.url("camera"), timeout=5.0)
    try:
        sent = inst.ports["camera"].commands
        for shoot in (camera.expose, camera.flat, camera.chart, camera.expose_deferred):
            with pytest.raises(GonioError) as e:
                shoot(0.001, folder / "raw.dng")
            assert "control character" in one_line(e)
        assert inst.ports["camera"].commands == sent           # nothing reached the wire
    finally:
        camera.close()
    assert victim.read_text() == "precious"
    assert listing(tmp_path) == sorted(["victim"] + ([folder.name] if ch != "\x00" else []))


def test_sim_camera_bounds_its_lines(inst, tmp_path):
    from gonio.bench.drivers.camera import SimCamera

    camera = SimCamera(inst.url("camera"), timeout=5.0)
    try:
        deep = tmp_path.joinpath(*["d" * 200] * 25)              # > 4200 bytes, each part legal
        with pytest.raises(GonioError) as e:
            camera.expose(0.001, deep / "x.dng")
        assert "4200" in one_line(e)                             # SimCamera.MAX_LINE bytes
        assert camera.expose(0.001, tmp_path / "ok.dng")         # a plain path still works
    finally:
        camera.close()
    assert listing(tmp_path) == ["ok.dng"]
