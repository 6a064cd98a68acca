"""A capture killed (SIGKILL) while a point's bracket is on disk but not yet journalled (issue
36): the resumed run deletes those frames before measuring the point again, so the finished
session's raw/ holds exactly the files its journal commits."""

import os
import signal
import sqlite3
import subprocess
import time
from pathlib import Path

from gonio.bench.session.journal import RAW_DIR

from capture_process import ENV, GONIO, committed_files


def _point_files(session: Path) -> set[str]:
    raw = session / RAW_DIR
    return {f"{RAW_DIR}/{p.name}" for p in raw.iterdir() if p.name.startswith("p") and p.stat().st_size > 0} \
        if raw.is_dir() else set()


def _journalled_files(session: Path) -> set[str]:
    """The point files the journal names now, read-only (the capture is still writing it)."""
    try:
        db = sqlite3.connect(f"file:{session / 'journal.sqlite'}?mode=ro", uri=True, timeout=0.2)
        try:
            rows = db.execute("SELECT detail FROM points").fetchall()
        finally:
            db.close()
    except sqlite3.Error:
        return set()
    import json
    return {e["file"] for (d,) in rows for e in json.loads(d).get("exposures", [])}


def test_a_kill_between_a_points_frames_and_its_row_leaves_no_orphan(tmp_path):
    session = tmp_path / "s"
    proc = subprocess.Popen(GONIO + ["capture", "--sim", "--plan", "quick", "--seed", "6", "--out", str(session),
                                     "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    deadline = time.monotonic() + 240
    pending: set[str] = set()
    while time.monotonic() < deadline and proc.poll() is None:
        files = _point_files(session)
        if len(files) >= 6:
            pending = files - _journalled_files(session)
            if pending:
                break
        time.sleep(0.02)
    assert proc.poll() is None, "the capture finished before the test could kill it"
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
