"""A `gonio capture --sim` in its own process, for the kill and signal tests."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import time

GONIO = [sys.executable, "-m", "gonio.cli.main"]
ENV = dict(os.environ, PYTHONWARNINGS="ignore")


def journalled(session) -> int:
    """Points committed to the session's journal so far (0 while it cannot be read)."""
    journal = session / "journal.sqlite"
    if not journal.exists():
        return 0
    try:
        return sqlite3.connect(journal).execute("SELECT count(*) FROM points").fetchone()[0]
    except sqlite3.Error:
        return 0


def start_capture(session, *, after_points: int = 3, timeout_s: float = 180.0):
    """`gonio capture --sim --plan quick --seed 5` started, returned once it has journalled
    ``after_points`` points (asserting it is still running): (process, points journalled)."""
    proc = subprocess.Popen(GONIO + ["capture", "--sim", "--plan", "quick", "--seed", "5", "--out", str(session),
                                     "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    deadline = time.monotonic() + timeout_s
    done = 0
    while time.monotonic() < deadline and proc.poll() is None:
        done = journalled(session)
        if done >= after_points:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the capture finished before the test could stop it"
    return proc, done


def committed_files(session) -> set[str]:
    """Every RAW file the session's journal commits: calibration frames and points' exposures."""
    from gonio.bench.session.journal import Journal

    j = Journal(session / "journal.sqlite")
    try:
        files = {v[1] for kind in ("dark", "flat", "chart") for v in j.frames(kind).values()}
        files |= {e["file"] for row in j.points() for e in row["detail"].get("exposures", [])}
    finally:
        j.close()
    return files
