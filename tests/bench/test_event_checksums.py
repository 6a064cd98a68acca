"""Events carry checksums like points (issue 36): what export and resume read from an event
(the camera's colour matrix, the reference monitor's reading) is never used damaged, `gonio
verify` reports it, and `--rebuild-journal` keeps only the events that pass."""

from __future__ import annotations

import shutil
import sqlite3

import pytest

from gonio.bench.session.journal import Journal, event_checksum
from gonio.core.errors import SessionError


def _journal(tmp_path):
    j = Journal(tmp_path / "journal.sqlite")
    j.event("p_ref", "0.00123")
    j.event("rgb_cam", "[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]")
    return j


def test_an_event_is_checked_when_read(tmp_path):
    j = _journal(tmp_path)
    assert j.first_event("p_ref") == "0.00123" and [k for _, k, _ in j.events()] == ["p_ref", "rgb_cam"]
    # a flipped digit in the stored text (0.00123 -> 0.00133), as a bad sector would leave it
    j.db.execute("UPDATE events SET text = '0.00133' WHERE kind = 'p_ref'")
    j.db.commit()
    with pytest.raises(SessionError, match="1 event row\\(s\\) are damaged .*gonio verify .*--rebuild-journal"):
        j.first_event("rgb_cam")
    good, bad = j.checked_events()
    assert [k for _, k, _ in good] == ["rgb_cam"] and len(bad) == 1
    j.close()


def test_a_journal_from_before_event_checksums_is_read_unchecked_then_upgraded(tmp_path):
    db = sqlite3.connect(tmp_path / "journal.sqlite")
    db.execute("CREATE TABLE events (id INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, kind TEXT NOT NULL, "
               "text TEXT NOT NULL)")
    db.execute("INSERT INTO events (time, kind, text) VALUES (1.5, 'p_ref', '0.002')")
    db.commit()
    db.close()
    j = Journal(tmp_path / "journal.sqlite")
    assert j.first_event("p_ref") == "0.002"
    j.event("warning", "x")                       # the first new event adds the column
    rows = list(j.db.execute("SELECT kind, checksum FROM events ORDER BY id"))
    assert rows[0] == ("p_ref", None) and rows[1][1] == event_checksum(*next(
        (t, k, x) for t, k, x in j.events() if k == "warning"))
    j.close()


def test_salvage_keeps_only_events_that_pass(tmp_path):
    from gonio.bench.session.salvage import _event_ok

    ok = {"time": 2.0, "kind": "p_ref", "text": "0.1", "checksum": event_checksum(2.0, "p_ref", "0.1")}
    assert _event_ok(ok) and _event_ok({**ok, "checksum": None})
    assert not _event_ok({**ok, "text": "0.2"}) and not _event_ok({**ok, "checksum": b"\xff"})


def test_a_checksum_that_no_longer_decodes_is_a_damaged_row_not_a_traceback(tmp_path):
    """A flipped high bit leaves the stored checksum text invalid UTF-8: SQLite's text decoding
    raised OperationalError out of `gonio verify` (the long journal corpus, bit 0x80)."""
    j = _journal(tmp_path)
    j.db.execute("UPDATE events SET checksum = CAST(X'6565ff31' AS TEXT) WHERE kind = 'p_ref'")
    j.db.commit()
    good, bad = j.checked_events()
    assert [k for _, k, _ in good] == ["rgb_cam"] and len(bad) == 1
    j.close()


def test_a_damaged_event_is_rebuilt_not_whole(tmp_path):
    """Export refuses a session whose event row fails its checksum and points to
    `--rebuild-journal`; the rebuild then ran into "whole and consistent; nothing to rebuild"
    (it checked the points only): a dead end. Now it rebuilds, keeps every point, and drops the
    damaged event."""
    from gonio.bench.dataset.export import to_dataset
    from gonio.bench.samples import load_sample
    from gonio.bench.session import integrity
    from gonio.bench.session.verify import verify_session
    from gonio.cli.capture import capture_sim

    folder = tmp_path / "session"
    capture_sim(folder, sample=load_sample(None), plan="quick", seed=1, progress=False)
    before = to_dataset(folder)
    with Journal(folder / "journal.sqlite") as j:
        n = len(j.points())
        kinds = [k for _, k, _ in j.events()]
        j.db.execute("UPDATE events SET text = text || ' ' WHERE id = (SELECT min(id) FROM events)")
        j.db.commit()
    assert not verify_session(folder).ok
    with pytest.raises(SessionError, match="event row\\(s\\) are damaged") as exc:
        to_dataset(folder)
    assert "\n" not in str(exc.value)
    text, doc, why = integrity.load_session(folder)
    line = integrity.rebuild_journal(folder, text, doc, why)
    assert line.startswith(f"rebuilt the journal: {n} point(s) recovered")
    with Journal(folder / "journal.sqlite") as j:
        assert len(j.points()) == n
        after = [k for _, k, _ in j.events()]
    # the damaged one left out, every other one kept (export reads the instrument time, the open
    # beam, ... from them: a rebuild that kept three kinds changed instrument_time_s silently)
    assert after == kinds[1:] + ["rebuild"]
    assert verify_session(folder).ok
    ds = to_dataset(folder)
    assert ds.sizes["point"] == n and ds.attrs["instrument_time_s"] == before.attrs["instrument_time_s"]


def test_salvage_refuses_an_event_a_flipped_type_byte_left_without_time_or_text():
    """A row journalled before checksums has none, so only its form can be checked: a NULL or
    non-finite time, or a kind or text that is not text, is damage (the long journal corpus:
    a rebuild that kept every event kind then failed on float(None))."""
    from gonio.bench.session.salvage import _event_ok

    ok = {"time": 2.0, "kind": "p_ref", "text": "0.1", "checksum": None}
    assert _event_ok(ok)
    for bad in ({"time": None}, {"time": float("nan")}, {"time": True}, {"kind": None}, {"text": 3.0}):
        assert not _event_ok({**ok, **bad}), bad
