"""The session folder and its crash-safe journal.

::

    session/
      .lock           flock'ed by the one process that writes into the folder (taken first)
      session.toml    plan, instrument settings, ports, versions, seed, sample truth: written
                      ONCE, before the first move (checked by `gonio.bench.session.integrity`)
      journal.sqlite  WAL, synchronous=FULL: a committed row per finished point, calibration
                      frame and event; RAW files' SHA-256; RAW names reserved before writing
      raw/            RAW files (temporary name, fsync, rename; never overwritten)
      dataset.nc      after export

A point's row is one transaction, written after everything about it succeeded; point and event
rows carry checksums of their stored values, checked whenever they are read.
"""

# The lock is taken before anything else is written. session.toml goes through a temporary
# name; its SHA-256 and text are recorded in the journal and checked by every resume and
# export. Every RAW file's name is reserved (committed) before the camera writes it, and the
# journal is the only record of what is done: a file in raw/ that it does not name means the
# journal lost commits.

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import math
import os
import platform
import sqlite3
import time
import tomllib
from importlib import metadata
from pathlib import Path
from typing import Any, Iterable, Mapping

from gonio.core.files import sha256_file, write_new_text
from gonio.core.preflight import mount_of
from gonio.core.errors import SessionError

__all__ = ["SESSION_FILE", "JOURNAL_FILE", "RAW_DIR", "LOCK_FILE", "Journal", "SessionLock", "write_session",
           "read_session", "session_text", "verify_files", "damaged_files", "dumps_toml", "versions",
           "POINT_COLUMNS", "point_checksum", "decode_point", "event_checksum", "preparation_times"]

SESSION_FILE = "session.toml"
JOURNAL_FILE = "journal.sqlite"
RAW_DIR = "raw"
LOCK_FILE = ".lock"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS calibration (   -- dark and flat-field frames
    name TEXT PRIMARY KEY,       -- e.g. "dark:0.004", "flat:3"
    kind TEXT NOT NULL,          -- "dark" | "flat"
    seconds REAL NOT NULL,
    file TEXT NOT NULL,
    sha256 TEXT NOT NULL,
    finished REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS points (
    idx INTEGER PRIMARY KEY,
    theta_i REAL, phi_i REAL, theta_o REAL, phi_o REAL,
    yaw REAL, tilt REAL, azimuth REAL, lamp REAL,
    brdf TEXT NOT NULL,          -- JSON [R, G, B], sr^-1
    brdf_std TEXT NOT NULL,      -- JSON [R, G, B], sr^-1, 1-sigma
    saturated INTEGER NOT NULL,
    detail TEXT NOT NULL,        -- JSON: exposures, files, checksums, monitor, region statistics
    finished REAL NOT NULL,
    checksum TEXT                -- point_checksum of the columns above (NULL: journalled before checksums)
);
CREATE TABLE IF NOT EXISTS session (       -- what session.toml was when the session started
    key TEXT PRIMARY KEY,        -- "sha256", "text", "doc" (canonical JSON)
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS files (         -- every RAW file name, reserved before it is written
    file TEXT PRIMARY KEY,
    reserved REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS superseded (    -- point rows replaced by a new measurement
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    idx INTEGER NOT NULL,
    row TEXT NOT NULL,           -- JSON of the old points row
    why TEXT NOT NULL,
    time REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    time REAL NOT NULL,
    kind TEXT NOT NULL,
    text TEXT NOT NULL,
    checksum TEXT                -- event_checksum of time, kind and text (NULL: journalled before checksums)
);
"""


POINT_COLUMNS = ("idx", "theta_i", "phi_i", "theta_o", "phi_o", "yaw", "tilt", "azimuth", "lamp", "brdf",
                 "brdf_std", "saturated", "detail", "finished")
_REAL = frozenset(range(1, 9)) | {13}           # the REAL columns of POINT_COLUMNS
_TEXT = (9, 10, 12)                             # the TEXT columns (JSON)
# the stored values, text as bytes: a damaged row never fails inside SQLite's UTF-8 decoding
_SELECT_POINTS = ("SELECT " + ", ".join(f"CAST({c} AS BLOB)" if k in _TEXT else c for k, c in enumerate(POINT_COLUMNS))
                  + ", CAST(checksum AS BLOB) FROM points")
_SELECT_UNCHECKED = _SELECT_POINTS.replace(", CAST(checksum AS BLOB) FROM", ", NULL FROM")     # before checksums


def point_checksum(values) -> str:
    """SHA-256 (hex) of a points row's stored values, in `POINT_COLUMNS` order.

    Canonical form: the values as a compact JSON list, text as UTF-8 text, every REAL a float
    (``-0.0`` as ``0.0`` and NaN as null: what SQLite gives back for them). Raises
    `UnicodeDecodeError` for text that is not UTF-8 (a damaged row).
    """
    canon = []
    for k, v in enumerate(values):
        if isinstance(v, (bytes, bytearray, memoryview)):
            v = bytes(v).decode("utf-8")
        elif k in _REAL and isinstance(v, (int, float)) and not isinstance(v, bool):
            v = None if math.isnan(v) else float(v) + 0.0
        canon.append(v)
    text = json.dumps(canon, ensure_ascii=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def event_checksum(when, kind, text) -> str:
    """SHA-256 (hex) of an event's stored values (time as a float, kind and text as UTF-8):
    what export and resume read from an event (the camera's colour matrix, the reference
    monitor's reading) is as checked as a point."""
    if isinstance(kind, (bytes, bytearray, memoryview)):
        kind = bytes(kind).decode("utf-8")
    if isinstance(text, (bytes, bytearray, memoryview)):
        text = bytes(text).decode("utf-8")
    canon = json.dumps([float(when) + 0.0, kind, text], ensure_ascii=True, separators=(",", ":"))
    return hashlib.sha256(canon.encode("ascii")).hexdigest()


def decode_point(values, checksum) -> tuple[dict[str, Any] | None, str]:
    """``(row, "")`` of a points row's stored values (`POINT_COLUMNS` order, text as bytes or
    str) and its stored checksum, JSON columns decoded; ``(None, why)`` if the row is damaged.
    A row without a checksum (journalled before checksums) is decoded unchecked."""
    values = list(values)
    if len(values) != len(POINT_COLUMNS):
        return None, "its row has the wrong number of columns"
    try:
        if checksum is not None:
            if isinstance(checksum, (bytes, bytearray)):
                checksum = bytes(checksum).decode("ascii")
            if point_checksum(values) != checksum:
                return None, "its journal row fails its checksum"
        row = {}
        for k, (name, v) in enumerate(zip(POINT_COLUMNS, values)):
            if isinstance(v, (bytes, bytearray, memoryview)):
                v = bytes(v).decode("utf-8")
            if k in _REAL and isinstance(v, int) and not isinstance(v, bool):
                v = float(v)
            row[name] = json.loads(v) if k in _TEXT else v
    except (UnicodeDecodeError, ValueError, TypeError):
        return None, "its journal row is not readable"
    if not isinstance(row["idx"], int) or not all(isinstance(row[c], list) for c in ("brdf", "brdf_std")) \
            or not isinstance(row["detail"], dict):
        return None, "its journal row is malformed"
    return row, ""


class SessionLock:
    """An exclusive lock on a session folder while a process measures into it.

    ``flock`` on ``.lock``: the kernel releases it when the process dies, however it dies, so
    a killed capture never leaves a stale lock behind.
    """

    def __init__(self, folder: str | Path):
        self.path = Path(folder) / LOCK_FILE
        self.fd = None

    def __enter__(self) -> "SessionLock":
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self.fd)
            self.fd = None
            raise SessionError(f"{self.path.parent} is in use by another capture; wait for it or stop it first") from None
        return self

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def versions() -> dict[str, str]:
    """Versions of gonio, Python and the packages a dataset depends on."""
    out = {"python": platform.python_version()}
    for pkg in ("gonio", "numpy", "scipy", "pyserial", "rawpy", "xarray", "h5netcdf"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "unknown"
    return out


class Journal:
    """The SQLite journal of a session (WAL mode, ``synchronous=FULL``)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        try:
            self.db = sqlite3.connect(str(self.path), isolation_level=None, timeout=30.0)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=FULL")
            self.db.executescript(_SCHEMA)
        except sqlite3.DatabaseError as exc:
            if getattr(exc, "sqlite_errorcode", None) == sqlite3.SQLITE_FULL or "disk is full" in str(exc):
                raise                            # not damage: the caller says the disk is full
            raise SessionError(f"journal {self.path} is unreadable ({exc}); the session folder is damaged") from None

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> "Journal":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def record_frame(self, name: str, kind: str, seconds: float, file: str, sha256: str) -> None:
        """Commit a calibration frame (``kind`` "dark" or "flat", exposure s, file relative to the session)."""
        self.record_frames([(name, kind, seconds, file, sha256)])

    def record_frames(self, rows: Iterable[tuple[str, str, float, str, str]]) -> None:
        """Commit a set of calibration frames, ``(name, kind, seconds, file, sha256)`` each, in
        one transaction: all of them or none (the flat field's set)."""
        now = time.time()
        with self.db:
            self.db.execute("BEGIN")
            self.db.executemany("INSERT OR REPLACE INTO calibration VALUES (?, ?, ?, ?, ?, ?)",
                                [(*row, now) for row in rows])

    def frames(self, kind: str) -> dict[str, tuple[float, str, str]]:
        """``{name: (seconds, file, sha256)}`` of the committed calibration frames of ``kind``."""
        return {r[0]: (r[1], r[2], r[3]) for r in self.db.execute(
            "SELECT name, seconds, file, sha256 FROM calibration WHERE kind = ? ORDER BY name", (kind,))}

    def forget_frames(self, kind: str) -> None:
        """Drop the calibration frames of ``kind`` (an incomplete set is taken again whole)."""
        with self.db:
            self.db.execute("BEGIN")
            self.db.execute("DELETE FROM calibration WHERE kind = ?", (kind,))

    # -- the session record and the RAW file names -------------------------------------
    def record_session(self, text: str, doc: Mapping[str, Any]) -> None:
        """Record session.toml (its SHA-256, text and parsed content) once, when the session starts."""
        rows = [("sha256", hashlib.sha256(text.encode("utf-8")).hexdigest()), ("text", text),
                ("doc", json.dumps(doc, sort_keys=True, default=str))]
        with self.db:
            self.db.execute("BEGIN")
            self.db.executemany("INSERT INTO session VALUES (?, ?)", rows)

    def session_record(self) -> dict[str, str]:
        """``{"sha256", "text", "doc"}`` as recorded (empty if the session was never recorded)."""
        return dict(self.db.execute("SELECT key, value FROM session"))

    def reserve(self, file: str) -> None:
        """Commit a RAW file's name before the camera writes it (so no file goes unaccounted for)."""
        with self.db:
            self.db.execute("BEGIN")
            self.db.execute("INSERT INTO files VALUES (?, ?)", (file, time.time()))

    def reserve_all(self, files: Iterable[str]) -> None:
        with self.db:
            self.db.execute("BEGIN")
            self.db.executemany("INSERT OR IGNORE INTO files VALUES (?, ?)", [(f, time.time()) for f in files])

    def reserved(self) -> set[str]:
        """Every RAW file name the journal ever reserved."""
        return {r[0] for r in self.db.execute("SELECT file FROM files")}

    def supersede(self, idxs: Iterable[int], why: str) -> list[int]:
        """Move the rows of points ``idxs`` to ``superseded`` (one transaction): they are measured again."""
        idxs = sorted({int(i) for i in idxs})
        moved = []
        with self.db:
            self.db.execute("BEGIN")
            for i in idxs:
                cur = self.db.execute("SELECT * FROM points WHERE idx = ?", (i,))
                row = cur.fetchone()
                if row is None:
                    continue
                names = [d[0] for d in cur.description]
                self.db.execute("INSERT INTO superseded (idx, row, why, time) VALUES (?, ?, ?, ?)",
                                (i, json.dumps(dict(zip(names, row))), why, time.time()))
                self.db.execute("DELETE FROM points WHERE idx = ?", (i,))
                moved.append(i)
        return moved

    def superseded_files(self) -> set[str]:
        """The RAW files of every superseded point row (kept: they are the session's history)."""
        out: set[str] = set()
        for (text,) in self.db.execute("SELECT row FROM superseded"):
            try:
                detail = json.loads(json.loads(text).get("detail") or "{}")
                out.update(str(e["file"]) for e in detail.get("exposures", []))
            except (ValueError, TypeError, KeyError, AttributeError):
                continue      # a damaged history row: its files are kept, none is named here
        return out

    def forget_frame(self, name: str) -> None:
        with self.db:
            self.db.execute("BEGIN")
            self.db.execute("DELETE FROM calibration WHERE name = ?", (name,))

    def insert_rows(self, table: str, rows: list[dict[str, Any]]) -> None:
        """Insert rows salvaged from a damaged journal (``--rebuild-journal``) as they were."""
        if not rows:
            return
        if table == "events":                      # salvaged events get their checksums again
            rows = [{**r, "checksum": event_checksum(r["time"], r["kind"], r["text"])} for r in rows]
        names = list(rows[0])
        with self.db:
            self.db.execute("BEGIN")
            if table == "events" and not self._events_checked():
                self.db.execute("ALTER TABLE events ADD COLUMN checksum TEXT")
            self.db.executemany(f"INSERT INTO {table} ({', '.join(names)}) VALUES ({', '.join('?' * len(names))})",
                                [tuple(r[n] for n in names) for r in rows])

    def record_point(self, idx: int, angles: Iterable[float], stage: Iterable[float], brdf, brdf_std,
                     saturated: bool, detail: Mapping[str, Any]) -> None:
        """Commit one finished point and its checksum in a single transaction."""
        row = (int(idx), *map(float, angles), *map(float, stage),
               json.dumps([float(v) for v in brdf]), json.dumps([float(v) for v in brdf_std]),
               int(bool(saturated)), json.dumps(detail, sort_keys=True), time.time())
        if len(row) != len(POINT_COLUMNS):
            raise ValueError(f"a point row has {len(POINT_COLUMNS)} values, not {len(row)}")
        with self.db:
            self.db.execute("BEGIN")
            if not self._has_checksums():           # a journal from before checksums: given the column
                self.db.execute("ALTER TABLE points ADD COLUMN checksum TEXT")
            self.db.execute(f"INSERT INTO points ({', '.join(POINT_COLUMNS)}, checksum) VALUES "
                            f"({','.join('?' * (len(row) + 1))})", (*row, point_checksum(row)))

    def _has_checksums(self) -> bool:
        return any(r[1] == "checksum" for r in self.db.execute("PRAGMA table_info(points)"))

    def done(self) -> set[int]:
        """Indices of the committed points."""
        return {r[0] for r in self.db.execute("SELECT idx FROM points")}

    def checked_points(self) -> tuple[list[dict[str, Any]], dict[int, str], int]:
        """``(rows, damaged, unchecked)``: the committed points whose row is whole (JSON columns
        decoded, by plan index), ``{index: why}`` of those whose row fails its checksum or does
        not decode, and how many rows carry no checksum (journalled before checksums).
        `sqlite3.DatabaseError` where SQLite cannot read the table."""
        sql = _SELECT_POINTS if self._has_checksums() else _SELECT_UNCHECKED
        rows, damaged, unchecked = [], {}, 0
        for r in self.db.execute(sql + " ORDER BY idx"):
            row, why = decode_point(r[:-1], r[-1])
            if row is None:
                damaged[int(r[0]) if isinstance(r[0], int) else -1] = why
                continue
            unchecked += r[-1] is None
            rows.append(row)
        return rows, damaged, unchecked

    def points(self) -> list[dict[str, Any]]:
        """Every committed point as a dict (JSON columns decoded), by plan index.

        Raises a one-line `SessionError` if a row is damaged (fails its checksum, does not
        decode) or SQLite cannot read the table: no damaged row is ever used."""
        folder = self.path.parent
        try:
            rows, damaged, _ = self.checked_points()
        except sqlite3.DatabaseError as exc:
            raise SessionError(f"{self.path} is damaged ({exc}); see `gonio verify {folder}` and recover with "
                               f"`gonio capture --resume {folder} --rebuild-journal`") from None
        if damaged:
            idx = sorted(damaged)
            shown = ", ".join(map(str, idx[:10])) + (f" and {len(idx) - 10} more" if len(idx) > 10 else "")
            raise SessionError(f"{self.path}: {len(idx)} point(s) are damaged ({shown}: {damaged[idx[0]]}); see "
                               f"`gonio verify {folder}` and recover with `gonio capture --resume {folder} "
                               "--rebuild-journal`")
        return rows

    def event(self, kind: str, text: str) -> None:
        """Log an event (pause, resume, warning, fault) with the wall time and its checksum."""
        now = time.time()
        with self.db:
            self.db.execute("BEGIN")
            if not self._events_checked():          # a journal from before checksums: given the column
                self.db.execute("ALTER TABLE events ADD COLUMN checksum TEXT")
            self.db.execute("INSERT INTO events (time, kind, text, checksum) VALUES (?, ?, ?, ?)",
                            (now, kind, text, event_checksum(now, kind, text)))

    def _events_checked(self) -> bool:
        return any(r[1] == "checksum" for r in self.db.execute("PRAGMA table_info(events)"))

    def checked_events(self) -> tuple[list[tuple[float, str, str]], list[int]]:
        """``(events, damaged)``: every event whose row passes its checksum (or has none: journalled
        before checksums) as ``(time, kind, text)``, and the ids of those that fail it or do not
        decode."""
        sql = ("SELECT id, time, CAST(kind AS BLOB), CAST(text AS BLOB), "
               + ("CAST(checksum AS BLOB)" if self._events_checked() else "NULL") + " FROM events ORDER BY id")
        good, bad = [], []
        for rid, when, kind, text, digest in self.db.execute(sql):
            try:
                if digest is not None and event_checksum(when, kind, text) != (
                        bytes(digest).decode("ascii") if isinstance(digest, (bytes, bytearray)) else digest):
                    raise ValueError("checksum")
                good.append((float(when), bytes(kind).decode("utf-8"), bytes(text).decode("utf-8")))
            except (UnicodeDecodeError, ValueError, TypeError):
                bad.append(int(rid))
        return good, bad

    def events(self) -> list[tuple[float, str, str]]:
        """Every event ``(time, kind, text)`` in order; a one-line `SessionError` if one is damaged."""
        good, bad = self.checked_events()
        if bad:
            folder = self.path.parent
            raise SessionError(f"{self.path}: {len(bad)} event row(s) are damaged (id {bad[0]}: it fails its "
                               f"checksum); see `gonio verify {folder}` and recover with `gonio capture --resume "
                               f"{folder} --rebuild-journal`")
        return good

    def first_event(self, kind: str) -> str | None:
        """Text of the first event of ``kind`` (e.g. the session's reference monitor reading), or None;
        a one-line `SessionError` if any event is damaged (none is ever used)."""
        return next((text for _, k, text in self.events() if k == kind), None)


def preparation_times(events) -> list[tuple[int, float]]:
    """``(points kept before it, seconds)`` of each finished preparation the journal's
    ``instrument_time`` events record (a run's homing, calibration frames, lamp warm-up)."""
    out = []
    for _, kind, text in events:
        if kind != "instrument_time":
            continue
        try:
            d = json.loads(text)
            s, n = float(d["s"]), int(d["points"])
        except (ValueError, TypeError, KeyError):
            continue
        if math.isfinite(s) and s >= 0:
            out.append((n, s))
    return out


# -- session.toml ---------------------------------------------------------------------------

def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):        # JSON's escapes are TOML's; TOML also wants DEL escaped
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if hasattr(v, "tolist"):
        return _toml_value(v.tolist())
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _toml_key(k) -> str:
    """A bare key where TOML allows one (A-Za-z0-9_-), else a quoted one."""
    k = str(k)
    bare = k.isascii() and k.replace("_", "").replace("-", "").isalnum()
    return k if bare else _toml_value(k)


def dumps_toml(doc: Mapping[str, Any], _prefix: str = "") -> str:
    """Serialise nested dicts of scalars and lists to TOML (enough for session.toml)."""
    lines, tables = [], []
    for k, v in doc.items():
        if isinstance(v, Mapping):
            tables.append((k, v))
        else:
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in tables:
        name = f"{_prefix}{_toml_key(k)}"
        out += f"\n[{name}]\n" + dumps_toml(v, name + ".")
    return out


def session_text(doc: Mapping[str, Any]) -> str:
    """The text of ``session.toml`` for ``doc`` (checked to read back)."""
    text = dumps_toml(doc)
    tomllib.loads(text)                     # never write what cannot be read back
    return text


def write_session(folder: str | Path, doc: Mapping[str, Any] | str) -> Path:
    """Create the session folder (and ``raw/``) and write ``session.toml`` once, through a
    temporary name; `SessionError` if the folder already has one (it is never replaced)."""
    folder = Path(folder)
    text = doc if isinstance(doc, str) else session_text(doc)
    try:
        (folder / RAW_DIR).mkdir(parents=True, exist_ok=True)
        write_new_text(folder / SESSION_FILE, text)
    except FileExistsError:
        raise SessionError(f"{folder} already holds a session; resume it with --resume {folder} "
                           "or choose another --out") from None
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise SessionError(f"cannot write the session to {folder}: the disk at {mount_of(folder)} is full "
                               f"({exc.strerror}); free some space and run the command again, or choose "
                               "another --out") from None
        raise SessionError(f"cannot write the session to {folder} ({exc.strerror}); choose another --out") from None
    return folder / SESSION_FILE


def read_session(folder: str | Path) -> dict[str, Any]:
    """Read ``session.toml``; `SessionError` (one line) if the folder is not a session."""
    folder = Path(folder)
    path = folder / SESSION_FILE
    if not path.is_file():
        raise SessionError(f"{folder} is not a gonio session (no {SESSION_FILE}); give the folder a capture wrote")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SessionError(f"{path} is corrupt ({exc}); the session cannot be resumed") from None


def _bad(folder: Path, file: str, digest: str) -> bool:
    p = folder / file
    try:
        return not p.is_file() or sha256_file(p) != digest
    except OSError:
        return True


def damaged_files(folder: str | Path, journal: Journal) -> tuple[dict[str, str], dict[int, str]]:
    """Journalled RAW files that are missing or whose checksum does not match.

    Returns ``({calibration name: file}, {point index: first bad file})``.
    """
    folder = Path(folder)
    cal = {name: file for kind in ("dark", "flat", "open_beam") for name, (_, file, digest) in journal.frames(kind).items()
           if _bad(folder, file, digest)}
    points = {}
    for row in journal.points():
        for e in row["detail"].get("exposures", []):
            if _bad(folder, e["file"], e["sha256"]):
                points[int(row["idx"])] = e["file"]
                break
    return cal, points


def verify_files(folder: str | Path, journal: Journal) -> list[str]:
    """RAW files the journal names whose checksum does not match (missing or corrupt)."""
    folder = Path(folder)
    bad = []
    for _, file, digest in [v for kind in ("dark", "flat", "open_beam") for v in journal.frames(kind).values()]:
        if _bad(folder, file, digest):
            bad.append(file)
    for row in journal.points():
        for e in row["detail"].get("exposures", []):
            if _bad(folder, e["file"], e["sha256"]):
                bad.append(e["file"])
    return bad
