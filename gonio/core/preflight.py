"""Checks before work starts, and environment errors as one line.

Every command that writes checks its output first (``check_output_file``,
``check_output_dir``): the path is encodable and free of control characters (a newline in
``--out`` would otherwise reach a device's line protocol as a second command:
`control_character`), not a folder where a file is wanted (or the
reverse), its nearest existing folder is writable (probed by creating and removing a hidden
temporary entry: permission bits alone say nothing for root or a read-only mount), and,
where a size estimate exists, the disk holding it has room (``check_free_space``).

``environment_errors()`` turns what the environment throws during the work (``OSError``:
disk full, permission, read-only file system; ``UnicodeDecodeError``: binary bytes where text
was expected; ``MemoryError``) into a :class:`GonioError` of one line that names the file or
the disk and says what to do.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import sqlite3
import stat
import tempfile
from pathlib import Path

from gonio.core.errors import GonioError

__all__ = ["check_output_file", "check_output_dir", "check_free_space", "check_input_file",
           "environment_errors", "writing", "mount_of", "disk_full", "oserror_line", "MiB",
           "control_character"]

MiB = 1 << 20
#: kept free beyond an estimate: a file system at 100 % fails in ways no estimate sees
MARGIN = 16 * MiB


#: C0 controls (newline, CR, NUL, ESC, ...), DEL, C1 controls (NEL ``\x85``, CSI ``\x9b``, ...) and
#: the Unicode line and paragraph separators: what ends or rewrites a line of a device's text
#: protocol, a terminal or a log. Shared by the drivers (what they send) and the simulated
#: devices (what they accept).
_CONTROL = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def control_character(text: str) -> str | None:
    """The first control character of ``text`` (C0, DEL, C1, U+2028, U+2029), None if none."""
    m = _CONTROL.search(text)
    return m.group() if m else None


def _encodable(path: Path, what: str) -> None:
    text = str(path)
    if "\x00" in text:
        raise GonioError(f"{what} {text!r} holds a NUL byte; give a plain path")
    bad = control_character(text)
    if bad is not None:
        raise GonioError(f"{what} {text!r} holds the control character {bad!r}; "
                         "give a path without control characters (newline, CR, ESC, ...)")
    try:
        os.fsencode(text)
    except UnicodeError:
        raise GonioError(f"{what} {text!r} cannot be encoded for this file system; "
                         "rename it or set a UTF-8 locale (LANG=C.UTF-8)") from None
    for part in path.parts:
        if len(os.fsencode(part)) > 255:
            raise GonioError(f"{what}: the path component {part[:40]!r}... is longer than 255 bytes; shorten it")
    if len(os.fsencode(text)) > 4000:
        raise GonioError(f"{what} is a path of more than 4000 bytes; use a shorter one")


def _existing_ancestor(path: Path) -> Path:
    p = Path(os.path.abspath(path))
    while not os.path.lexists(p):
        if p.parent == p:
            break
        p = p.parent
    return p


def mount_of(path) -> str:
    """The mount point of the file system holding ``path`` (its nearest existing folder)."""
    p = _existing_ancestor(Path(path))
    while not os.path.ismount(p) and p.parent != p:
        p = p.parent
    return str(p)


def _probe_writable(folder: Path, what: str, target: Path) -> None:
    try:
        fd, probe = tempfile.mkstemp(prefix=".gonio-probe-", dir=folder)
    except OSError as exc:
        reason = {errno.EROFS: "is on a read-only file system", errno.ENOSPC: "is on a full disk",
                  errno.EDQUOT: "is over its disk quota"}.get(exc.errno, "is not writable")
        raise GonioError(f"{what} {target}: {folder} {reason} ({exc.strerror}); "
                         "give a folder you can write to") from None
    os.close(fd)
    os.unlink(probe)


def _check_parent_chain(folder: Path, what: str, target: Path) -> Path:
    """The nearest existing ancestor of ``folder`` must be a writable folder; return it."""
    anc = _existing_ancestor(folder)
    if not anc.is_dir():
        raise GonioError(f"{what} {target}: {anc} is a file, not a folder; give another path")
    _probe_writable(anc, what, target)
    return anc


def disk_full(exc: BaseException) -> bool:
    """``exc`` says the disk is full: ENOSPC or EDQUOT, or SQLite's SQLITE_FULL."""
    if isinstance(exc, OSError):
        return exc.errno in (errno.ENOSPC, errno.EDQUOT)

    if isinstance(exc, sqlite3.DatabaseError):
        code = getattr(exc, "sqlite_errorcode", None)
        return (code is not None and code & 0xFF == sqlite3.SQLITE_FULL) or "disk is full" in str(exc)
    return False


def check_free_space(path, need_bytes: int, what: str, hint: str = "free some space or write elsewhere") -> None:
    """Refuse when the disk holding ``path`` has less than ``need_bytes`` (plus a margin) free."""
    anc = _existing_ancestor(Path(path))
    try:
        free = shutil.disk_usage(anc if anc.is_dir() else anc.parent).free
    except OSError:
        return
    if free < int(need_bytes) + MARGIN:
        raise GonioError(f"not enough space for {what}: the disk at {mount_of(anc)} has {free / MiB:.0f} MiB free, "
                         f"about {(int(need_bytes) + MARGIN) / MiB:.0f} MiB are needed; {hint}")


def check_output_file(path, what: str = "output file", *, need_bytes: int = 0) -> Path:
    """``path`` can be written as a file; returns it as a Path."""
    path = Path(path)
    _encodable(path, what)
    if str(path) in ("", ".") or path.name in ("", ".", ".."):
        raise GonioError(f"{what} {str(path)!r} is not a file name; give a path such as out/fit.json")
    if path.is_dir():
        raise GonioError(f"{what} {path} is a folder; give a file path inside it (e.g. {path / 'out'})")
    if os.path.lexists(path) and not path.is_file():
        raise GonioError(f"{what} {path} exists and is not a regular file; give another path")
    _check_parent_chain(path.parent if str(path.parent) else Path("."), what, path)
    if need_bytes:
        check_free_space(path.parent, need_bytes, what)
    return path


def check_output_dir(path, what: str = "output folder", *, need_bytes: int = 0) -> Path:
    """``path`` is (or can be made) a writable folder; returns it as a Path. Nothing is created."""
    path = Path(path)
    _encodable(path, what)
    if str(path) == "":
        raise GonioError(f"{what} is empty; give a folder")
    if os.path.lexists(path) and not path.is_dir():
        raise GonioError(f"{what} {path} exists and is not a folder; give a folder path")
    if path.is_dir():
        _probe_writable(path, what, path)
    else:
        _check_parent_chain(path, what, path)
    if need_bytes:
        check_free_space(path, need_bytes, what)
    return path


def check_input_file(path, what: str = "input file", max_bytes: int | None = None) -> Path:
    """``path`` names an existing regular file (not a FIFO, device or socket, which could block
    or never end), of at most ``max_bytes`` where given, that can be opened; returns it as a Path."""
    path = Path(path)
    _encodable(path, what)
    if not path.exists():
        raise GonioError(f"{what} {path} does not exist; check the path")
    if path.is_dir():
        raise GonioError(f"{what} {path} is a folder; give a file")
    st = path.stat()
    if not stat.S_ISREG(st.st_mode):
        raise GonioError(f"{what} {path} is not a regular file (a FIFO, device or socket); give a file")
    if max_bytes is not None and st.st_size > max_bytes:
        raise GonioError(f"{what} {path} is {st.st_size / MiB:.1f} MiB, more than such a file can be "
                         f"({max_bytes / MiB:.3g} MiB); give the right file")
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise GonioError(f"cannot open {what} {path} ({exc.strerror}); check its permissions") from None
    return path


def oserror_line(exc: OSError) -> str:
    """One line for an environment error: the file, what is wrong, what to do."""
    return _oserror_line(exc)


def _oserror_line(exc: OSError) -> str:
    name = exc.filename if exc.filename is not None else ""
    where = f"{name}: " if name != "" else ""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        disk = mount_of(name) if name != "" else "the output disk"
        return (f"{where}the disk at {disk} is full ({exc.strerror}); nothing was left half-written; "
                "free some space and run the command again")
    if exc.errno == errno.EROFS:
        return f"{where}read-only file system; write somewhere else"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return f"{where}permission denied; give a path you can write to (or read)"
    if exc.errno == errno.EISDIR:
        return f"{where}is a folder where a file is needed; give a file path"
    if exc.errno == errno.ENOTDIR:
        return f"{where}a part of the path is a file, not a folder; give another path"
    if exc.errno == errno.EEXIST:
        return f"{where}already exists and is in the way; give another path"
    if exc.errno == errno.ENOENT:
        return f"{where}no such file or folder; check the path"
    if exc.errno == errno.ENAMETOOLONG:
        return f"{where}the path is too long; use a shorter one"
    return f"{where}{exc.strerror or exc}; check the path and the disk"


@contextlib.contextmanager
def environment_errors():
    """Turn environment errors raised inside the block into one-line GonioErrors."""
    try:
        yield
    except GonioError:
        raise
    except OSError as exc:
        raise GonioError(_oserror_line(exc)) from None
    except UnicodeDecodeError as exc:
        raise GonioError(f"an input file holds bytes that are not UTF-8 text ({exc.reason} at byte {exc.start}); "
                         "give the text file (TOML, CSV, JSON) the option expects") from None
    except MemoryError:
        raise GonioError("out of memory: the input is too large for this machine; give a smaller one") from None
    except Exception as exc:
        if not disk_full(exc):              # SQLite's "database or disk is full"
            raise
        name = getattr(exc, "filename", None)
        raise GonioError(_oserror_line(OSError(errno.ENOSPC, "database or disk is full", name))) from None


@contextlib.contextmanager
def writing(path):
    """Around the write of ``path``: an OSError without a file name (fsync, rename) is named
    after ``path`` and its disk, as one line."""
    try:
        yield
    except OSError as exc:
        if exc.filename is None:
            exc = OSError(exc.errno, exc.strerror or str(exc), str(path))
        raise GonioError(_oserror_line(exc)) from None
