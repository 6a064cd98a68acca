"""Session folder, journal and crash-safe files."""

import os
import sqlite3
import sys
import tomllib

import pytest

from gonio.core.files import atomic_write_bytes, make_durable, remove_orphans, sha256_file, tmp_name
from gonio.bench.session.journal import Journal, SessionLock, dumps_toml, read_session, write_session
from gonio.core.errors import SessionError


def test_journal_pragmas_and_rows(tmp_path):
    with Journal(tmp_path / "j.sqlite") as j:
        assert j.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert j.db.execute("PRAGMA synchronous").fetchone()[0] == 2          # FULL
        j.record_frame("dark:0.004", "dark", 0.004, "raw/d.dng", "ab" * 32)
        j.record_point(3, (30, 0, 40, 180), (1, 2, 3, 4), [0.1, 0.2, 0.3], [0.01, 0.02, 0.03], False,
                       {"exposures": [{"file": "raw/p.dng", "sha256": "cd" * 32}]})
        with pytest.raises(sqlite3.IntegrityError):                           # a point is journalled once
            j.record_point(3, (30, 0, 40, 180), (1, 2, 3, 4), [0, 0, 0], [0, 0, 0], False, {})
    with Journal(tmp_path / "j.sqlite") as j:                                   # committed: survives a reopen
        assert j.done() == {3} and j.frames("dark") == {"dark:0.004": (0.004, "raw/d.dng", "ab" * 32)}
        assert j.frames("flat") == {}
        row = j.points()[0]
        assert row["brdf"] == [0.1, 0.2, 0.3] and row["theta_o"] == 40 and row["saturated"] == 0


def test_toml_round_trip(tmp_path):
    doc = {"session": {"seed": 3, "name": 'a "quoted" name', "ok": True},
           "plan": {"points": [[30.0, 0.0, 40.0, 180.0]], "name": "x"},
           "settings": {"axes": {"yaw": [1, 1, -95.0, 95.0], "cycle_dist": 720000}, "reference": {"reflectance": 0.99}}}
    write_session(tmp_path / "s", doc)
    assert read_session(tmp_path / "s") == doc
    assert (tmp_path / "s" / "raw").is_dir()
    assert tomllib.loads(dumps_toml({"a": {"b": {"c": 1.5}}})) == {"a": {"b": {"c": 1.5}}}


def test_not_a_session(tmp_path):
    with pytest.raises(SessionError, match="not a gonio session"):
        read_session(tmp_path)
    (tmp_path / "session.toml").write_text("x = [")
    with pytest.raises(SessionError, match="corrupt"):
        read_session(tmp_path)


def test_atomic_files(tmp_path):
    digest = atomic_write_bytes(tmp_path / "a.bin", b"hello")
    assert digest == sha256_file(tmp_path / "a.bin") and not tmp_name(tmp_path / "a.bin").exists()
    tmp_name(tmp_path / "b.dng").write_bytes(b"half")
    (tmp_path / "c.dng.part").write_bytes(b"half")
    assert sorted(p.name for p in remove_orphans(tmp_path)) == [".tmp-b.dng", "c.dng.part"]
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_a_batch_is_made_durable_by_one_sync_or_an_fsync_each(tmp_path, monkeypatch):
    """make_durable (the flat field's set): Linux's syncfs once, no fsync; where syncfs is
    missing or fails, an fsync of every file and of their folder; an fsync's error raised."""
    from gonio.core import atomic

    files = [tmp_path / f"flat_{k}.dng" for k in range(5)]
    for f in files:
        f.write_bytes(b"frame")
    fsynced, real = [], os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: fsynced.append(os.readlink(f"/proc/self/fd/{fd}")) or real(fd))
    if sys.platform.startswith("linux") and atomic._syncfs() is not None:
        make_durable(files)
        assert fsynced == []
    monkeypatch.setattr(atomic, "_syncfs", lambda: (lambda fd: -1))      # syncfs failing
    make_durable(files)
    assert sorted(fsynced) == sorted([str(f) for f in files] + [str(tmp_path)])
    fsynced.clear()
    monkeypatch.setattr(atomic, "_syncfs", lambda: None)                 # no syncfs here
    monkeypatch.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(OSError(28, "No space left on device")))
    with pytest.raises(OSError, match="No space"):
        make_durable(files)
    make_durable([])                                                     # nothing to do


def test_session_lock_is_exclusive(tmp_path):
    with SessionLock(tmp_path):
        with pytest.raises(SessionError, match="in use by another capture"):
            with SessionLock(tmp_path):
                pass
    with SessionLock(tmp_path):                 # released
        pass
