"""``gonio fit DATA --scene SCENE`` (issue 16): the scene's table and fit file; bad input is
one line and exit status 2 before anything is written."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

GONIO = [sys.executable, "-m", "gonio.cli.main"]
RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"
PAPER = RGL / "paper_white_rgb.bsdf"


def _run(*args, cwd):
    return subprocess.run(GONIO + [str(a) for a in args], capture_output=True, text=True, cwd=cwd, timeout=600)


@pytest.mark.parametrize("extra, says", [
    (["--scene", "moonlight"], "overcast, product-shot, close-up-sun"),
    (["--scene", "overcast", "--scene-size", "3"], "--scene-size 3"),
    (["--scene", "overcast", "--scene-spp", "0"], "--scene-spp 0"),
    (["--scene", "overcast", "--threshold", "nan"], "--threshold nan"),
    (["--scene", "overcast", "--posterior"], "--posterior"),
    (["--scene", "NOSAMPLE"], 'id="sample"'),
    (["--scene", "BROKEN"], "not a readable XML"),
])
def test_bad_scene_input_is_one_line_and_exit_2(tmp_path, capsys, extra, says):
    """In-process (gonio.cli.main.main), as the CLI's other refusal tests."""
    from gonio.cli import main as cli

    data = tmp_path / "m.bsdf"
    data.write_bytes(b"not really")      # never read: the scene's options are checked first
    (tmp_path / "NOSAMPLE.xml").write_text('<scene version="3.0.0"><bsdf type="diffuse" id="x"/></scene>')
    (tmp_path / "BROKEN.xml").write_text("<scene version=")
    extra = [str(tmp_path / f"{e}.xml") if e in ("NOSAMPLE", "BROKEN") else e for e in extra]
    assert cli.main(["fit", str(data), "--out", str(tmp_path / "f.json"), *extra]) == 2
    err = capsys.readouterr().err
    assert says in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "f.json").exists()


def test_a_capture_dataset_cannot_be_rendered_as_the_measured_material(tmp_path):
    """The one refusal also checked through a separate process: the exit status as a shell sees it."""
    r = _run("fit", tmp_path / "dataset.nc", "--scene", "overcast", "--out", tmp_path / "f.json", cwd=tmp_path)
    assert r.returncode == 2 and "RGL .bsdf or a MERL .binary" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.skipif(not PAPER.exists(), reason="no RGL data here")
@pytest.mark.slow
def test_scene_fit_writes_the_table_and_the_front(tmp_path):
    """paper_white under overcast, both roughplastic distributions: every candidate has a
    rendered difference, a noise floor, a Mitsuba cost and its scene-fitted parameters; the
    chosen one is below the threshold, on the front, and is the fit file's model."""
    out = tmp_path / "f.json"
    r = _run("fit", PAPER, "--model", "roughplastic", "--scene", "overcast", "--scene-size", "16",
             "--scene-spp", "128", "--out", out, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "scene overcast" in r.stdout and "chosen for scene overcast" in r.stdout
    doc = json.loads(out.read_text())
    s = doc["scene"]
    assert {row["options"]["distribution"] for row in s["rows"]} == {"beckmann", "ggx"}
    for row in s["rows"]:
        assert row["cost_s"] > 0 and row["noise"] >= 0 and set(row["params"]) == {"diffuse_reflectance", "alpha",
                                                                                   "int_ior"}
    chosen = [row for row in s["rows"] if row["chosen"]]
    assert len(chosen) == 1 and chosen[0]["delta_e"] < s["threshold"] and chosen[0]["on_front"]
    assert doc["model"]["name"] == "roughplastic"
    assert doc["model"]["options"]["distribution"] == chosen[0]["options"]["distribution"]
    assert s["mitsuba"]["type"] == "roughplastic"
