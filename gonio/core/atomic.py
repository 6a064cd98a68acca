"""gonio's one atomic file writer: write to a temporary name beside the target, fsync, rename.

POSIX ``rename`` replaces atomically. On any error, KeyboardInterrupt included, the temporary
file is removed and the previous file, if any, is left as it was. It lives in the lowest layer
so that every folder (sim and models too) can use it: :func:`atomic_open` for a file object,
:func:`atomic_path` for writers that want a path (Mitsuba's and matplotlib's image writers,
which go by the extension). The file written gets the mode the user's umask gives a new file
(0644 under umask 022), not mkstemp's private 0600; a rename replaces a symlink at the target
instead of writing through it.

The temporary is ``.<name>.<pid>-<random>.tmp`` (``atomic_path(..., keep_suffix=True)`` appends
the target's extension). :func:`is_temporary` is the one rule that recognises a temporary: this
scheme, ``.tmp-<name>`` (the bench's camera copies, the export's netCDF writer) and
``<name>.part`` (older versions of the simulated camera). Temporaries left by dead processes are
removed once per process and folder (:func:`remove_stale_temporaries`, see below).
"""

# Stale temporaries: a process killed outright (SIGKILL, power cut) cannot remove its temporary,
# so a write first removes the temporary files of the same target left by processes that no
# longer run (and, for names without a pid, written by older versions of gonio, those untouched
# for ten minutes). The folder is listed for them once per process (the first write into it,
# remove_stale_temporaries): a process's own temporaries are removed by the process itself, and
# what an earlier, killed process left is there when this one starts. Listing the folder at
# every write cost time in proportion to the folder's size, so a capture's time grew with the
# square of its frame count (figures: docs/performance.md). A writer killed while this process
# runs leaves its temporaries to the next process (a capture folder has one writer: its lock;
# a resume removes them, remove_orphans).

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading
import time
from pathlib import Path

__all__ = ["atomic_open", "atomic_path", "commit", "file_mode", "is_temporary", "make_durable", "remove_orphans",
           "remove_stale_temporaries", "RESERVED_PREFIX"]

#: The temporary name of a file another program writes before gonio commits it (``.tmp-x``).
RESERVED_PREFIX = ".tmp-"

_UNTAGGED_AGE_S = 600.0
_umask_lock = threading.Lock()


def _umask() -> int:
    """The process umask, read without changing it where Linux allows."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _umask_lock:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def file_mode() -> int:
    """The permission bits a new regular file gets under the current umask."""
    return 0o666 & ~_umask()


_TEMPORARY = re.compile(r"^\..+\.(?P<tag>[^.]+)\.tmp(\.[^.]+)?$")


def is_temporary(name: str) -> bool:
    """True for the name of a temporary file of any gonio writer (see the module notes)."""
    return name.startswith(RESERVED_PREFIX) or name.endswith(".part") or bool(_TEMPORARY.match(name))


def _tag(name: str, target: str) -> str | None:
    """The writer's tag (``<pid>-<random>``, or an older untagged random part) when ``name`` is
    a temporary of ``target`` written by :func:`atomic_open` or :func:`atomic_path`."""
    prefix = f".{target}."
    if not name.startswith(prefix):
        return None
    rest = name[len(prefix):]
    suffix = Path(target).suffix
    for end in [".tmp"] + ([".tmp" + suffix] if suffix else []):
        if rest.endswith(end) and len(rest) > len(end):
            tag = rest[: -len(end)]
            return None if "." in tag else tag  # "." : the temporary of a longer name (fit.json.bak)
    return None


def _stale(tag: str, st: os.stat_result) -> bool:
    """Whether the temporary with writer tag ``tag`` and lstat ``st`` has no running writer."""
    head, sep, _ = tag.partition("-")
    if sep and head.isdigit():
        return not (int(head) == os.getpid() or _pid_alive(int(head)))
    return time.time() - st.st_mtime >= _UNTAGGED_AGE_S


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True  # someone else's process, or a pid we cannot ask about: leave its file
    return True


#: per folder (its absolute path) this process has listed: the names there that may be a
#: temporary (:data:`_TEMPORARY`) when it was listed, not yet removed or found owned
_listed: dict[str, set[str]] = {}
_listed_lock = threading.Lock()


def _candidates(folder: Path) -> set[str] | None:
    """The names in ``folder`` that may be a temporary, listed once per process and folder;
    None if the folder cannot be read. (A folder made anew at a listed path is not listed
    again: what it holds was written while this process ran, the case the module notes leave to
    the next process.)"""
    key = os.path.abspath(folder)
    with _listed_lock:
        names = _listed.get(key)
        if names is None:
            try:
                with os.scandir(folder) as it:
                    names = {e.name for e in it if _TEMPORARY.match(e.name)}
            except OSError:
                return None
            _listed[key] = names
        return names


def remove_stale_temporaries(path, *, rescan: bool = False) -> list[Path]:
    """Remove the temporary files of ``path`` that no running writer owns; return them.

    The folder is listed once per process (module notes; ``rescan`` lists it again): the
    temporaries of ``path`` found then are checked here, at the first write of ``path`` (and
    at later ones while a live writer still owns one), without listing the folder again.
    """
    path = Path(path)
    removed = []
    if rescan:
        with _listed_lock:
            _listed.pop(os.path.abspath(path.parent), None)
    names = _candidates(path.parent)
    if not names:
        return removed
    with _listed_lock:
        mine = [(n, t) for n in names if (t := _tag(n, path.name)) is not None]
    for name, tag in mine:
        entry = path.parent / name
        try:
            st = os.lstat(entry)
            if (st.st_mode & 0o170000) == 0o040000 or not _stale(tag, st):
                continue
            os.unlink(entry)
            removed.append(entry)
        except FileNotFoundError:
            pass                                  # gone: removed by its writer or someone else
        except OSError:
            continue
        with _listed_lock:
            names.discard(name)
    return removed


def remove_orphans(folder) -> list[Path]:
    """Remove the temporaries in ``folder`` (:func:`is_temporary`) that no running writer owns;
    the reserved names (``.tmp-x``, ``x.part``) are removed whoever wrote them: call it only
    while holding the folder (the capture's lock)."""
    removed = []
    folder = Path(folder)
    if not folder.is_dir():
        return removed
    for entry in sorted(os.scandir(folder), key=lambda e: e.name):
        name = entry.name
        if not is_temporary(name):
            continue
        try:
            if not entry.is_file(follow_symlinks=False):
                continue
            if not (name.startswith(RESERVED_PREFIX) or name.endswith(".part")):
                if not _stale(_TEMPORARY.match(name)["tag"], entry.stat(follow_symlinks=False)):
                    continue
            os.unlink(entry.path)
            removed.append(Path(entry.path))
        except OSError:
            continue
    return removed


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def commit(tmp, path, *, durable: bool = True) -> None:
    """fsync the finished temporary ``tmp``, rename it to ``path`` and fsync the folder, so
    that ``path`` is either the old file or the whole new one, after a power cut too.

    ``durable=False``: the rename alone (``path`` is never seen half-written, a crash of this
    process loses nothing); for a batch of files that :func:`make_durable` then syncs at once
    and that nothing records as finished before it returns."""
    if durable:
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    os.replace(tmp, path)
    if durable:
        _fsync_dir(Path(path).parent)


def _syncfs():
    """Linux's syncfs(2) from the C library, or None (another OS, or a C library without it)."""
    try:
        import ctypes
        fn = ctypes.CDLL(None, use_errno=True).syncfs
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int]
    return fn


def make_durable(paths) -> None:
    """Make every file in ``paths`` (written and renamed without fsync: ``commit(...,
    durable=False)``) and its folder's entries survive a power cut, as :func:`commit` does for
    one file, at the cost of one sync of their file system instead of two fsyncs a file.

    Linux: one ``syncfs`` per file system (st_dev) the files are on: their data and the
    folders' metadata, together, in one journal commit (512 flat frames: 0.09 s against 0.63 s
    of an fsync each, ext4 on this machine's virtual disk). Where syncfs is missing or reports
    an error (a full disk's delayed allocation, an I/O error), an fsync of each file and
    folder, which raises that error as `OSError` naming the file."""
    paths = [Path(p) for p in paths]
    if not paths:
        return
    sync = _syncfs() if sys.platform.startswith("linux") else None
    if sync is not None:
        folders = {}
        for p in paths:
            folders.setdefault(os.stat(p.parent).st_dev, p.parent)
        ok = True
        for folder in folders.values():
            fd = os.open(folder, os.O_RDONLY)
            try:
                ok = sync(fd) == 0 and ok
            finally:
                os.close(fd)
        if ok:
            return
    for p in paths:
        fd = os.open(p, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    for folder in {p.parent for p in paths}:
        _fsync_dir(folder)


def _temporary(path: Path, suffix: str = "") -> tuple[int, str]:
    """A new temporary file beside ``path`` with the umask's mode: (fd, name)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}-", suffix=".tmp" + suffix, dir=path.parent)
    try:
        os.fchmod(fd, file_mode())
    except BaseException:
        os.close(fd)
        os.unlink(tmp)
        raise
    return fd, tmp


@contextlib.contextmanager
def atomic_path(path, keep_suffix: bool = False):
    """``with atomic_path(path) as tmp: writer(tmp)`` writes ``path`` all or nothing: the
    writer writes the temporary name (ending in ``path``'s extension with ``keep_suffix``),
    which is fsynced and renamed to ``path`` when the block succeeds, removed when it fails."""
    path = Path(path)
    fd, tmp = _temporary(path, path.suffix if keep_suffix else "")
    os.close(fd)
    try:
        yield tmp
        commit(tmp, path)
        tmp = None
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def _link_new(tmp: str, path: Path) -> None:
    """Give the finished ``tmp`` the name ``path`` only if nothing has that name: a hard link,
    which (unlike a rename) fails if ``path`` exists (`FileExistsError`). On a file system
    without hard links the name is checked, then the file renamed (the caller's lock must
    exclude other writers there)."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise
    except OSError:                      # no hard links here (FAT, some network shares)
        if os.path.lexists(path):
            raise FileExistsError(str(path)) from None
        os.replace(tmp, path)
        return
    os.unlink(tmp)


@contextlib.contextmanager
def atomic_open(path, mode: str = "w", *, replace: bool = True, durable: bool = True, **kwargs):
    """``with atomic_open(path, "wb") as fh: ...`` writes ``path`` all or nothing.

    ``replace=False`` never replaces an existing file: `FileExistsError` at the end of the
    block if ``path`` exists then, and nothing is changed (a session's write-once files).

    ``durable=False`` leaves out the two fsyncs (file, folder): ``path`` is still never seen
    half-written by another process, and a crash of the writer leaves the old file or the new
    one, but after a power cut it may be missing or empty. Only for a file that its reader
    checks and commits durably itself: the simulated camera's frame, which the bench checks
    against the camera's SHA-256, fsyncs and renames (``gonio/bench/drivers/camera.Delivery``)."""
    path = Path(path)
    tmp = None
    try:
        fd, tmp = _temporary(path)
        with os.fdopen(fd, mode, **kwargs) as fh:
            yield fh
            if durable:
                fh.flush()
                os.fsync(fh.fileno())
        if replace:
            os.replace(tmp, path)
        else:
            _link_new(tmp, path)
        tmp = None
        if durable:
            _fsync_dir(path.parent)
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
