"""Cameras (simulated protocol, watched folder, gphoto2) and RAW decoding."""

import hashlib
import subprocess
from pathlib import Path

import numpy as np
import pytest
import tifffile

from benchfakes import expect
from gonio.bench.drivers.camera import (Gphoto2Camera, SimCamera, WatchedFolderCamera, decode_raw, shutter_value)
from gonio.core.errors import CommunicationError, DeviceError, GonioError


def write_dng(path, mosaic, black=512, white=16383):
    """A minimal Bayer DNG (RGGB) with the tags LibRaw needs (shared/notes/tech-facts.md)."""
    tags = [(50706, "B", 4, (1, 4, 0, 0), True), (50707, "B", 4, (1, 1, 0, 0), True),
            (50708, "s", 0, "test cam", True), (50778, "H", 1, (21,), True),
            (33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True),
            (50714, "I", 1, (black,), True), (50717, "I", 1, (white,), True),
            (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),
            (50728, "2I", 3, (1, 1, 1, 1, 1, 1), True)]
    tifffile.imwrite(path, np.asarray(mosaic, np.uint16), photometric=32803, extratags=tags)
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def mosaic(r, g1, g2, b, h=24, w=32, black=512):     # LibRaw refuses tiny images
    m = np.empty((h, w), np.uint16)
    m[0::2, 0::2], m[0::2, 1::2], m[1::2, 0::2], m[1::2, 1::2] = r + black, g1 + black, g2 + black, b + black
    return m


def test_decode_raw_linear_black_subtracted(tmp_path):
    write_dng(tmp_path / "a.dng", mosaic(100, 200, 300, 4000))
    f = decode_raw(tmp_path / "a.dng")
    assert f.signal.shape == (3, 12, 16)
    assert np.all(f.signal[0] == 100) and np.all(f.signal[1] == 250) and np.all(f.signal[2] == 4000)
    assert np.all(f.peak[1] == 300)                    # the brighter green decides saturation
    assert list(f.n_raw) == [1, 2, 1] and f.black == 512 and f.white == 16383 and f.full_scale == 16383 - 512


def test_decode_raw_bad_files(tmp_path):
    with pytest.raises(GonioError, match="missing"):
        decode_raw(tmp_path / "nope.dng")
    (tmp_path / "junk.dng").write_bytes(b"not a raw file" * 10)
    with pytest.raises(GonioError, match="cannot decode"):
        decode_raw(tmp_path / "junk.dng")


def _expose_reply(data_writer):
    def reply(written: bytes) -> str:
        path = written.decode().split(" ", 2)[2].strip()
        return f"OK {data_writer(path)}\n"
    return reply


def test_sim_camera_protocol(tmp_path):
    target = tmp_path / "raw" / "p00001.dng"
    target.parent.mkdir()
    tmp = target.with_name(".tmp-p00001.dng")
    ex = expect("c1", [("*IDN?\n", "gonio,SimCamera,SIM1,0.1\n"), ("SENSOR?\n", "32 24 14 512 16383 RGGB\n"),
                       (f"EXPOSE 0.004 {tmp}\n", _expose_reply(lambda p: write_dng(p, mosaic(1, 2, 3, 4))))])
    cam = SimCamera("expect://c1")
    assert cam.sensor.width == 32 and cam.sensor.black == 512 and cam.idn.startswith("gonio")
    digest = cam.expose(0.004, target)
    assert digest == hashlib.sha256(target.read_bytes()).hexdigest()
    assert not tmp.exists() and ex.done()


def test_sim_camera_retries_bad_file_then_errors(tmp_path):
    target = tmp_path / "x.dng"
    tmp = tmp_path / ".tmp-x.dng"
    bad = lambda p: (Path(p).write_bytes(b"half"), "0" * 64)[1]          # checksum mismatch
    nothing = lambda p: "ab" * 32                                      # reports a file it never wrote
    good = lambda p: write_dng(p, mosaic(1, 2, 3, 4))
    expect("c2", [("*IDN?\n", "gonio,SimCamera,SIM1,0.1\n"), ("SENSOR?\n", "32 24 14 512 16383 RGGB\n"),
                  (f"EXPOSE 0.5 {tmp}\n", _expose_reply(bad)), (f"EXPOSE 0.5 {tmp}\n", _expose_reply(nothing)),
                  (f"EXPOSE 0.5 {tmp}\n", _expose_reply(good))])
    cam = SimCamera("expect://c2", retries=2)
    cam.expose(0.5, target)
    assert target.exists() and not tmp.exists()
    expect("c3", [("*IDN?\n", "gonio,SimCamera,SIM1,0.1\n"), ("SENSOR?\n", "32 24 14 512 16383 RGGB\n"),
                  (f"EXPOSE 100 {tmp}\n", "ERR bad exposure\n")])
    with pytest.raises(DeviceError, match="bad exposure"):
        SimCamera("expect://c3").expose(100, target)


def test_sim_camera_reconnects_once_when_silent(tmp_path):
    ex = expect("c4", [("*IDN?\n", "gonio,SimCamera,SIM1,0.1\n"), ("SENSOR?\n", "32 24 14 512 16383 RGGB\n"),
                       ("*IDN?\n", None), ("*IDN?\n", "gonio,SimCamera,SIM1,0.1\n"),
                       ("*IDN?\n", None), ("*IDN?\n", None)])
    cam = SimCamera("expect://c4")
    assert cam._query("*IDN?").startswith("gonio") and ex.opened == 2
    with pytest.raises(CommunicationError, match="even after a reconnect"):
        cam._query("*IDN?")


def test_watched_folder_camera(tmp_path):
    drop = tmp_path / "drop"
    drop.mkdir()
    write_dng(drop / "old.dng", mosaic(1, 1, 1, 1))           # already there: not a new capture
    fired = []

    def trigger(seconds):
        fired.append(seconds)
        write_dng(drop / f"IMG_{len(fired)}.dng", mosaic(10, 20, 30, 40))
    cam = WatchedFolderCamera(drop, trigger, poll_s=0.1, sleep=lambda s: None)
    out = tmp_path / "a.dng"
    digest = cam.expose(0.25, out)
    assert fired == [0.25] and digest == hashlib.sha256(out.read_bytes()).hexdigest()
    assert decode_raw(out).signal[0, 0, 0] == 10
    cam2 = WatchedFolderCamera(drop, None, timeout_s=0.3, poll_s=0.1, sleep=lambda s: None)
    with pytest.raises(DeviceError, match="no new RAW file"):
        cam2.expose(0.1, tmp_path / "b.dng")
    with pytest.raises(GonioError, match="does not exist"):
        WatchedFolderCamera(tmp_path / "missing")


def test_gphoto2_camera_commands(tmp_path):
    calls = []

    def run(cmd, **kw):
        calls.append(cmd)
        if "--filename" in cmd:
            write_dng(cmd[cmd.index("--filename") + 1], mosaic(1, 2, 3, 4))
        return subprocess.CompletedProcess(cmd, 0, "", "")
    cam = Gphoto2Camera(port="usb:001,004", run=run)
    out = tmp_path / "g.dng"
    cam.expose(0.004, out)
    assert calls[0] == ["gphoto2", "--port", "usb:001,004", "--set-config", "shutterspeed=1/250"]
    assert calls[1][3:] == ["--capture-image-and-download", "--filename", str(tmp_path / ".tmp-g.dng"),
                            "--force-overwrite"]
    assert out.exists() and not (tmp_path / ".tmp-g.dng").exists()
    assert shutter_value(2.5) == "2.5" and shutter_value(1 / 3) == "1/3"
    fail = Gphoto2Camera(run=lambda cmd, **kw: subprocess.CompletedProcess(cmd, 1, "", "*** Error: no camera found"))
    with pytest.raises(DeviceError, match="no camera found"):
        fail.expose(0.1, tmp_path / "h.dng")
    with pytest.raises(GonioError, match="not installed"):
        Gphoto2Camera(gphoto2="gphoto2-definitely-missing")
