"""A user's scene file (issue 36): confined to its folder, its files, film, samples and depths
bounded, its renders under a deadline; each refusal one line and exit status 2, nothing written."""

import os
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gonio.core.deadline import call_with_deadline
from gonio.core.errors import GonioError
from gonio.fitting.selection.scene_file import checked_scene

RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"
PAPER = RGL / "paper_white_rgb.bsdf"

SCENE = """<scene version="3.0.0">
  <integrator type="direct"/>
  <shape type="sphere"><float name="radius" value="1"/><bsdf type="diffuse" id="sample"/></shape>
  <sensor type="perspective">
    <float name="fov" value="30"/>
    <transform name="to_world"><lookat origin="0, 0, 4.5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>
    <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="0.8"/></emitter>
EXTRA</scene>
"""
LAUGHS = ('<?xml version="1.0"?><!DOCTYPE scene [<!ENTITY a "aaaaaaaaaa">'
          + "".join(f'<!ENTITY {n} "{("&" + p + ";") * 10}">' for p, n in zip("abcdefg", "bcdefgh")) + "]>")
PLY_HEAD = (b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n")
WALL = PLY_HEAD + struct.pack("<12f", -1, -1, -2, 1, -1, -2, 1, 1, -2, -1, 1, -2) + struct.pack("<B3iB3i", 3, 0, 1, 2,
                                                                                                3, 0, 2, 3)


def ply(name):
    return f'<shape type="ply"><string name="filename" value="{name}"/></shape>'


def texture(name):
    return (f'<shape type="sphere"><float name="radius" value="0.1"/><bsdf type="diffuse"><texture type="bitmap" '
            f'name="reflectance"><string name="filename" value="{name}"/></texture></bsdf></shape>')


def png(w, h):
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)


def _folder(tmp_path):
    """A scene folder with a mesh, a sub-folder, a symlink to /etc, a FIFO and damaged files."""
    d = tmp_path / "scene"
    (d / "sub").mkdir(parents=True)
    (d / "wall.ply").write_bytes(WALL)
    (d / "sub" / "inc.xml").write_text(f'<scene version="3.0.0">{ply("wall.ply")}</scene>')
    (d / "empty.ply").write_bytes(b"")
    (d / "huge.ply").write_bytes(PLY_HEAD.replace(b"vertex 4", b"vertex 1000000000") + b"\0" * 64)
    (d / "bomb.png").write_bytes(png(100_000, 100_000) + b"\0" * 8)
    (d / "small.png").write_bytes(png(4, 4) + b"\0" * 8)
    (d / "notes.txt").write_text("not an image")
    os.symlink("/etc", d / "etc")
    os.symlink("/dev/zero", d / "zero.ply")
    os.mkfifo(d / "fifo.ply")
    return d


HOSTILE = [
    ("include_abs", SCENE.replace("EXTRA", '<include filename="/etc/passwd"/>'), "by an absolute path"),
    ("include_dotdot", SCENE.replace("EXTRA", '<include filename="../../../../etc/passwd"/>'), "outside the scene's"),
    ("symlink_dir", SCENE.replace("EXTRA", '<include filename="etc/passwd"/>'), "outside the scene's"),
    ("devzero", SCENE.replace("EXTRA", ply("/dev/zero")), "by an absolute path"),
    ("devzero_link", SCENE.replace("EXTRA", ply("zero.ply")), "outside the scene's"),
    ("fifo", SCENE.replace("EXTRA", ply("fifo.ply")), "not a regular file"),
    ("empty_ply", SCENE.replace("EXTRA", ply("empty.ply")), "not a PLY file"),
    ("huge_ply", SCENE.replace("EXTRA", ply("huge.ply")), "declares more elements"),
    ("missing", SCENE.replace("EXTRA", ply("nosuch.ply")), "does not exist"),
    ("png_bomb", SCENE.replace("EXTRA", texture("bomb.png")), "100000 x 100000 pixels"),
    ("not_image", SCENE.replace("EXTRA", texture("notes.txt")), "not an image gonio can check"),
    ("laughs", LAUGHS + SCENE.replace("EXTRA", '<string name="x" value="&amp;"/>'), "DOCTYPE"),
    ("xxe", '<!DOCTYPE scene [<!ENTITY x SYSTEM "file:///etc/passwd">]>' + SCENE.replace("EXTRA", ""), "DOCTYPE"),
    ("self_include", SCENE.replace("EXTRA", '<include filename="s.xml"/>'), "<include> more than"),
    ("path", SCENE.replace("EXTRA", '<path value="/etc"/>'), "<path>"),
    ("default", SCENE.replace("EXTRA", '<default name="f" value="/etc/passwd"/>' + ply("$f")), "absolute path"),
    ("undefined", SCENE.replace("EXTRA", ply("$nosuch")), "without a <default>"),
    ("film", SCENE.replace('value="8"/><integer name="height"', 'value="100000"/><integer name="height"')
     .replace("EXTRA", ""), "the film's width 100000"),
    ("spp", SCENE.replace('"sample_count" value="4"', '"sample_count" value="99999999"').replace("EXTRA", ""),
     "sample_count"),
    ("rr_depth", SCENE.replace('<integrator type="direct"/>', '<integrator type="path"><integer name="rr_depth" '
                               'value="1000000000"/></integrator>').replace("EXTRA", ""), "rr_depth"),
    ("deep", SCENE.replace("EXTRA", "<a>" * 5000 + "</a>" * 5000), "nests elements"),
    ("not_int", SCENE.replace('"sample_count" value="4"', '"sample_count" value="x"').replace("EXTRA", ""),
     "not an integer"),
    ("serialized", SCENE.replace("EXTRA", '<shape type="serialized"><string name="filename" value="wall.ply"/>'
                                          '</shape>'), "serialized"),
]


@pytest.mark.parametrize("name, text, says", HOSTILE, ids=[h[0] for h in HOSTILE])
def test_a_hostile_scene_is_refused_in_one_line(tmp_path, name, text, says):
    d = _folder(tmp_path)
    (d / "s.xml").write_text(text)
    with pytest.raises(GonioError, match=None) as err:
        checked_scene(d / "s.xml")
    assert says in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_a_good_scene_reads_only_the_files_it_was_checked_with(tmp_path):
    """Includes inlined, defaults substituted, every path absolute and inside the folder."""
    d = _folder(tmp_path)
    (d / "s.xml").write_text(SCENE.replace("EXTRA", '<default name="m" value="wall"/><include filename="sub/inc.xml"/>'
                                           + ply("$m.ply") + texture("small.png")))
    root = checked_scene(d / "s.xml")
    names = [e.get("value") for e in root.iter("string") if e.get("name") == "filename"]
    assert names == [str(d.resolve() / "wall.ply")] * 2 + [str(d.resolve() / "small.png")]
    assert not list(root.iter("include")) and not list(root.iter("default"))


def test_a_film_without_a_size_gets_the_render_size(tmp_path):
    """A film (or a sensor) without width and height would be Mitsuba's 768 x 576: gonio sets both."""
    from gonio.fitting.selection.by_scene import _scene_file_with

    for i, text in enumerate([SCENE.replace('<integer name="width" value="8"/><integer name="height" value="8"/>', ""),
                              SCENE.replace('<film type="hdrfilm"><integer name="width" value="8"/><integer '
                                            'name="height" value="8"/></film>', "")]):
        path = tmp_path / f"s{i}.xml"
        path.write_text(text.replace("EXTRA", ""))
        xml = _scene_file_with(path, {"type": "diffuse"}, 16, 4)
        assert '<integer name="width" value="16"' in xml and '<integer name="height" value="16"' in xml, xml


def test_the_deadline_kills_the_child_and_passes_errors_back():
    t0 = time.monotonic()
    with pytest.raises(GonioError, match="did not finish within its 1 s"):
        call_with_deadline(time.sleep, (60,), seconds=1, what="sleeping")
    assert time.monotonic() - t0 < 30
    with pytest.raises(ValueError, match="invalid literal"):
        call_with_deadline(int, ("x",), seconds=60, what="int")
    with pytest.raises(GonioError, match="ended without an answer"):
        call_with_deadline(os._exit, (3,), seconds=60, what="exit")
    assert call_with_deadline(sum, ([1, 2, 3],), seconds=60, what="sum") == 6


def _gonio(*args, cwd):
    return subprocess.run([sys.executable, "-m", "gonio.cli.main", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


@pytest.mark.skipif(not PAPER.exists(), reason="no RGL data here")
def test_cli_refuses_a_scene_that_reads_etc_passwd(tmp_path):
    """Through the command line: one line, exit 2, no fit file (it ended in a traceback)."""
    d = _folder(tmp_path)
    (d / "s.xml").write_text(SCENE.replace("EXTRA", '<include filename="/etc/passwd"/>'))
    r = _gonio("fit", PAPER, "--model", "diffuse", "--scene", d / "s.xml", "--out", tmp_path / "f.json", cwd=tmp_path)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "absolute path" in r.stderr, r.stderr
    assert not (tmp_path / "f.json").exists()


@pytest.mark.skipif(not PAPER.exists(), reason="no RGL data here")
def test_cli_renders_under_a_deadline(tmp_path):
    """A render past --scene-time-limit ends in one line, exit 2, nothing written."""
    d = _folder(tmp_path)
    (d / "s.xml").write_text(SCENE.replace("EXTRA", ""))
    r = _gonio("fit", PAPER, "--model", "diffuse", "--scene", d / "s.xml", "--scene-time-limit", "1",
               "--out", tmp_path / "f.json", cwd=tmp_path)
    assert r.returncode == 2 and "did not finish within its 1 s" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "f.json").exists()
