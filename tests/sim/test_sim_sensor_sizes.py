"""The simulated camera's sizes (issue 40: only 64 x 48): a real camera's 24 MP, 14-bit RGGB
sensor as an option of `gonio sim serve`, read through gonio's camera driver, and a 24 MP frame
decoded by rawpy (LibRaw), the decoder a lab's tools use."""

import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from gonio.sim.physics.sensor import SENSOR_SIZES, SensorModel, camera_table, sensor_size

pytestmark = pytest.mark.timeout(300)


def test_sizes_and_field_of_view():
    assert sensor_size("24mp") == (6000, 4000, 14) == SENSOR_SIZES["24mp"]     # 24.0 MP, 3:2
    assert sensor_size("640x480") == (640, 480, 14) and sensor_size("CI") == (64, 48, 14)
    for bad in ("7x7", "6001x4000", "24 mp", "x", "1e4x10", "20000x20000"):
        with pytest.raises(ValueError, match="WIDTHxHEIGHT"):
            sensor_size(bad)
    cam = {"width": 64, "height": 48, "pixel_size": 0.01, "bits": 14, "gain_e_per_dn": 2.0}
    big = camera_table("24mp", cam)
    assert big["width"] * big["pixel_size"] == pytest.approx(64 * 0.01)   # the same field of view
    assert big["gain_e_per_dn"] == 2.0 and big["bits"] == 14


def test_mosaic_is_the_per_pixel_weighted_sum():
    # the tile-by-tile mosaic equals each pixel's row of the camera matrix under RGGB, exactly
    s = SensorModel(width=64, height=48, seed=1)
    rad = np.random.default_rng(3).random((48, 64, 3))
    weights = s.colour.cam_from_srgb[s.channel_map]
    assert np.array_equal(s.mosaic(rad), np.einsum("hwj,hwj->hw", rad, weights))


def _serve(*extra):
    p = subprocess.Popen([sys.executable, "-m", "gonio.cli.main", "sim", "serve", "--clock", "instant", *extra],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ports = {}
    deadline = time.monotonic() + 120
    while len(ports) < 3 and time.monotonic() < deadline:
        line = p.stdout.readline()
        if not line:
            break
        tok = line.split()
        if len(tok) == 4 and tok[2] == "->":
            ports[tok[0]] = tok[1]
    return p, ports


def _stop(p):
    p.send_signal(signal.SIGTERM)
    p.communicate(timeout=60)


def test_a_24mp_camera_through_the_camera_driver(capsys):
    import gonio.sim as gs
    from gonio.bench.drivers.camera import SimCamera
    from gonio.bench.settings import default_settings
    from gonio.cli.main import main

    inst = gs.Instrument({"camera": camera_table("24mp", default_settings()["camera"])}, seed=1, spp=1)
    inst.register("sizes-24mp")
    try:
        cam = SimCamera(inst.url("camera"), timeout=5)
        s = cam.sensor
        assert (s.width, s.height, s.bits, s.black, s.white, s.cfa) == (6000, 4000, 14, 512, 16383, "RGGB")
        cam.close()
    finally:
        inst.unregister()
    assert main(["sim", "serve", "--camera-size", "7x7"]) == 2            # refused before serving
    err = capsys.readouterr().err
    assert "--camera-size" in err and "WIDTHxHEIGHT" in err and len(err.strip().splitlines()) == 1


@pytest.mark.long
def test_sim_serve_offers_a_24mp_camera():
    from gonio.bench.drivers.camera import SimCamera

    p, ports = _serve("--camera-size", "24mp")
    try:
        assert set(ports) == {"zaber", "meter", "camera"}, p.stderr.read() if p.poll() is not None else ports
        cam = SimCamera(ports["camera"], timeout=30)
        s = cam.sensor
        assert (s.width, s.height, s.bits, s.black, s.white, s.cfa) == (6000, 4000, 14, 512, 16383, "RGGB")
        cam.close()
    finally:
        _stop(p)
    bad = subprocess.run([sys.executable, "-m", "gonio.cli.main", "sim", "serve", "--camera-size", "7x7"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--camera-size" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


@pytest.mark.long
def test_a_24mp_frame_decodes_in_rawpy(tmp_path):
    rawpy = pytest.importorskip("rawpy")
    import gonio.sim as gs
    from gonio.bench.settings import default_settings

    base = default_settings()
    inst = gs.Instrument({"camera": camera_table("24mp", base["camera"])}, seed=1, spp=1)
    inst.home_all()
    inst.set_pose(lamp=60.0)
    inst.lamp.switch(inst.clock.now(), True)
    data = inst.capture(0.008)
    path = tmp_path / "f.dng"
    path.write_bytes(data)
    with rawpy.imread(str(path)) as raw:
        img = raw.raw_image_visible
        assert img.shape == (4000, 6000) and raw.white_level == 16383
        assert raw.color_desc.decode() in ("RGBG", "RGB") and img.max() <= 16383
        assert np.median(img) > 512                     # the lit holder, over the black level
