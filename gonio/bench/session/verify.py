"""``gonio verify SESSION``: which measured points are intact, which are damaged, how to recover.

A point is intact when its journal row matches its checksum and belongs to the plan, and
every RAW file it names matches its recorded SHA-256. The journal is read the way a resume
and an export read it (`gonio.bench.session.integrity.open_journal`); where they would refuse
it, what a rebuild would recover is counted instead (`gonio.bench.session.salvage`). Nothing in
the session folder is written. The recovery: ``--rebuild-journal`` for a damaged journal (it
keeps every intact point), a plain resume for RAW files alone (it measures their points again).
"""

from __future__ import annotations

import fcntl
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gonio.bench.session import integrity
from gonio.bench.session.journal import JOURNAL_FILE, LOCK_FILE
from gonio.bench.session.salvage import salvage
from gonio.core.errors import SessionError
from gonio.core.files import sha256_file

__all__ = ["Verdict", "verify_session"]


@dataclass
class Verdict:
    """What `verify_session` found. ``damaged``: ``{point index: why}``; ``unchecked``: points
    journalled before checksums (read, not checked); ``journal``: why a resume or an export would
    refuse the journal ("" if they would not)."""

    folder: Path
    planned: int
    intact: list[int] = field(default_factory=list)
    damaged: dict[int, str] = field(default_factory=dict)
    unchecked: int = 0
    journal: str = ""

    @property
    def missing(self) -> list[int]:
        """Plan points with no row at all: not measured yet (or lost without a trace)."""
        have = set(self.intact) | set(self.damaged)
        return [k for k in range(self.planned) if k not in have]

    @property
    def ok(self) -> bool:
        return not self.damaged and not self.journal

    def recovery(self) -> str:
        if "--restore-session" in self.journal:
            return f"gonio capture --resume {self.folder} --restore-session"
        if self.journal:
            return f"gonio capture --resume {self.folder} --rebuild-journal"
        return f"gonio capture --resume {self.folder}"

    def lines(self) -> list[str]:
        """The report, a few lines."""
        out = [f"{self.folder}: {self.planned} point(s) planned: {len(self.intact)} intact, {len(self.damaged)} "
               f"damaged, {len(self.missing)} not in the journal"]
        if self.unchecked:
            out.append(f"{self.unchecked} intact point(s) were journalled before checksums: read, not checked")
        if self.journal:
            out.append(f"journal: {self.journal}")
        for k, why in list(self.damaged.items())[:20]:
            out.append(f"damaged: point {k}: {why}")
        if len(self.damaged) > 20:
            out.append(f"damaged: {len(self.damaged) - 20} more point(s)")
        if not self.ok:
            keep = f"keeps the {len(self.intact)} intact point(s) and measures the rest again"
            out.append(f"recover: {self.recovery()} ({keep}); nothing damaged is exported until then")
        elif self.missing:
            out.append(f"incomplete: `{self.recovery()}` measures the {len(self.missing)} point(s) left")
        return out


def _not_in_use(folder: Path) -> None:
    """Refuse while a capture measures into the folder (its lock is held); takes nothing."""
    lock = folder / LOCK_FILE
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return                                  # no lock file: no capture ever ran here
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise SessionError(f"{folder} is in use by a capture; verify it once the capture has stopped") from None
    finally:
        os.close(fd)


def _raw_problem(folder: Path, row) -> str:
    for e in row["detail"].get("exposures", []):
        try:
            p = folder / str(e["file"])
            if not p.is_file() or sha256_file(p) != e["sha256"]:
                return f"its RAW file {e['file']} is missing or does not match its checksum"
        except (OSError, KeyError, TypeError):
            return "its RAW files cannot be checked"
    return ""


def verify_session(folder: str | Path) -> Verdict:
    """Check every measured point of the session ``folder`` (see the module docstring).

    Raises a one-line `SessionError` when ``folder`` is not a session, its ``session.toml`` is
    not readable (restore it first), or a capture is measuring into it.
    """
    folder = Path(folder)
    data, doc, why = integrity.load_session(folder)
    if doc is None:
        raise SessionError(f"{folder / 'session.toml'} is not valid TOML ({why}); put the original back with "
                           f"`gonio capture --resume {folder} --restore-session`, then verify again")
    plan = integrity.check_doc(doc, folder)
    _not_in_use(folder)
    n = len(plan)
    verdict = Verdict(folder, n)
    bad_events: list[int] = []
    try:
        with integrity.open_journal(folder, data, doc, why, plan=plan, write=False) as j:
            rows, damaged, verdict.unchecked = j.checked_points()
            bad_events = j.checked_events()[1]
    except integrity.NothingMeasured:
        return verdict
    except SessionError as exc:
        verdict.journal = str(exc)
        found = salvage(folder / JOURNAL_FILE, n)
        rows, damaged, verdict.unchecked = found["decoded"], dict(found["damaged"]), found["unchecked"]
    stage = np.asarray(doc["order"]["stage_deg"], float)
    for row in rows:
        k = row["idx"]
        if not (0 <= k < n and integrity.row_matches(row, plan.angles[k], stage[k])):
            damaged[k] = "its journal row is not the plan's point"
            continue
        problem = _raw_problem(folder, row)
        if problem:
            damaged[k] = problem
        else:
            verdict.intact.append(k)
    verdict.damaged = {k: damaged[k] for k in sorted(damaged)}
    if bad_events and not verdict.journal:
        verdict.journal = f"{len(bad_events)} event row(s) fail their checksum (what export and resume read from them)"
    if any("journal row" in w or "SQLite" in w for w in verdict.damaged.values()) and not verdict.journal:
        verdict.journal = "some point rows are damaged"
    return verdict
