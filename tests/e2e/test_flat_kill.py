"""A capture killed (SIGKILL) while it takes the flat-field frames (issue 36): the resumed run
deletes the frames of the incomplete set before taking it again, so the finished session's
raw/ holds exactly the files its journal commits (it kept up to 353 orphan frames a kill)."""

import os
import signal
import subprocess
import time
from pathlib import Path

from gonio.bench.session.journal import RAW_DIR

from capture_process import ENV, GONIO, committed_files


def _raw(session: Path) -> set[str]:
    return {f"{RAW_DIR}/{p.name}" for p in (session / RAW_DIR).iterdir()} if (session / RAW_DIR).is_dir() else set()


def test_a_kill_during_the_flat_field_leaves_no_orphan_frames(tmp_path):
    session = tmp_path / "s"
    proc = subprocess.Popen(GONIO + ["capture", "--sim", "--plan", "quick", "--seed", "5", "--out", str(session),
                                     "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    deadline = time.monotonic() + 180
    flats = set()
    while time.monotonic() < deadline and proc.poll() is None:
        flats = {f for f in _raw(session) if "/flat_" in f and (session / f).stat().st_size > 0}
        if len(flats) >= 20:
            break
        time.sleep(0.01)
    assert proc.poll() is None, "the capture finished before the test could kill it"
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    assert len(flats) >= 20 and not committed_files(session) & flats      # frames of an uncommitted set

    r = subprocess.run(GONIO + ["capture", "--resume", str(session), "--quiet"], capture_output=True, text=True,
                       env=ENV, timeout=600)
    assert r.returncode == 0, r.stderr
    committed = committed_files(session)
    assert any("/flat_" in f for f in committed)
    orphans = sorted(_raw(session) - committed)
    assert orphans == [], f"{len(orphans)} orphan files after the resume: {orphans[:5]}"
