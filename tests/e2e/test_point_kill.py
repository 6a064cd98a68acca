"""A capture killed (SIGKILL) while a point's bracket is on disk but not yet journalled (issue
36): the resumed run deletes those frames before measuring the point again, so the finished
session's raw/ holds exactly the files its journal commits."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from gonio.bench.session.journal import RAW_DIR

from capture_process import ENV, GONIO, committed_files


def _point_files(session: Path) -> set[str]:
    raw = session / RAW_DIR
    return {f"{RAW_DIR}/{p.name}" for p in raw.iterdir() if p.name.startswith("p") and p.stat().st_size > 0} \
        if raw.is_dir() else set()


# A capture whose sixth point is held just before its journal row is written: its frames are
# on disk and checked, its row is not. Deterministic where a race with the running capture was
# not (the row of the point seen pending could be committed before the kill landed).
_HELD = """
import pathlib, sys, time
from gonio.bench.session.journal import Journal
real, seen = Journal.record_point, []
def held(self, *args, **kwargs):
    seen.append(1)
    if len(seen) == 6:
        pathlib.Path(sys.argv[1]).write_text("held")
        time.sleep(3600)
    return real(self, *args, **kwargs)
Journal.record_point = held
from gonio.cli.main import main
sys.exit(main(["capture", "--sim", "--plan", "quick", "--seed", "6", "--out", sys.argv[2], "--quiet"]))
"""


def test_a_kill_between_a_points_frames_and_its_row_leaves_no_orphan(tmp_path):
    session, marker = tmp_path / "s", tmp_path / "held"
    proc = subprocess.Popen([sys.executable, "-c", _HELD, str(marker), str(session)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None and not marker.exists():
        time.sleep(0.02)
    assert marker.exists() and proc.poll() is None, "the capture did not reach its sixth point"
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=60)
    left = _point_files(session) - committed_files(session)
    assert left, "no point frame was waiting for its journal row when the capture was killed"

    r = subprocess.run(GONIO + ["capture", "--resume", str(session), "--quiet"], capture_output=True, text=True,
                       env=ENV, timeout=600)
    assert r.returncode == 0, r.stderr
    raw = {f"{RAW_DIR}/{p.name}" for p in (session / RAW_DIR).iterdir()}
    orphans = sorted(raw - committed_files(session))
    assert orphans == [], f"{len(orphans)} orphan files after the resume: {orphans[:5]}"
