"""A simulated spectral capture (issue 39) killed (SIGKILL) between a point's frames and its
journal row resumes like any other capture: every (geometry, wavelength) point is measured
once at its own wavelength, the monitor's per-wavelength references are reused, and raw/
holds exactly the files the journal commits (mirrors test_point_kill.py)."""

import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from gonio.bench.session.journal import RAW_DIR, Journal

from capture_process import ENV, GONIO, committed_files

ROOT = Path(__file__).resolve().parents[2]
SETTINGS = "[monochromator]\ngratings = [[1, 200, 650], [2, 650, 1400]]\n"
PLAN = ('name = "spectral-four"\n[spectral]\nfrom_nm = 400\nto_nm = 700\nstep_nm = 100\n'
        '[[scan]]\nkind = "points"\npoints = [[30, 0, 30, 180], [30, 0, 50, 180], [20, 0, 40, 90]]\n')

# held before its fifth row: the monochromator has been to several wavelengths and is mid-sweep
_HELD = """
import pathlib, sys, time
from gonio.bench.session.journal import Journal
real, seen = Journal.record_point, []
def held(self, *args, **kwargs):
    seen.append(1)
    if len(seen) == 5:
        pathlib.Path(sys.argv[1]).write_text("held")
        time.sleep(3600)
    return real(self, *args, **kwargs)
Journal.record_point = held
from gonio.cli.main import main
sys.exit(main(["capture", "--sim", "--plan", sys.argv[3], "--settings", sys.argv[4], "--sample", sys.argv[5],
               "--seed", "8", "--out", sys.argv[2], "--quiet"]))
"""


@pytest.mark.long        # two capture processes: about 10 s
def test_a_killed_spectral_capture_resumes_at_its_wavelengths(tmp_path):
    session, marker = tmp_path / "s", tmp_path / "held"
    (tmp_path / "plan.toml").write_text(PLAN)
    (tmp_path / "settings.toml").write_text(SETTINGS)
    sample = ROOT / "gonio" / "cli" / "samples" / "red-lacquer.toml"
    proc = subprocess.Popen([sys.executable, "-c", _HELD, str(marker), str(session), str(tmp_path / "plan.toml"),
                             str(tmp_path / "settings.toml"), str(sample)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None and not marker.exists():
        time.sleep(0.02)
    assert marker.exists() and proc.poll() is None, f"the capture did not reach its fifth point: {proc.stderr.read()}"
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    with Journal(session / "journal.sqlite") as j:
        before = {r["idx"] for r in j.points()}
        refs_before = sum(1 for e in j.events() if e[1] == "p_ref_nm")
    assert len(before) == 4 and refs_before >= 1

    r = subprocess.run(GONIO + ["capture", "--resume", str(session), "--quiet"], capture_output=True, text=True,
                       env=ENV, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "12/12 points" in r.stdout
    doc = tomllib.loads((session / "session.toml").read_text())
    wl = doc["plan"]["wavelength_nm"]
    with Journal(session / "journal.sqlite") as j:
        rows = j.points()
        refs = [e[2] for e in j.events() if e[1] == "p_ref_nm"]
    assert sorted(r["idx"] for r in rows) == list(range(12))
    for row in rows:                                  # each point at its own wavelength, before and after the kill
        assert row["detail"]["wavelength_nm"] == pytest.approx(wl[row["idx"]], abs=0.01)
    assert len(refs) == 4 == len(set(wl))            # one monitor reference per wavelength, the killed run's kept
    raw = {f"{RAW_DIR}/{p.name}" for p in (session / RAW_DIR).iterdir()}
    assert sorted(raw - committed_files(session)) == []
