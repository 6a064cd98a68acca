"""The session's file helpers: checksums, exclusive reservations, write-once files, and the
commit of a file another program wrote under a reserved name (``.tmp-<name>``: the camera's
copy, the export's netCDF writer). Writing gonio's own files goes through the house's one
atomic writer, :mod:`gonio.core.atomic`, which also holds the one rule that recognises a
temporary (:func:`~gonio.core.atomic.is_temporary`)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from gonio.core import atomic

__all__ = ["TMP_PREFIX", "sha256_file", "atomic_write_bytes", "atomic_write_text", "fsync_dir",
           "commit_file", "make_durable", "create_exclusive", "write_new_text", "remove_orphans", "is_tiff",
           "text_head"]

TMP_PREFIX = atomic.RESERVED_PREFIX     # reserved names start with this; a resume removes any left behind


def sha256_file(path: str | os.PathLike) -> str:
    """SHA-256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def fsync_dir(folder: str | os.PathLike) -> None:
    """fsync a folder, so that a rename inside it survives a power cut."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def tmp_name(path: str | os.PathLike) -> Path:
    """The temporary name beside ``path`` (same folder, hidden, ``.tmp-`` prefix)."""
    p = Path(path)
    return p.with_name(TMP_PREFIX + p.name)


def commit_file(tmp: str | os.PathLike, path: str | os.PathLike, *, durable: bool = True) -> None:
    """fsync ``tmp``, rename it to ``path`` and fsync the folder (gonio.core.atomic.commit);
    ``durable=False``: the rename alone, for a batch that :func:`make_durable` syncs at once."""
    atomic.commit(tmp, path, durable=durable)


def make_durable(paths) -> None:
    """Every file of a batch committed with ``durable=False`` made to survive a power cut at
    once (gonio.core.atomic.make_durable): before anything records the batch as finished."""
    atomic.make_durable(paths)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> str:
    """Write ``data`` to ``path`` atomically (:func:`gonio.core.atomic.atomic_open`); return
    its SHA-256 (hex)."""
    with atomic.atomic_open(path, "wb") as fh:
        fh.write(data)
    return hashlib.sha256(data).hexdigest()


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through a temporary name."""
    atomic_write_bytes(path, text.encode("utf-8"))


def create_exclusive(path: str | os.PathLike) -> bool:
    """Create ``path`` empty with ``O_CREAT | O_EXCL``: False if anything already has that name.

    A capture reserves each RAW file's name this way before the camera writes it (the camera's
    rename then replaces the empty placeholder), so no existing RAW file is ever overwritten.
    """
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)   # the umask decides the mode
    except FileExistsError:
        return False
    os.close(fd)
    return True


def write_new_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically, refusing to replace an existing file
    (:func:`gonio.core.atomic.atomic_open` with ``replace=False``: `FileExistsError`, and
    nothing is changed, if ``path`` exists)."""
    with atomic.atomic_open(path, "wb", replace=False) as fh:
        fh.write(text.encode("utf-8"))


def remove_orphans(folder: str | os.PathLike) -> list[Path]:
    """Delete the temporary files left in ``folder`` by a crash (the one rule:
    :func:`gonio.core.atomic.is_temporary`; ``.tmp-*`` and ``*.part`` whoever wrote them, the
    atomic writer's own when their writer no longer runs). Call it holding the session lock."""
    return atomic.remove_orphans(folder)


def is_tiff(path: Path) -> bool:
    """Whether ``path`` starts as a TIFF (a DNG is one): b"II*\\0" or b"MM\\0*"."""
    try:
        with open(path, "rb") as fh:
            return fh.read(4) in (b"II*\x00", b"MM\x00*")
    except OSError:
        return False


def text_head(path, size: int = 1 << 14) -> bytes | None:
    """The first ``size`` bytes of a file that may be a text format (for detection by content);
    None when it cannot be read or holds a NUL byte (binary)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(size)
    except OSError:
        return None
    return None if b"\x00" in head else head
