"""Operator commands (gonio devices, home, move, jog, shot) against the simulated instrument:
in-process on ``sim://`` URLs, and as real processes on the pseudo-terminals of a real
``gonio sim serve`` process. Every bad input: one line on stderr, exit status 2, nothing moved.
"""

import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import gonio.sim as gs
from gonio.bench.plan import markers as _markers
from gonio.bench.plan import kinematics
from gonio.bench.drivers.camera import decode_raw
from gonio.bench.settings import AXES, default_settings, merge_settings
from gonio.cli.main import main

pytestmark = pytest.mark.timeout(300)
_count = iter(range(10 ** 6))


@pytest.fixture
def inst():
    i = gs.Instrument(seed=3).register(f"op{next(_count)}")
    yield i
    i.unregister()


def run(argv, capsys):
    """main() in-process; returns (status, stdout, stderr lines)."""
    try:
        rc = main(argv)
    except SystemExit as exc:            # argparse's one-line errors
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, [line for line in err.splitlines() if line.strip()]


def assert_refused(result, *needles):
    rc, out, err = result
    assert rc == 2, (rc, out, err)
    assert len(err) == 1 and err[0].startswith("gonio: error:"), err
    for n in needles:
        assert n in err[0], err[0]


def url(inst, port):
    return inst.url(port)


def pose_deg(inst):
    return np.array([math.degrees(inst.angles()[n]) for n in AXES])


def test_devices_identifies_every_device(inst, capsys):
    rc, out, err = run(["devices", "--port", url(inst, "zaber"), "--meter-port", url(inst, "meter"),
                        "--camera", url(inst, "camera")], capsys)
    assert rc == 0, err
    lines = out.splitlines()
    assert lines[0].endswith(": 2 devices")
    assert ("device 1: device id 30342, serial 91001, firmware 7.38 build 15708, 4 axes "
            "(peripheral ids 0 0 0 0); stages: yaw on axis 1") in lines[1]
    assert lines[2].startswith("  device 2: device id 30311, serial 92001") and lines[2].endswith("LED source")
    assert lines[3] == f"meter {url(inst, 'meter')}: Thorlabs,PM100D,P0000001,2.8.0"
    assert lines[4] == f"camera {url(inst, 'camera')}: gonio,SimCamera,SIM00001,0.1.0 (64 x 48 pixels, 14 bits, RGGB)"


def test_home_move_by_angles_and_stage_and_jog(inst, capsys):
    z = url(inst, "zaber")
    assert run(["home", "--port", z], capsys)[0] == 0
    assert np.allclose(pose_deg(inst), 0.0, atol=1e-3)
    rc, out, err = run(["move", "--port", z, "--angles", "30,0,45,180"], capsys)
    assert rc == 0, err
    want = kinematics.inverse(30, 0, 45, 180)
    assert np.allclose(pose_deg(inst), want, atol=1e-3)
    # the simulator's own geometry at the pose it reached gives back the asked directions
    g = inst.geometry()
    assert np.allclose(kinematics.angles_of(g["wi"])[0], 30, atol=1e-3)
    assert np.allclose(kinematics.angles_of(g["wo"])[0], 45, atol=1e-3)
    assert "theta_i 30.00" in out and "theta_o 45.00" in out
    assert run(["move", "--port", z, "--stage", "10,-20,30,60"], capsys)[0] == 0
    assert np.allclose(pose_deg(inst), [10, -20, 30, 60], atol=1e-3)
    rc, out, _ = run(["jog", "--port", z, "--axis", "tilt", "--by", "-2.5"], capsys)
    assert rc == 0 and out.startswith("jogged tilt by -2.5 deg")
    assert np.allclose(pose_deg(inst), [10, -22.5, 30, 60], atol=1e-3)


def _bad_cases(z, tmp):
    return [
        (["move", "--port", z, "--angles", "30,0,95,180"], ["below the horizon"]),
        (["move", "--port", z, "--angles", "40,0,40,0"], ["lamp in front of the camera"]),
        (["move", "--port", z, "--stage", "10,20,30,3"], ["lamp = 3 deg", "in front of the camera"]),
        (["move", "--port", z, "--stage", "100,0,0,60"], ["yaw = 100 deg is outside its limits [-95, 95]"]),
        (["move", "--port", z, "--stage", "1,2,3"], ["--stage", "four numbers"]),
        (["move", "--port", z, "--angles", "30,0,nan,180"], ["four numbers"]),
        (["move", "--port", z, "--angles", "1e999,0,1,1"], ["four numbers"]),
        (["move", "--port", z], ["one of the arguments --stage --angles is required"]),
        (["move", "--port", z, "--stage", "0,0,0,60", "--angles", "30,0,45,180"], ["not allowed with"]),
        (["move", "--port", z, "--stage", "0,0,0,60", "--baud", "0"], ["baud rate"]),
        (["jog", "--port", z, "--axis", "yaw", "--by", "200"], ["between -90 and 90"]),
        (["jog", "--port", z, "--axis", "yaw", "--by", "0"], ["non-zero"]),
        (["jog", "--port", z, "--axis", "roll", "--by", "1"], ["invalid choice"]),
        (["jog", "--port", z, "--axis", "tilt", "--by", "90"], ["tilt = 90", "outside its limits"]),
        (["move", "--port", "/nonexistent/ttyUSB9", "--stage", "0,0,0,60"], ["cannot open the stage port"]),
        (["move", "--port", "sim://nobody/zaber", "--stage", "0,0,0,60"], ["cannot open the stage port"]),
        (["devices"], ["devices needs --port"]),
        (["devices", "--port", "loop://"], ["no Zaber device answered on loop://"]),
        (["move", "--port", "\x00", "--stage", "0,0,0,60"], ["give a serial port"]),
        (["shot", "--port", z, "--meter-port", z, "--camera", z, "--out", str(tmp), "--flux", "2"],
         ["flux as a fraction"]),
    ]


def test_bad_input_is_one_line_and_nothing_moves(inst, capsys, tmp_path):
    z = url(inst, "zaber")
    assert run(["home", "--port", z], capsys)[0] == 0
    assert run(["move", "--port", z, "--stage", "0,0,0,60"], capsys)[0] == 0
    before = inst.pose_microsteps()
    for argv, needles in _bad_cases(z, tmp_path / "shot"):
        assert_refused(run(argv, capsys), *needles)
        assert inst.pose_microsteps() == before, argv
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("x")
    assert_refused(run(["shot", "--port", z, "--meter-port", url(inst, "meter"), "--camera", url(inst, "camera"),
                        "--out", str(tmp_path / "full")], capsys), "is not empty")
    assert sorted(os.listdir(tmp_path / "full")) == ["keep.txt"]


def test_nothing_moves_before_homing(inst, capsys):
    before = inst.pose_microsteps()
    assert_refused(run(["move", "--port", url(inst, "zaber"), "--angles", "30,0,45,180"], capsys),
                   "not homed", "gonio home --port")
    assert_refused(run(["jog", "--port", url(inst, "zaber"), "--axis", "yaw", "--by", "1"], capsys), "not homed")
    assert inst.pose_microsteps() == before


def test_shot_needs_homed_stages(inst, capsys, tmp_path):
    assert_refused(run(["shot", "--port", url(inst, "zaber"), "--meter-port", url(inst, "meter"),
                        "--camera", url(inst, "camera"), "--out", str(tmp_path / "s")], capsys), "not homed")
    assert not (tmp_path / "s").exists() and not inst.lamp.on


def test_shot_writes_dng_preview_and_record(inst, capsys, tmp_path):
    z = url(inst, "zaber")
    assert run(["home", "--port", z], capsys)[0] == 0
    out = tmp_path / "shot"
    rc, text, err = run(["shot", "--port", z, "--meter-port", url(inst, "meter"), "--camera", url(inst, "camera"),
                         "--out", str(out), "--angles", "20,0,40,180"], capsys)
    assert rc == 0, err
    doc = json.loads((out / "shot.json").read_text())
    assert doc["angles_deg"]["theta_i"] == pytest.approx(20, abs=1e-3)
    assert doc["exposures"] and len(doc["darks"]) == len(doc["exposures"])
    for e in doc["exposures"] + doc["darks"]:
        f = decode_raw(out / e["file"])
        assert f.signal.shape == (3, 24, 32)
    assert doc["regions"]["source"] == "geometry" and doc["regions"]["pixels"]["sample"] > 0
    # the sample is diffuse 0.5 and the reference diffuse 0.99: f_r = 0.5 / pi
    assert np.allclose(doc["f_r_estimate"], 0.5 / math.pi, rtol=0.01)
    assert doc["identification"]["zaber"][0]["device_id"] == "30342"
    from PIL import Image

    with Image.open(out / "preview.png") as im:
        assert im.size == (32, 24) and im.mode == "RGB"
        px = np.asarray(im)
    assert (px == [0, 255, 0]).all(-1).any() and (px == [0, 96, 255]).all(-1).any()   # outlines drawn
    assert not inst.lamp.on                     # the LED is off after a shot


def _marker_settings(**holder):
    s = merge_settings(default_settings(), {"camera": {"width": 480, "height": 360, "pixel_size": 0.0027}})
    s["holder"] = {**s["holder"], "markers": _markers.example_layout(), **holder}
    return s


def _green_superpixels(img):
    g = img[..., 1]
    return 0.25 * (g[0::2, 0::2] + g[0::2, 1::2] + g[1::2, 0::2] + g[1::2, 1::2])


@pytest.mark.parametrize("stage", [(0.0, 0.0, 0.0, 40.0), (20.0, 10.0, 30.0, 60.0)])
def test_detected_regions_follow_a_moved_holder(stage):
    """The simulated holder is moved by a known shift and turn; the pose found from its markers
    matches it, and the regions found lie inside the moved squares, where the geometry's do not."""
    shift, turn = (0.04, -0.03), 3.0
    bench = _marker_settings()
    truth = _markers.HolderPose(np.array(shift), turn, 0.0, ())
    for sim_pose, want in (((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), ((*shift, turn), (*shift, turn))):
        inst = gs.Instrument(_marker_settings(sim_pose=list(sim_pose)), seed=1)
        inst.set_pose(**dict(zip(AXES, stage)))
        img = _green_superpixels(inst.radiance())
        r = _markers.find_regions(img, np.array(stage), bench)
        assert r.source == "markers", r.why
        assert len(r.pose.ids) >= 2
        px = bench["camera"]["pixel_size"]
        assert np.allclose(r.pose.shift, want[:2], atol=px)          # within a pixel
        assert r.pose.angle_deg == pytest.approx(want[2], abs=0.3)
        true_pose = truth if want[2] else None
        ts, tr = _markers.posed_masks(np.array(stage), bench, true_pose, margin_px=0.0)
        assert r.sample.sum() > 100 and r.reference.sum() > 100
        assert not (r.sample & ~ts).any() and not (r.reference & ~tr).any()
        if want[2]:                              # the geometry alone puts regions off the moved squares
            gs_, gr = _markers.posed_masks(np.array(stage), bench, None)
            assert (gs_ & ~ts).sum() + (gr & ~tr).sum() > 50


def test_no_markers_fall_back_to_the_geometry():
    bench = _marker_settings()
    flat = np.full((180, 240), 0.05)
    r = _markers.find_regions(flat, np.zeros(4) + [0, 0, 0, 40], bench)
    assert r.source == "geometry" and "no marker" in r.why
    sm, rm = kinematics.roi_masks([0, 0, 0, 40], bench)
    assert (r.sample == sm).all() and (r.reference == rm).all()


def test_malformed_marker_table_is_one_line(capsys):
    for bad in ({"dictionary": "DICT_NOPE", "size": 0.1, "ids": [0], "centres": [[0, 0]]},
                {"dictionary": "DICT_4X4_50", "size": -1, "ids": [0], "centres": [[0, 0]]},
                {"dictionary": "DICT_4X4_50", "size": 0.1, "ids": [0, 0], "centres": [[0, 0], [1, 1]]},
                {"dictionary": "DICT_4X4_50", "size": 0.1, "ids": [0], "centres": [[0, "x"]]},
                "markers"):
        s = _marker_settings()
        s["holder"]["markers"] = bad
        with pytest.raises(Exception) as exc:
            _markers.layout_of(s)
        assert type(exc.value).__name__ == "GonioError" and "\n" not in str(exc.value)


# -- a real `gonio sim serve` process and real `gonio` processes on its ptys -------------------
GONIO = [sys.executable, "-m", "gonio.cli.main"]


def _gonio(*args):
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run(GONIO + list(args), capture_output=True, text=True, timeout=120, env=env)


@pytest.fixture
def served():
    proc = subprocess.Popen(GONIO + ["sim", "serve", "--clock", "instant", "--seed", "2"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    paths = {}
    deadline = time.monotonic() + 90
    while len(paths) < 3 and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        tok = line.split()
        if len(tok) == 4 and tok[2] == "->":
            paths[tok[0]] = tok[1]
    try:
        assert set(paths) == {"zaber", "meter", "camera"}, proc.stderr.read() if proc.poll() is not None else paths
        yield paths
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_commands_on_the_ptys_of_gonio_sim_serve(served, tmp_path):
    z, m, c = served["zaber"], served["meter"], served["camera"]
    p = _gonio("devices", "--port", z, "--meter-port", m, "--camera", c)
    assert p.returncode == 0, p.stderr
    assert "device id 30342" in p.stdout and "Thorlabs,PM100D" in p.stdout and "gonio,SimCamera" in p.stdout
    p = _gonio("move", "--port", z, "--stage", "0,0,0,60")
    assert p.returncode == 2 and "not homed" in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert _gonio("home", "--port", z).returncode == 0
    p = _gonio("move", "--port", z, "--angles", "30,0,45,180")
    assert p.returncode == 0 and "theta_i 30.00 phi_i 0.00 theta_o 45.00" in p.stdout, p.stderr
    p = _gonio("jog", "--port", z, "--axis", "lamp", "--by", "5")
    assert p.returncode == 0 and "lamp 80.000" in p.stdout, p.stdout + p.stderr
    p = _gonio("shot", "--port", z, "--meter-port", m, "--camera", c, "--out", str(tmp_path / "s"))
    assert p.returncode == 0, p.stderr
    files = sorted(os.listdir(tmp_path / "s"))
    assert "preview.png" in files and "shot.json" in files
    assert any(f.startswith("shot_") and f.endswith(".dng") for f in files)
    p = _gonio("move", "--port", z, "--stage", "0,0,0,2")
    assert p.returncode == 2 and "in front of the camera" in p.stderr


def test_shot_finds_the_regions_from_the_markers_of_a_moved_holder(capsys, tmp_path):
    """gonio shot with a settings file whose holder carries markers: the shot records regions
    found from them and the holder's pose the simulator was given (its truth)."""
    layout = _markers.example_layout()
    cent = ", ".join(f"[{x!r}, {y!r}]" for x, y in layout["centres"])
    toml = tmp_path / "markers.toml"
    toml.write_text("[camera]\nwidth = 480\nheight = 360\npixel_size = 0.0027\n[holder]\n"
                    f"markers = {{ dictionary = \"DICT_4X4_50\", size = {layout['size']!r}, "
                    f"ids = {layout['ids']!r}, centres = [{cent}] }}\n")
    from gonio.bench.settings import load_settings

    bench = load_settings(toml)
    sim = merge_settings(bench, {"holder": {"sim_pose": [0.03, 0.02, -2.0]}})
    inst = gs.Instrument(sim, seed=4).register(f"op{next(_count)}")
    try:
        z = inst.url("zaber")
        assert run(["home", "--port", z, "--settings", str(toml)], capsys)[0] == 0
        rc, text, err = run(["shot", "--port", z, "--meter-port", inst.url("meter"), "--camera", inst.url("camera"),
                             "--out", str(tmp_path / "s"), "--settings", str(toml), "--angles", "30,0,20,180"], capsys)
    finally:
        inst.unregister()
    assert rc == 0, err
    assert "regions from markers" in text
    reg = json.loads((tmp_path / "s" / "shot.json").read_text())["regions"]
    assert reg["source"] == "markers"
    assert np.allclose(reg["holder_pose"]["shift"], [0.03, 0.02], atol=0.0027)
    assert reg["holder_pose"]["angle_deg"] == pytest.approx(-2.0, abs=0.3)


def _corner_masks(stage, settings, pose, binning=2, margin_px=1.0):
    """The regions by the definition: all four corners of each super-pixel's footprint inside."""
    cam, hold = settings["camera"], settings["holder"]
    h, w = cam["height"] // binning, cam["width"] // binning
    i, j = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    xy = np.stack([pose.to_holder(kinematics.image_to_local(stage, binning * i + dr, binning * j + dc, settings))
                   for dr in (-0.5, binning - 0.5) for dc in (-0.5, binning - 0.5)])
    half = hold["sample_half"] - margin_px * cam["pixel_size"]
    return tuple(np.all((np.abs(xy[..., 0] - cx) <= half) & (np.abs(xy[..., 1]) <= half), axis=0)
                 for cx in (-hold["offset"], hold["offset"]))


def test_posed_masks_are_the_corner_test():
    """The affine shortcut gives the masks of the corner-by-corner definition, and with no pose
    those of kinematics.roi_masks, over random poses."""
    settings = default_settings()
    rng = np.random.default_rng(5)
    for _ in range(40):
        stage = np.array([rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(-180, 180), rng.uniform(10, 170)])
        pose = _markers.HolderPose(rng.uniform(-0.05, 0.05, 2), rng.uniform(-5, 5), 0.0, ())
        want = _corner_masks(stage, settings, pose)
        got = _markers.posed_masks(stage, settings, pose)
        assert all((a == b).all() for a, b in zip(want, got))
        ref = kinematics.roi_masks(stage, settings)
        assert all((a == b).all() for a, b in zip(ref, _markers.posed_masks(stage, settings, None)))


def test_bench_capture_prints_the_table_against_its_bound(capsys):
    rc, out, err = run(["bench", "capture", "--skip-full", "--points", "2"], capsys)
    assert rc == 0, err
    lines = out.splitlines()
    head = next(i for i, line in enumerate(lines) if "proj/bound" in line)
    row = lines[head + 1].split()
    assert row[0] == "64x48" and row[1] == "2"
    motion, expose, bound = map(float, row[2:5])
    assert motion > 0 and expose > 0 and bound == pytest.approx(motion + expose, abs=2e-3)
    col = lines[head].split().index("proj/bound")
    assert float(row[col].rstrip("x")) >= 1.0        # bound + host time is never below the bound
    verdict = next(line for line in lines if line.startswith("64x48: "))
    assert "against the motion + exposure bound" in verdict and "target <= 1.1x" in verdict and "MiB" in verdict
    for argv, needle in ((["--points", "0"], "give 1 to 20 points"), (["--full-size", "6000by4000"], "WIDTHxHEIGHT"),
                         (["--full-size", "7x7"], "WIDTHxHEIGHT")):
        assert_refused(run(["bench", "capture", *argv], capsys), needle)


def test_jogging_works_at_the_home_pose(inst, capsys):
    """Issue 40: at home (every axis 0, the lamp arm in front of the camera) every jog was refused
    as 'lamp in front of the camera'. A jog of another axis leaves the lamp where it is; a lamp
    inside the zone may be jogged; only a lamp jogged into the zone from outside is refused."""
    z = url(inst, "zaber")
    assert run(["home", "--port", z], capsys)[0] == 0
    rc, out, err = run(["jog", "--port", z, "--axis", "yaw", "--by", "5"], capsys)
    assert rc == 0 and out.startswith("jogged yaw by +5 deg"), err
    rc, out, err = run(["jog", "--port", z, "--axis", "lamp", "--by", "30"], capsys)
    assert rc == 0, err
    assert np.allclose(pose_deg(inst), [5, 0, 0, 30], atol=1e-3)
    before = inst.pose_microsteps()
    assert_refused(run(["jog", "--port", z, "--axis", "lamp", "--by", "-28"], capsys), "in front of the camera")
    assert inst.pose_microsteps() == before


def test_shot_takes_darks_for_the_exposures_it_merges(inst, capsys, tmp_path):
    """Issue 40: a shot whose probe saturated took a dark for it too (one more frame than the
    bracket asked for) and said nothing of it. The darks now match the merged exposures, and the
    probe is named in the summary and marked unmerged in shot.json."""
    z = url(inst, "zaber")
    assert run(["home", "--port", z], capsys)[0] == 0
    toml = tmp_path / "probe.toml"
    toml.write_text("[capture]\nprobe_s = 0.064\n")        # saturates at this pose: the ladder steps down
    out = tmp_path / "s"
    rc, text, err = run(["shot", "--port", z, "--meter-port", url(inst, "meter"), "--camera", url(inst, "camera"),
                         "--out", str(out), "--stage", "0,0,0,60", "--settings", str(toml)], capsys)
    assert rc == 0, err
    doc = json.loads((out / "shot.json").read_text())
    merged = [e["seconds"] for e in doc["exposures"] if e["merged"]]
    probes = [e["seconds"] for e in doc["exposures"] if not e["merged"]]
    assert merged == doc["bracket"] and probes == [0.064], doc["exposures"]
    assert [d["seconds"] for d in doc["darks"]] == merged
    assert sorted(p.name for p in out.glob("dark_*.dng")) == [f"dark_{t * 1e6:010.0f}us.dng" for t in merged]
    assert f"{len(merged)} exposures" in text and "1 saturated probe 0.064 s, not merged" in text
    assert f"and {len(merged)} darks" in text
