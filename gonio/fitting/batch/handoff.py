"""Measurements handed to local worker processes through files, not over the cluster's sockets.

Where ``fit_batch``'s workers are processes of this machine that this process started (a
``LocalCluster`` with processes), each dataset is written once to a file in a private
temporary folder (mode 0700; ``tempfile`` honours ``TMPDIR``): the arrays as raw bytes,
64-byte aligned, the rest as a pickle (protocol 5, its arrays out of band). A worker maps the
file copy-on-write (``mmap.ACCESS_COPY``) and unpickles the Measurements with its arrays
viewing the mapping: no copy, no socket. The files are written while the workers start on the
first ones (:meth:`Handoff.promise`, :meth:`Handoff.write_pending`); each appears whole.
The same folder holds the batch's claims (:func:`claim`: a claim file created with
``O_EXCL``, so exactly one worker takes each dataset). The folder is removed when the batch
ends; :func:`sweep_stale` removes this user's ``gonio-batch-*`` folders whose owner process
is gone. A reader checks what it maps and says what is wrong in one line.
"""

# Why files: over the cluster (client.scatter) every array is pickled, encrypted (the local
# cluster talks TLS), sent, decrypted and unpickled (figures: docs/performance.md,
# gonio.fitting.batch.handoff).
# Each file is renamed once written; a worker ahead of the writer waits for it.
# Claims: on local workers fit_batch runs a task per worker thread, and each takes the next
# dataset not yet taken by creating its claim file with O_EXCL (atomic on a local file
# system: exactly one creator wins).
# Stale folders: a process killed with SIGKILL (the kernel's out-of-memory killer, a lab's
# watchdog) cannot remove its folder; its datasets' files would stay in the temporary folder,
# in memory where that is a tmpfs, until the next reboot. So each folder names its owner (an
# owner file: process id and, on Linux, the process's start time, so that a reused id is told
# apart), and every new batch first runs sweep_stale; a folder whose owner file is not written
# yet, or cannot be read, is left alone.
# A file is read only by a worker of the cluster this process started, as this user; the
# reader still checks what it maps (its marker, its trailer's bounds).

from __future__ import annotations

import mmap
import os
import pickle
import shutil
import stat
import struct
import tempfile

#: the first bytes of a handoff file (format version 1)
MAGIC = b"GONIOHO1"
#: the trailer: the pickle's offset and length (little-endian unsigned 64-bit)
_TRAILER = struct.Struct("<QQ")
#: every array's bytes start on such a boundary (a cache line; AVX-512 loads)
ALIGN = 64


class HandoffError(OSError):
    """A handoff file that is not what :func:`write` wrote."""


def write(meas, path) -> int:
    """Write ``meas`` (any picklable object; its contiguous arrays travel as raw bytes) to
    ``path``, which must not exist. Returns the bytes written."""
    buffers = []
    meta = pickle.dumps(meas, protocol=5, buffer_callback=buffers.append)
    index = []
    with open(path, "xb") as fh:
        fh.write(MAGIC)
        offset = len(MAGIC)
        for buf in buffers:
            raw = buf.raw()
            pad = -offset % ALIGN
            fh.write(b"\0" * pad)
            offset += pad
            fh.write(raw)
            index.append((offset, raw.nbytes))
            offset += raw.nbytes
        tail = pickle.dumps((meta, index), protocol=5)
        fh.write(tail)
        fh.write(_TRAILER.pack(offset, len(tail)))
    return offset + len(tail) + _TRAILER.size


def read(path):
    """What :func:`write` wrote to ``path``, its arrays viewing a private copy-on-write map
    of the file (writable; nothing is copied until written)."""
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if size < len(MAGIC) + _TRAILER.size:
            raise HandoffError(f"{path}: {size} bytes is too short for a gonio handoff file")
        mapped = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_COPY)
    if mapped[:len(MAGIC)] != MAGIC:
        raise HandoffError(f"{path}: not a gonio handoff file (its first bytes are not {MAGIC!r})")
    offset, length = _TRAILER.unpack(mapped[size - _TRAILER.size:])
    if not len(MAGIC) <= offset <= offset + length <= size - _TRAILER.size:
        raise HandoffError(f"{path}: its trailer points outside the file (offset {offset}, length {length})")
    try:
        meta, index = pickle.loads(mapped[offset:offset + length])
        spans = [(int(start), int(nbytes)) for start, nbytes in index]
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError) as exc:
        raise HandoffError(f"{path}: its index does not read ({type(exc).__name__})") from None
    for start, nbytes in spans:
        if not len(MAGIC) <= start <= start + nbytes <= offset:
            raise HandoffError(f"{path}: an array's bytes ({start}, {nbytes}) lie outside the data part")
    view = memoryview(mapped)
    return pickle.loads(meta, buffers=[view[start:start + nbytes] for start, nbytes in spans])


def claim(folder, index: int):
    """Claim dataset ``index`` of a batch whose claims live in ``folder``: True for the one
    caller that creates its claim (``O_CREAT | O_EXCL``: atomic, whichever worker process
    asks first), False for every other; None once the folder is gone (the batch is over:
    stop)."""
    try:
        fd = os.open(os.path.join(folder, str(int(index))), os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except FileExistsError:
        return False
    except FileNotFoundError:
        return None
    os.close(fd)
    return True


class BatchOver(HandoffError):
    """Raised by a loader of :meth:`Handoff.promise` whose file will never come: the batch
    ended or its writer failed (a claiming task then stops)."""


def read_when_written(path, poll_s: float = 0.002):
    """:func:`read` of a file that :meth:`Handoff.write_pending` may not have written yet:
    waits for it (a file appears whole: written under another name, then renamed), polling
    every 50 us at first and every ``poll_s`` at most; raises :class:`BatchOver` once its
    folder is gone or marked failed."""
    import time

    folder = os.path.dirname(path)
    wait = 5e-5
    while True:
        try:
            return read(path)
        except FileNotFoundError:
            if not os.path.isdir(folder) or os.path.exists(os.path.join(folder, FAILED)):
                raise BatchOver(f"{path}: the batch ended before this dataset was written") from None
        time.sleep(wait)
        wait = min(2 * wait, poll_s)


#: the marker :meth:`Handoff.fail` leaves in the folder
FAILED = "writer-failed"


#: the prefix of a batch's folder in the temporary folder
PREFIX = "gonio-batch-"
#: the file in a batch's folder that names the process that made it
OWNER = "owner"


def _start_time(pid: int):
    """Process ``pid``'s start time in clock ticks since boot (``/proc/PID/stat``, field 22),
    or None where there is no such file (not Linux, or no such process)."""
    try:
        with open(f"/proc/{int(pid)}/stat", "rb") as fh:
            raw = fh.read()
    except OSError:
        return None
    try:  # the command name (field 2) may hold spaces and parentheses: split after its last ')'
        return int(raw[raw.rindex(b")") + 2:].split()[19])
    except (ValueError, IndexError):
        return None


def _owner_text() -> str:
    pid = os.getpid()
    start = _start_time(pid)
    return f"{pid} {start if start is not None else '-'}\n"


def _owner_gone(text: str) -> bool:
    """Whether the process an ``owner`` file names has ended (its id unused, or used by a
    process that started at another time). False where the text does not read."""
    try:
        pid_s, start_s = text.split()
        pid = int(pid_s)
    except ValueError:
        return False
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:       # a live process of another user: the id was reused
        return True
    if start_s == "-":
        return False
    start = _start_time(pid)
    return start is not None and str(start) != start_s


def sweep_stale(folder=None) -> list:
    """Remove this user's batch folders in ``folder`` (the temporary folder by default) whose
    owner process has ended (killed before it could remove them). Returns the paths removed;
    never raises for a folder it cannot read or remove."""
    folder = tempfile.gettempdir() if folder is None else os.fspath(folder)
    removed = []
    try:
        names = [n for n in os.listdir(folder) if n.startswith(PREFIX)]
    except OSError:
        return removed
    uid = os.getuid()
    for name in names:
        path = os.path.join(folder, name)
        try:
            st = os.lstat(path)
            if not stat.S_ISDIR(st.st_mode) or st.st_uid != uid:
                continue
            with open(os.path.join(path, OWNER), encoding="ascii", errors="replace") as fh:
                text = fh.read(100)
        except OSError:           # no owner file yet (its batch is starting), or unreadable
            continue
        if _owner_gone(text):
            shutil.rmtree(path, ignore_errors=True)
            if not os.path.exists(path):
                removed.append(path)
    return removed


class Handoff:
    """A batch's private temporary folder: handoff files, the datasets' claims
    (:attr:`claims`, for :func:`claim`) and its ``owner`` file; :meth:`close` removes it all
    (also on leaving a ``with`` block). Made after :func:`sweep_stale`.

    :meth:`promise` returns a dataset's loader (a picklable function of no arguments:
    ``functools.partial(read_when_written, path)``) before its file exists, and
    :meth:`write_pending` writes the promised files afterwards, in order, each whole under
    its final name (written as ``.part``, then renamed), so that workers may start on the
    first datasets while the later ones are written."""

    def __init__(self):
        sweep_stale()
        self.folder = tempfile.mkdtemp(prefix=PREFIX)     # mode 0700
        self.claims = os.path.join(self.folder, "claims")
        try:
            os.mkdir(self.claims, 0o700)
            owner = os.path.join(self.folder, OWNER)
            with open(owner + ".part", "x", encoding="ascii") as fh:
                fh.write(_owner_text())
            os.replace(owner + ".part", owner)      # whole, or not there (a sweep skips it)
        except BaseException:
            shutil.rmtree(self.folder, ignore_errors=True)
            raise
        self.count = 0
        self.nbytes = 0
        self.pending = []

    def _path(self):
        path = os.path.join(self.folder, f"dataset{self.count:06d}.bin")
        self.count += 1
        return path

    def _write(self, meas, path):
        part = path + ".part"
        try:
            self.nbytes += write(meas, part)
            os.replace(part, path)
        except BaseException:
            try:
                os.unlink(part)          # no half-written file for a worker to find
            except OSError:
                pass
            raise

    def promise(self, meas):
        import functools

        path = self._path()
        self.pending.append((meas, path))
        return functools.partial(read_when_written, path)

    def write_pending(self) -> None:
        """Write every promised file, in the order promised; on an error, mark the folder
        failed (:meth:`fail`: the waiting loaders stop) and raise it."""
        pending, self.pending = self.pending, []
        try:
            for meas, path in pending:
                self._write(meas, path)
        except BaseException:
            self.fail()
            raise

    def fail(self) -> None:
        """Mark the folder failed: :func:`read_when_written` stops waiting."""
        try:
            os.close(os.open(os.path.join(self.folder, FAILED), os.O_CREAT | os.O_WRONLY, 0o600))
        except OSError:          # a full disk may refuse even this: close() removes the folder
            pass

    def close(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
