"""A session is one consistent record: checks that every resume and export runs first.

``session.toml`` is written once; its SHA-256, text and parsed content are recorded in the
journal when the session starts (`Journal.record_session`). Before a resume touches anything
(and before an export reads anything): ``session.toml`` must parse, hold every table a session
needs and be what the journal recorded (otherwise ONE line says what differs and how to put
the original back, ``--restore-session``); the journal must exist, be readable (``PRAGMA
quick_check``) and hold the session record; every file in ``raw/`` must be one the journal
reserved; every journalled point must belong to the plan (index, angles and stage pose).

Otherwise the session is refused with the recovery command, ``gonio capture --resume DIR
--rebuild-journal`` (`rebuild_journal`), which salvages what it can (keeping the old journal
and every RAW file), so that the resume measures only what could not be recovered.
"""

# The journal is the only record of what is done. The one line names what differs (a changed
# pose, seed, plan length, order...). A RAW file's name is committed before the camera writes
# the file, so an unknown file in raw/ means the journal lost commits (e.g. its -wal).
# rebuild_journal keeps the old journal beside the new one, salvages what it can still read,
# keeps the calibration frames and points whose RAW files match their recorded checksums, and
# registers every RAW file (none is ever overwritten).

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
import tomllib
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from gonio.core.files import atomic_write_text, sha256_file
from gonio.bench.session.journal import JOURNAL_FILE, RAW_DIR, SESSION_FILE, Journal, damaged_files
from gonio.bench.session.salvage import salvage
from gonio.core.preflight import mount_of
from gonio.bench.settings import validate_settings
from gonio.core.errors import GonioError, SessionError
from gonio.bench.plan.plans import plan_from_dict

__all__ = ["load_session", "check_doc", "describe_difference", "open_journal", "raw_files", "rebuild_journal",
           "restore_session", "parse_points", "NothingMeasured", "repair", "drop_placeholders", "row_matches"]

class NothingMeasured(SessionError):
    """The session has no journal yet and raw/ is empty: nothing was measured."""


TABLES = ("session", "ports", "plan", "order", "settings")


def _rebuild_hint(folder: Path) -> str:
    return f"recover with `gonio capture --resume {folder} --rebuild-journal`"


def load_session(folder: Path) -> tuple[bytes, dict[str, Any] | None, str]:
    """``(bytes, parsed doc or None, why it does not parse)`` of ``session.toml``."""
    path = folder / SESSION_FILE
    if not path.is_file():
        raise SessionError(f"{folder} is not a gonio session (no {SESSION_FILE}); give the folder a capture wrote")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SessionError(f"cannot read {path} ({exc.strerror}); check its permissions") from None
    try:
        return data, tomllib.loads(data.decode("utf-8")), ""
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        return data, None, " ".join(str(exc).split())


def check_doc(doc: Mapping[str, Any], folder: Path):
    """Check that ``doc`` is a whole session; return its `Plan`. One-line `SessionError` otherwise."""
    try:
        return _check_doc(doc, folder)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        raise SessionError(f"{folder / SESSION_FILE} is malformed ({type(exc).__name__}: {exc}); put back the "
                           "original session.toml") from None


def _check_doc(doc: Mapping[str, Any], folder: Path):
    where = f"{folder / SESSION_FILE}"
    for t in TABLES:
        if not isinstance(doc.get(t), Mapping):
            raise SessionError(f"{where} has no [{t}] table; the session cannot be resumed as it is "
                               "(put back the original session.toml)")
    try:
        plan = plan_from_dict(doc["plan"], source=str(doc["plan"].get("source", "")))
    except GonioError as exc:
        raise SessionError(f"{where}: {exc}") from None
    n = len(doc["plan"].get("points", []))
    if len(plan) != n:
        raise SessionError(f"{where}: its plan lists {n - len(plan)} point(s) twice; a session's plan has "
                           "each point once (put back the original session.toml)")
    order = doc["order"].get("order")
    try:
        order = np.asarray(order, dtype=np.int64)
        stage = np.asarray(doc["order"].get("stage_deg"), dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise SessionError(f"{where}: [order] is not a list of point indices and stage poses") from None
    if order.shape != (n,) or stage.shape != (n, 4) or not np.all(np.isfinite(stage)):
        raise SessionError(f"{where}: [order] has {order.size} indices and {stage.size // 4} stage poses for a "
                           f"plan of {n} points; put back the original session.toml")
    counts = np.bincount(order[(order >= 0) & (order < n)], minlength=n) if n else np.zeros(0, int)
    if np.any((order < 0) | (order >= n)) or np.any(counts != 1):
        dup = [int(i) for i in np.flatnonzero(counts > 1)[:1]] or [int(i) for i in order if not 0 <= i < n][:1]
        raise SessionError(f"{where}: [order] is not each point of the plan once (point {dup[0] if dup else '?'}); "
                           "put back the original session.toml")
    seed = doc["session"].get("seed", -1)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise SessionError(f"{where}: [session] seed {seed!r} is not an integer")
    try:
        validate_settings(doc["settings"])
    except GonioError as exc:
        raise SessionError(f"{where}: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise SessionError(f"{where}: [settings] is incomplete or malformed ({type(exc).__name__}: {exc})") from None
    return plan


# -- what differs -----------------------------------------------------------------------------

def _fmt(v) -> str:
    s = json.dumps(v, default=str)
    return s if len(s) <= 60 else s[:57] + "..."


def _first_diff(a, b, path: str) -> str | None:
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        for k in sorted(set(a) | set(b), key=str):
            p = f"{path}.{k}" if path else str(k)
            if k not in b:
                return f"{p} is missing"
            if k not in a:
                return f"{p} = {_fmt(b[k])} was added"
            d = _first_diff(a[k], b[k], p)
            if d:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{path} has {len(b)} entries instead of {len(a)}"
        for k, (x, y) in enumerate(zip(a, b)):
            d = _first_diff(x, y, f"{path}[{k}]")
            if d:
                return d
        return None
    if a != b or type(a) is not type(b) and not (isinstance(a, (int, float)) and isinstance(b, (int, float))):
        return f"{path} is {_fmt(b)} instead of {_fmt(a)}"
    return None


def describe_difference(rec: Mapping[str, Any], cur: Mapping[str, Any]) -> str:
    """What differs between the recorded session (``rec``) and ``cur``, in a few words."""
    try:
        return _describe(rec, cur)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, StopIteration):
        return _first_diff(dict(rec), dict(cur), "") or "its text differs"


def _describe(rec: Mapping[str, Any], cur: Mapping[str, Any]) -> str:
    for t in TABLES:
        if t in cur and not isinstance(cur[t], Mapping):
            return f"its [{t}] is no longer a table"
    for t in sorted(set(rec) | set(cur)):
        if t not in cur:
            return f"its [{t}] table is missing"
        if t not in rec:
            return f"it has a [{t}] table the session did not have"
    rp, cp = rec["plan"].get("points", []), cur["plan"].get("points", [])
    if isinstance(cp, list) and len(cp) != len(rp):
        return f"its plan has {len(cp)} points instead of {len(rp)} ({'shorter' if len(cp) < len(rp) else 'longer'})"
    if isinstance(cp, list):
        for k, (x, y) in enumerate(zip(rp, cp)):
            if x != y:
                return f"plan point {k} is {_fmt(y)} instead of {_fmt(x)}"
    ro, co = rec["order"].get("order", []), cur["order"].get("order", [])
    if isinstance(co, list) and co != ro:
        seen = set()
        for i in co:
            if i in seen:
                return f"its order lists point {i} twice"
            seen.add(i)
        if len(co) != len(ro):
            return f"its order has {len(co)} entries instead of {len(ro)}"
        k = next(k for k, (x, y) in enumerate(zip(ro, co)) if x != y)
        return f"its order visits point {co[k]} at step {k} instead of point {ro[k]}"
    rs, cs = rec["order"].get("stage_deg", []), cur["order"].get("stage_deg", [])
    if isinstance(cs, list) and cs != rs and len(cs) == len(rs):
        k = next(k for k, (x, y) in enumerate(zip(rs, cs)) if x != y)
        return f"the stage pose of point {k} is {_fmt(cs[k])} instead of {_fmt(rs[k])}"
    if rec["session"].get("seed") != cur["session"].get("seed"):
        return f"its seed is {_fmt(cur['session'].get('seed'))} instead of {_fmt(rec['session'].get('seed'))}"
    for t in ("settings", "ports", "meta", "sample_truth", "session", "plan", "order"):
        if t in rec:
            d = _first_diff(rec[t], cur[t], t)
            if d:
                return d
    d = _first_diff(dict(rec), dict(cur), "")
    return d or "its text differs (formatting or comments only)"


def _changed(folder: Path, what: str) -> SessionError:
    return SessionError(f"{folder / SESSION_FILE} was changed after the session started: {what}; put the "
                        f"original back with `gonio capture --resume {folder} --restore-session` "
                        "(the journal keeps it), or start a new session")


def _canonical(doc) -> Any:
    return json.loads(json.dumps(doc, sort_keys=True, default=str))


# -- the journal --------------------------------------------------------------------------------

def raw_files(folder: Path) -> list[str]:
    """Files in ``raw/`` as ``raw/NAME`` (temporary and hidden files left out)."""
    d = folder / RAW_DIR
    if not d.is_dir():
        return []
    return sorted(f"{RAW_DIR}/{p.name}" for p in d.iterdir()
                  if p.is_file() and not p.name.startswith(".") and not p.name.endswith(".part"))


def _no_room(path: Path, exc: BaseException) -> None:
    """An I/O error opening a journal on a full disk is not damage (SQLite needs room beside it, its
    -shm and -wal files, even to read it): say so, rather than send the user to --rebuild-journal."""
    code = getattr(exc, "sqlite_errorcode", 0) & 0xFF
    if not (isinstance(exc, OSError) or code in (sqlite3.SQLITE_IOERR, sqlite3.SQLITE_FULL, sqlite3.SQLITE_CANTOPEN)):
        return
    try:
        free = shutil.disk_usage(path.parent).free
    except OSError:
        return
    if free < (1 << 20):
        raise SessionError(f"{path} cannot be read: the disk at {mount_of(path)} is full ({free // 1024} KiB free; "
                           f"{exc}); free some space and run the command again") from None


def _inspect(path: Path) -> tuple[str, str]:
    """``("missing" | "empty" | "damaged" | "unrecorded" | "ok", detail)`` of a journal file."""
    if not path.exists():
        return "missing", "is missing"
    try:
        wal = Path(str(path) + "-wal")
        if path.stat().st_size == 0 and not (wal.exists() and wal.stat().st_size > 0):
            return "empty", "is empty"
        db = sqlite3.connect(str(path), timeout=30.0)
    except (OSError, sqlite3.Error) as exc:
        _no_room(path, exc)
        return "damaged", f"cannot be opened ({exc})"
    try:
        check = db.execute("PRAGMA quick_check").fetchone()
        if not check or check[0] != "ok":
            return "damaged", f"is damaged ({check[0] if check else 'no answer'})"
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if "session" not in tables or "files" not in tables:
            return "unrecorded", "has no session record"
        if db.execute("SELECT count(*) FROM session WHERE key = 'sha256'").fetchone()[0] != 1:
            return "unrecorded", "has no session record"
        return "ok", ""
    except sqlite3.DatabaseError as exc:
        _no_room(path, exc)
        return "damaged", f"is damaged ({exc})"
    finally:
        db.close()


def _has_rows(path: Path) -> bool:
    try:
        db = sqlite3.connect(str(path))
        try:
            return any(db.execute(f"SELECT 1 FROM {t} LIMIT 1").fetchone() for t in ("points", "calibration"))
        finally:
            db.close()
    except sqlite3.Error:
        return False


def open_journal(folder: Path, data: bytes, doc: Mapping[str, Any] | None, why: str, *, plan=None,
                 write: bool = True) -> Journal:
    """Open the journal of a session after every check of the module docstring.

    ``write``: a resume (under the lock) may record the session in a journal that never got its
    record (a capture killed between writing session.toml and its journal, nothing measured).
    Raises a one-line `SessionError` otherwise.
    """
    path = folder / JOURNAL_FILE
    state, detail = _inspect(path)
    files = raw_files(folder)
    if state in ("missing", "empty", "unrecorded"):
        if files or (state == "unrecorded" and _has_rows(path)):
            raise SessionError(f"{path} {detail} but raw/ holds {len(files)} RAW file(s): the journal is the only "
                               f"record of what was measured; {_rebuild_hint(folder)}")
        if doc is None:
            raise SessionError(f"{folder / SESSION_FILE} is not valid TOML ({why}); the session cannot be resumed")
        if plan is None:
            check_doc(doc, folder)
        if not write:
            raise NothingMeasured(f"{folder} has no measured point yet; resume the capture first")
        if state == "empty":
            path.unlink()                     # an empty file: start the journal afresh
        j = Journal(path)
        j.record_session(data.decode("utf-8"), doc)
        j.event("record", "session.toml recorded by a resume (its capture stopped before the journal)")
        return j
    if state == "damaged":
        raise SessionError(f"{path} {detail}; {_rebuild_hint(folder)}")
    j = Journal(path)
    try:
        rec = j.session_record()
        if rec["sha256"] != hashlib.sha256(data).hexdigest():
            if hashlib.sha256(rec.get("text", "").encode("utf-8", "surrogatepass")).hexdigest() != rec["sha256"]:
                raise SessionError(f"{path}: its record of session.toml is damaged; {_rebuild_hint(folder)}")
            if doc is None:
                raise _changed(folder, f"it is no longer valid TOML ({why})")
            raise _changed(folder, describe_difference(json.loads(rec["doc"]), _canonical(doc)))
        if doc is None:
            raise SessionError(f"{folder / SESSION_FILE} is not valid TOML ({why})")
        plan = plan if plan is not None else check_doc(doc, folder)
        unknown = sorted(set(files) - j.reserved())
        if unknown:
            raise SessionError(f"raw/ holds {len(unknown)} RAW file(s) the journal does not name (first: "
                               f"{unknown[0]}): the journal lost commits (its -wal file?); {_rebuild_hint(folder)}")
        stage = np.asarray(doc["order"]["stage_deg"], float)
        for r in j.points():
            k = int(r["idx"])
            if not (0 <= k < len(plan)) or not row_matches(r, plan.angles[k], stage[k]):
                raise SessionError(f"{path}: journalled point {k} is not point {k} of the plan; the journal is "
                                   f"damaged; {_rebuild_hint(folder)}")
    except sqlite3.DatabaseError as exc:
        j.close()
        _no_room(path, exc)
        raise SessionError(f"{path} is damaged ({exc}); {_rebuild_hint(folder)}") from None
    except BaseException:
        j.close()
        raise
    return j


def row_matches(row: Mapping[str, Any], angles, stage) -> bool:
    """Whether a journalled point row has the plan point's angles and stage pose."""
    got = [row.get(k) for k in ("theta_i", "phi_i", "theta_o", "phi_o")]
    pose = [row.get(k) for k in ("yaw", "tilt", "azimuth", "lamp")]
    try:
        return (np.allclose(np.asarray(got, float), angles, atol=1e-6)
                and np.allclose(np.asarray(pose, float), stage, atol=1e-3))
    except (TypeError, ValueError):
        return False


# -- recovery ------------------------------------------------------------------------------------

def _verified(folder: Path, file, digest) -> bool:
    try:
        p = folder / str(file)
        return p.is_file() and sha256_file(p) == digest
    except OSError:
        return False


def rebuild_journal(folder: Path, data: bytes, doc: Mapping[str, Any] | None, why: str) -> str:
    """Replace a missing or damaged journal (see the module docstring); return the line to print.

    Caller holds the session lock.
    """
    if doc is None:
        raise SessionError(f"{folder / SESSION_FILE} is not valid TOML ({why}); the journal cannot be rebuilt "
                           "without it")
    path = folder / JOURNAL_FILE
    state, _ = _inspect(path)
    plan = check_doc(doc, folder)
    if state == "ok":
        try:
            with open_journal(folder, data, doc, why, plan=plan) as j:
                try:
                    events_damaged = bool(j.checked_events()[1])   # export and resume read them too
                except sqlite3.DatabaseError:
                    events_damaged = True
        except SessionError as exc:
            if "--rebuild-journal" not in str(exc):
                raise
        else:
            if not events_damaged:
                raise SessionError(f"{path} is whole and consistent; nothing to rebuild: resume without "
                                   "--rebuild-journal")
    n = len(plan)
    old = salvage(path, n)
    _same_session(folder, old["session"], data, doc)
    stage = np.asarray(doc["order"]["stage_deg"], float)
    cal = [r for r in old["calibration"] if _verified(folder, r.get("file"), r.get("sha256"))]
    points, damaged = [], dict(old["damaged"])
    for r, d in zip(old["points"], old["decoded"]):
        k = d["idx"]
        try:
            ok = row_matches(d, plan.angles[k], stage[k])
            if not ok:
                damaged[k] = "its journal row is not the plan's point"
            elif not d["detail"].get("exposures") or not all(
                    _verified(folder, e["file"], e["sha256"]) for e in d["detail"]["exposures"]):
                ok = False                  # measured again by the resume, as a corrupt RAW file always is
        except (KeyError, TypeError, ValueError, AttributeError):
            ok, damaged[k] = False, "its journal row is malformed"
        if ok:
            points.append(r)
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    kept = ""
    for suffix in ("", "-wal", "-shm"):
        p = Path(str(path) + suffix)
        if p.exists():
            aside = p.with_name(f"{JOURNAL_FILE}.damaged-{stamp}{suffix}")
            p.rename(aside)
            kept = kept or aside.name
    j = Journal(path)
    try:
        j.record_session(data.decode("utf-8"), doc)
        j.reserve_all(raw_files(folder))        # every RAW file stays: none is ever overwritten
        j.insert_rows("calibration", cal)
        j.insert_rows("points", points)
        j.insert_rows("events", [{k: e[k] for k in ("time", "kind", "text")} for e in old["events"]])
        line = (f"rebuilt the journal: {len(points)} point(s) recovered (rows and RAW files match their recorded "
                f"checksums), {n - len(points)} to measure")
        if damaged:
            idx = sorted(damaged)
            line += (f" ({len(idx)} damaged: {', '.join(map(str, idx[:10]))}" + (" ..." if len(idx) > 10 else "")
                     + "; measured again)")
        line += f"; the old journal is kept as {kept}" if kept else "; there was no old journal"
        j.event("rebuild", line)
    finally:
        j.close()
    return line


def _same_session(folder: Path, rec: Mapping[str, str], data: bytes, doc: Mapping[str, Any]) -> None:
    """Refuse to rebuild a journal for a session.toml other than the one it recorded. A record
    whose text does not match its own checksum is damaged: then its parsed content decides."""
    if not rec.get("sha256") or rec["sha256"] == hashlib.sha256(data).hexdigest():
        return
    text = rec.get("text")
    intact = text is not None and hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest() == rec["sha256"]
    try:
        recorded = json.loads(rec["doc"])
    except (KeyError, ValueError, TypeError):
        recorded = None
    if not intact and (recorded is None or recorded == _canonical(doc)):
        return
    raise _changed(folder, "its checksum differs from the journal's" if recorded is None
                   else describe_difference(recorded, _canonical(doc)))


def restore_session(folder: Path) -> str:
    """Put back ``session.toml`` as the journal recorded it; return the line to print."""
    path = folder / JOURNAL_FILE
    state, detail = _inspect(path)
    if state != "ok":
        raise SessionError(f"{path} {detail}: it holds no copy of session.toml to restore")
    with Journal(path) as j:
        rec = j.session_record()
    text = rec["text"]
    if hashlib.sha256(text.encode("utf-8")).hexdigest() != rec["sha256"]:
        raise SessionError(f"{path}: its copy of session.toml does not match its checksum; the journal is damaged")
    cur = folder / SESSION_FILE
    if cur.is_file() and cur.read_bytes() == text.encode("utf-8"):
        return f"{cur} is already the original; nothing to restore"
    kept = ""
    if cur.is_file():
        aside = cur.with_name(f"{SESSION_FILE}.changed-{datetime.now(timezone.utc).strftime('%Y%m%dT%H%M%SZ')}")
        cur.rename(aside)
        kept = f" (the changed one is kept as {aside.name})"
    atomic_write_text(cur, text)
    return f"restored {cur} from the journal{kept}; resume with `gonio capture --resume {folder}`"


def parse_points(spec: str, n: int) -> list[int]:
    """``"3,7,10-12"`` -> [3, 7, 10, 11, 12]; every index in [0, n)."""
    out: set[int] = set()
    for part in str(spec).split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part[1:]:
                a, b = part.split("-", 1)
                lo, hi = int(a), int(b)
            else:
                lo = hi = int(part)
        except ValueError:
            raise SessionError(f"--remeasure {spec!r}: give plan point indices such as 3,7,10-12") from None
        if lo > hi or lo < 0 or hi >= n:
            raise SessionError(f"--remeasure {spec!r}: point {lo if lo < 0 or lo >= n else hi} is outside the plan "
                               f"(0-{n - 1})")
        if hi - lo > 10_000_000:
            raise SessionError(f"--remeasure {spec!r}: range too large")
        out.update(range(lo, hi + 1))
    if not out:
        raise SessionError(f"--remeasure {spec!r}: give plan point indices such as 3,7,10-12")
    return sorted(out)


def repair(folder: Path, journal: Journal, want: list[int] | None, note) -> None:
    """Before a resume measures: take again the calibration frames whose RAW files are missing
    or corrupt, measure again the points whose RAW files are (and the points ``want``, from
    `parse_points`); each said in one line to ``note``. The old rows are kept in ``superseded``."""
    cal, bad = damaged_files(folder, journal)
    if any(name.startswith("open_beam") for name in cal):     # the transmitted points' normalisation is lost:
        for row in journal.points():                           # they are measured again over a new open beam
            if float(row["theta_o"]) > 90.0:
                bad.setdefault(int(row["idx"]), cal[min(n for n in cal if n.startswith("open_beam"))])
    if cal:
        names = sorted(cal)
        for name in names:
            journal.forget_frame(name)
        journal.event("retake", f"calibration frames missing or corrupt: {', '.join(names)}")
        note(f"{len(names)} calibration frame(s) are missing or corrupt (first: {cal[names[0]]}): taking them again")
    if bad:
        idx = sorted(bad)
        journal.supersede(idx, "RAW file missing or corrupt")
        shown = ", ".join(map(str, idx[:10])) + (f" and {len(idx) - 10} more" if len(idx) > 10 else "")
        note(f"measuring again {len(idx)} point(s) whose RAW files are missing or corrupt: {shown} "
             f"(first file: {bad[idx[0]]})")
    if want:
        moved = journal.supersede(want, "--remeasure")
        note(f"measuring again {len(want)} point(s) as asked ({len(moved)} had been measured)")
    drop_placeholders(folder, journal)


def drop_placeholders(folder: Path, journal: Journal) -> None:
    """Remove the empty placeholders of RAW files a stopped run reserved but never received."""
    used = {f for kind in ("dark", "flat", "open_beam") for _, f, _ in journal.frames(kind).values()}
    used |= {e["file"] for r in journal.points() for e in r["detail"].get("exposures", [])}
    for file in raw_files(folder):
        p = folder / file
        if file not in used and p.stat().st_size == 0:
            p.unlink()
