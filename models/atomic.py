"""Files that are never half-written: write to a temporary name beside the target, fsync,
rename (POSIX ``rename`` replaces atomically). On any error, KeyboardInterrupt included, the
temporary file is removed and the previous file, if any, is left as it was.

The temporary file is ``.<name>.<pid>-<random>.tmp``. A process killed outright (SIGKILL,
power cut) cannot remove it, so every write first removes the temporary files of the same
target left by processes that no longer run (and, for names without a pid, written by older
versions of gonio, those untouched for ten minutes). The file written gets the mode the
user's umask gives a new file (0644 under umask 022), not mkstemp's private 0600; a rename
replaces a symlink at the target instead of writing through it.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
import time
from pathlib import Path

__all__ = ["atomic_open", "file_mode", "remove_stale_temporaries"]

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


def remove_stale_temporaries(path) -> list[Path]:
    """Remove the temporary files of ``path`` that no running writer owns; return them."""
    path = Path(path)
    prefix, removed = f".{path.name}.", []
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return removed
    for entry in entries:
        name = entry.name
        if not (name.startswith(prefix) and name.endswith(".tmp")) or len(name) <= len(prefix) + 4:
            continue
        try:
            if entry.is_dir(follow_symlinks=False):
                continue
            tag = name[len(prefix):-4]
            if "." in tag:  # the temporary of a longer name (fit.json.bak), not of this one
                continue
            head, sep, _ = tag.partition("-")
            if sep and head.isdigit():
                if int(head) == os.getpid() or _pid_alive(int(head)):
                    continue
            elif time.time() - entry.stat(follow_symlinks=False).st_mtime < _UNTAGGED_AGE_S:
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


@contextlib.contextmanager
def atomic_open(path, mode: str = "w", **kwargs):
    """``with atomic_open(path, "wb") as fh: ...`` writes ``path`` all or nothing."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}-", suffix=".tmp", dir=path.parent)
        try:
            os.fchmod(fd, file_mode())
        except BaseException:
            os.close(fd)
            raise
        with os.fdopen(fd, mode, **kwargs) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        tmp = None
        _fsync_dir(path.parent)
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
