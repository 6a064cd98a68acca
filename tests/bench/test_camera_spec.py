"""``--camera`` is read in one place (gonio.bench.drivers.camera.camera_from_spec): capture,
calibrate and the operator commands get the same camera for the same words."""

import pytest

from gonio.bench.drivers import Gphoto2Camera, SimCamera, WatchedFolderCamera
from gonio.bench.drivers.camera import camera_from_spec, open_camera


def test_each_spelling_names_one_kind_of_camera(tmp_path, monkeypatch):
    monkeypatch.setattr(Gphoto2Camera, "__init__", lambda self, *a, **k: None)     # no gphoto2 here
    assert isinstance(camera_from_spec("gphoto2"), Gphoto2Camera)
    folder = camera_from_spec(f"folder:{tmp_path}")
    assert isinstance(folder, WatchedFolderCamera)
    assert camera_from_spec("sim://bench/camera") == "sim://bench/camera"    # the rig opens a port itself


def test_the_operator_commands_and_the_capture_read_it_alike(tmp_path, monkeypatch):
    """`gonio shot`/`devices` open what `gonio capture` would: a port as a SimCamera."""
    from gonio.bench.session import operate
    from gonio.cli import capture as capture_cli

    opened = []
    monkeypatch.setattr(SimCamera, "__init__", lambda self, url, timeout=None: opened.append((url, timeout)))
    assert isinstance(operate.open_camera("sim://x/camera"), SimCamera) and opened == [("sim://x/camera", 30.0)]
    assert isinstance(open_camera(f"folder:{tmp_path}"), WatchedFolderCamera)
    assert capture_cli._camera("sim://x/camera") == "sim://x/camera"
    assert isinstance(capture_cli._camera(f"folder:{tmp_path}"), WatchedFolderCamera)


def test_no_other_module_parses_the_spelling():
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "gonio"
    found = [str(p.relative_to(root)) for p in root.rglob("*.py")
             if '"folder:"' in p.read_text(encoding="utf-8") and p.name != "camera.py"]
    assert not found, found
