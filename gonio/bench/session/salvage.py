"""What a damaged journal still holds: every point whose row is whole, and which are damaged.

Two readings of a private copy of ``journal.sqlite`` (and its ``-wal``), merged: SQLite's,
one query per plan point (a damaged page loses only its own rows), and a reading of the
file's pages without SQLite (`gonio.bench.session.pages`), which still finds the rows when
the header page, the schema or the points table's root page is damaged. A point row counts
as whole only if it matches its checksum (`gonio.bench.session.journal.point_checksum`);
rows journalled before checksums are taken as SQLite reads them (the rebuild then checks them
against the plan and their RAW files). Of several whole copies of a point (older copies
linger in freed pages and in the -wal) the latest is kept, never one the journal moved to
``superseded``. Nothing in the session folder is written.
"""

from __future__ import annotations

import json
import math
import shutil
import sqlite3
import tempfile
from pathlib import Path
from typing import Any

from gonio.bench.session import pages
from gonio.bench.session.journal import POINT_COLUMNS, decode_point, event_checksum

__all__ = ["salvage"]


def _event_ok(e) -> bool:
    """An event row is well formed (a finite time, text kind and text) and passes its checksum,
    or has none (journalled before checksums)."""
    digest = e.get("checksum")
    when = e.get("time")
    if isinstance(when, bool) or not isinstance(when, (int, float)) or not math.isfinite(when) \
            or not all(isinstance(e.get(k), (str, bytes)) for k in ("kind", "text")):
        return False          # a flipped type byte reads a column as NULL or a number
    try:
        return digest is None or event_checksum(e["time"], e["kind"], e["text"]) == (
            bytes(digest).decode("ascii") if isinstance(digest, (bytes, bytearray)) else digest)
    except (UnicodeDecodeError, TypeError, ValueError, KeyError):
        return False
_CAL_KINDS = (b"dark", b"flat", b"chart")
_SELECT = ", ".join(f"CAST({c} AS BLOB)" if c in ("brdf", "brdf_std", "detail") else c for c in POINT_COLUMNS)


def _text(v) -> str:
    return bytes(v).decode("utf-8") if isinstance(v, (bytes, bytearray)) else v


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


class _Points:
    """Candidate rows of each point, then the choice of one."""

    def __init__(self):
        self.good: dict[int, list[tuple[dict, dict, bool]]] = {}     # idx -> (stored, decoded, checked)
        self.bad: dict[int, str] = {}

    def add(self, values, checksum, lost_why: str = "") -> None:
        row, why = decode_point(values, checksum)
        if row is None:
            k = values[0] if isinstance(values[0], int) else -1
            self.bad.setdefault(k, why)
            return
        stored = {c: _text(v) for c, v in zip(POINT_COLUMNS, values)}
        stored["checksum"] = _text(checksum)
        self.good.setdefault(row["idx"], []).append((stored, row, checksum is not None))

    def choose(self, n: int, superseded: set) -> tuple[list[dict], list[dict], dict[int, str], int]:
        """(stored rows, decoded rows, damaged {idx: why}, unchecked) of the plan's points."""
        stored, decoded, unchecked = [], [], 0
        for k in sorted(self.good):
            if not 0 <= k < n:
                continue
            live = [c for c in self.good[k] if (k, c[1]["finished"]) not in superseded]
            checked = [c for c in live if c[2]]
            pick = max(checked or live, key=lambda c: c[1]["finished"], default=None)
            if pick is None:
                continue
            stored.append(pick[0])
            decoded.append(pick[1])
            unchecked += not pick[2]
        have = {r["idx"] for r in decoded}
        damaged = {k: why for k, why in sorted(self.bad.items()) if 0 <= k < n and k not in have}
        return stored, decoded, damaged, unchecked


def _sqlite_pass(path: Path, n: int, pts: _Points, out: dict) -> set:
    """SQLite's reading; returns the (idx, finished) of superseded rows. Fills ``out``'s
    session, calibration and events where their tables read whole."""
    superseded: set = set()
    try:
        db = sqlite3.connect(str(path), timeout=5.0)
    except sqlite3.Error:
        return superseded

    def rows(sql, args=()):
        """(rows as dicts, True if the query read to the end)."""
        try:
            cur = db.execute(sql, args)
            names = [d[0] for d in cur.description]
            return [dict(zip(names, r)) for r in cur.fetchall()], True
        except (sqlite3.Error, ValueError, OverflowError):
            return [], False

    try:
        session, ok = rows("SELECT key, value FROM session")
        if ok:
            out["session"] = {r["key"]: r["value"] for r in session}
        cal, ok = rows("SELECT * FROM calibration")
        out["calibration"] = cal if ok else None
        events, ok = rows("SELECT * FROM events ORDER BY id")
        out["events"] = [e for e in events if _event_ok(e)] if ok else None      # every kind: export reads many
        for r in rows("SELECT idx, row FROM superseded")[0]:
            try:
                superseded.add((int(r["idx"]), float(json.loads(r["row"])["finished"])))
            except (KeyError, TypeError, ValueError):
                pass
        cols, ok = rows("PRAGMA table_info(points)")
        if not ok or not cols:
            return superseded
        out["readable"] = True
        check = "checksum" if any(c["name"] == "checksum" for c in cols) else "NULL"
        sql = f"SELECT {_SELECT}, {check} FROM points WHERE "
        for k in range(n):                   # one lookup per index: a bad page loses only its rows
            found, ok = rows(sql + "idx = ?", (k,))
            if not ok:
                pts.bad.setdefault(k, "SQLite cannot read its journal row (a damaged page)")
            for r in found:
                v = list(r.values())
                pts.add(v[:-1], v[-1])
        for r in rows(sql + "idx < 0 OR idx >= ?", (n,))[0]:       # a damaged index
            v = list(r.values())
            pts.add(v[:-1], v[-1])
    finally:
        db.close()
    return superseded


def _judge(rowid, values):
    if len(values) == 15 and values[0] is None and values[14] is not None:
        return decode_point((rowid, *values[1:14]), values[14])[0] is not None
    return None


def _page_pass(path: Path, n: int, pts: _Points, out: dict, superseded: set) -> None:
    """The pages' reading: points always; the other tables where SQLite could not read them."""
    try:
        cells = pages.scan(path, _judge)
    except (OSError, MemoryError):
        return
    cal: dict[bytes, dict] = {}
    events: dict[int, dict] = {}
    session: dict[str, str] = {}
    for c in cells:
        v = c.values
        if len(v) in (14, 15) and v[0] is None:
            pts.add((c.rowid, *v[1:14]), v[14] if len(v) == 15 else None)
        elif len(v) == 5 and v[0] is None and isinstance(v[1], int) and isinstance(v[2], bytes):
            try:
                superseded.add((v[1], float(json.loads(v[2])["finished"])))
            except (KeyError, TypeError, ValueError, UnicodeDecodeError):
                pass
        elif (len(v) == 6 and v[1] in _CAL_KINDS and all(isinstance(v[k], bytes) for k in (0, 3, 4))
              and _number(v[2]) and _number(v[5]) and len(v[4]) == 64):
            try:
                row = {"name": _text(v[0]), "kind": _text(v[1]), "seconds": float(v[2]), "file": _text(v[3]),
                       "sha256": _text(v[4]), "finished": float(v[5])}
            except UnicodeDecodeError:
                continue
            if row["name"] not in cal or cal[row["name"]]["finished"] < row["finished"]:
                cal[row["name"]] = row
        elif len(v) in (4, 5) and v[0] is None and _number(v[1]) and isinstance(v[2], bytes) \
                and isinstance(v[3], bytes) and (len(v) == 4 or v[4] is None or isinstance(v[4], bytes)):
            try:
                e = {"id": c.rowid, "time": float(v[1]), "kind": _text(v[2]), "text": _text(v[3]),
                     "checksum": _text(v[4]) if len(v) == 5 and v[4] is not None else None}
                if _event_ok(e):
                    events.setdefault(c.rowid, e)
            except UnicodeDecodeError:
                pass
        elif len(v) == 2 and v[0] in (b"sha256", b"text", b"doc") and isinstance(v[1], bytes):
            try:
                session.setdefault(_text(v[0]), _text(v[1]))
            except UnicodeDecodeError:
                pass
    if out["calibration"] is None:
        out["calibration"] = sorted(cal.values(), key=lambda r: r["name"])
    if out["events"] is None:
        out["events"] = [events[k] for k in sorted(events)]
    if not out["session"]:
        out["session"] = session
        out["session_from_pages"] = bool(session)


def salvage(path: Path, n: int) -> dict[str, Any]:
    """What the journal ``path`` of a plan of ``n`` points still holds.

    Returns a dict: ``points`` (rows as stored, with their ``checksum``: what
    `Journal.insert_rows` takes), ``decoded`` (the same rows, JSON decoded), ``damaged``
    (``{index: why}`` of plan points found only damaged or not readable), ``unchecked``
    (points without a checksum), ``calibration``, ``events`` (those a resume needs),
    ``session`` (the recorded session.toml: keys sha256, text, doc, as far as found) and
    ``readable`` (SQLite could read the points table).
    """
    out: dict[str, Any] = {"session": {}, "calibration": None, "events": None, "readable": False,
                           "session_from_pages": False}
    pts = _Points()
    superseded: set = set()
    if path.is_file() and path.stat().st_size > 0:
        with tempfile.TemporaryDirectory(prefix="gonio-salvage-") as tmp:
            copy = Path(tmp) / path.name             # SQLite writes beside what it opens: a private copy
            shutil.copyfile(path, copy)
            wal = Path(str(path) + "-wal")
            if wal.is_file():
                shutil.copyfile(wal, str(copy) + "-wal")
            superseded = _sqlite_pass(copy, n, pts, out)
            _page_pass(path, n, pts, out, superseded)
    out["calibration"] = out["calibration"] or []
    out["events"] = out["events"] or []
    out["points"], out["decoded"], out["damaged"], out["unchecked"] = pts.choose(n, superseded)
    return out
