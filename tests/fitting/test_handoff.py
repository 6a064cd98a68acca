"""Measurements handed to local workers through files (gonio.fitting.batch.handoff): what is read
is what was written, its arrays aligned views of a private map; a file that is not one is
refused in one line; a failed write leaves no file behind."""

import errno
import os
import pickle
from pathlib import Path

import numpy as np
import pytest

from gonio.fitting import Measurements
from gonio.fitting.batch import handoff as _handoff
from gonio.fitting.batch.handoff import ALIGN, Handoff, HandoffError, claim, read, write


def _measurements(n=257, seed=5):
    rng = np.random.default_rng(seed)
    wi = rng.normal(size=(n, 3))
    wo = rng.normal(size=(n, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wo[:, 2] = np.abs(wo[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    brdf = rng.uniform(0.01, 2.0, (n, 3))
    use = rng.uniform(size=(n, 3)) > 0.1
    return Measurements(wi, wo, brdf, 0.02 * brdf + 1e-4, use, attrs={"seed": seed, "sample": "<b>"},
                        weight=rng.uniform(0.5, 2.0, n), cluster=np.arange(n) // 3)


ARRAYS = ("wi", "wo", "brdf", "brdf_std", "use", "weight", "cluster")


def test_what_is_read_is_what_was_written_as_aligned_writable_views(tmp_path):
    """Every array comes back equal, with its dtype, on a 64-byte boundary, and writable;
    writing into one changes neither the file nor what the next reader sees (the map is
    copy-on-write)."""
    meas = _measurements()
    path = tmp_path / "m.bin"
    nbytes = write(meas, path)
    assert nbytes == os.path.getsize(path)
    got = read(path)
    assert isinstance(got, Measurements) and got.attrs == meas.attrs and got.channels == meas.channels
    for name in ARRAYS:
        a, b = getattr(meas, name), getattr(got, name)
        assert b.dtype == a.dtype and np.array_equal(a, b), name
        assert b.ctypes.data % ALIGN == 0, name
        assert b.flags.writeable, name
    got.brdf[:] = -1.0
    assert np.array_equal(read(path).brdf, meas.brdf)


def test_a_file_that_is_not_a_handoff_file_is_refused_in_one_line(tmp_path):
    path = tmp_path / "m.bin"
    write(_measurements(), path)
    good = path.read_bytes()
    cases = {"empty": b"", "short": good[:10], "other marker": b"NOTGONIO" + good[8:],
             "trailer past the end": good[:-16] + (len(good)).to_bytes(8, "little") + (5).to_bytes(8, "little"),
             "cut in the middle": good[:len(good) // 2]}
    offset, length = _handoff._TRAILER.unpack(good[-_handoff._TRAILER.size:])
    cases["index not a pickle"] = good[:offset] + b"\xff" * length + good[offset + length:]
    meta, index = pickle.loads(good[offset:offset + length])
    for name, span in (("an array past the data", (index[0][0], offset)), ("an array in the marker", (0, 8))):
        tail = pickle.dumps((meta, [span] + list(index[1:])), protocol=5)
        cases[name] = good[:offset] + tail + _handoff._TRAILER.pack(offset, len(tail))
    for what, raw in cases.items():
        bad = tmp_path / "bad.bin"
        bad.write_bytes(raw)
        with pytest.raises(HandoffError) as info:
            read(bad)
        assert "\n" not in str(info.value) and str(bad) in str(info.value), what


def test_write_never_replaces_a_file_and_a_failed_write_leaves_none(tmp_path, monkeypatch):
    """``write`` refuses an existing path; ``Handoff.write_pending`` that fails half way (the
    disk full as the trailer is written) removes its half-written file; ``close`` removes the
    folder."""
    path = tmp_path / "m.bin"
    path.write_bytes(b"keep")
    with pytest.raises(FileExistsError):
        write(_measurements(), path)
    assert path.read_bytes() == b"keep"

    class Full:
        size = _handoff._TRAILER.size

        def pack(self, *values):
            raise OSError(errno.ENOSPC, "No space left on device")

    with Handoff() as handoff:
        loader = handoff.promise(_measurements())
        handoff.write_pending()
        assert np.array_equal(loader().wi, _measurements().wi)
        monkeypatch.setattr(_handoff, "_TRAILER", Full())
        handoff.promise(_measurements())
        with pytest.raises(OSError, match="No space"):
            handoff.write_pending()
        assert sorted(os.listdir(handoff.folder)) == ["claims", "dataset000000.bin", _handoff.OWNER, _handoff.FAILED]
        assert (os.stat(handoff.folder).st_mode & 0o777) == 0o700
    assert not os.path.exists(handoff.folder)


def test_a_dataset_is_claimed_once_and_no_claim_outlives_the_batch():
    """``claim``: True for the first caller only, False for every later one, None once the
    batch's folder is gone (a claiming task then stops)."""
    with Handoff() as handoff:
        assert [claim(handoff.claims, i) for i in (0, 1, 0, 2, 1)] == [True, True, False, True, False]
    assert claim(handoff.claims, 3) is None


def test_a_promised_dataset_is_read_once_written_and_never_half_written(monkeypatch):
    """``promise`` gives the loader before the file exists: a reader waits for it
    (``read_when_written``) and gets the whole dataset once ``write_pending`` has written it
    (under another name, then renamed); where the writer fails (the disk full), the readers
    stop with ``BatchOver`` instead of waiting for ever, and so do they once the folder is
    gone."""
    import threading

    from gonio.fitting.batch.handoff import BatchOver

    meas = _measurements()
    with Handoff() as handoff:
        loader = handoff.promise(meas)
        got = {}
        reader = threading.Thread(target=lambda: got.update(m=loader()))
        reader.start()
        reader.join(0.05)
        assert reader.is_alive() and sorted(os.listdir(handoff.folder)) == ["claims", _handoff.OWNER]
        handoff.write_pending()
        reader.join(5)
        assert not reader.is_alive() and np.array_equal(got["m"].brdf, meas.brdf)
        assert sorted(os.listdir(handoff.folder)) == ["claims", "dataset000000.bin", _handoff.OWNER]

        class Full:
            size = _handoff._TRAILER.size

            def pack(self, *values):
                raise OSError(errno.ENOSPC, "No space left on device")

        late = handoff.promise(meas)
        monkeypatch.setattr(_handoff, "_TRAILER", Full())
        with pytest.raises(OSError, match="No space"):
            handoff.write_pending()
        assert not [f for f in os.listdir(handoff.folder) if f.endswith(".part")]
        with pytest.raises(BatchOver, match="ended"):
            late()
    with pytest.raises(BatchOver):
        loader()


def test_a_batch_folder_left_by_a_killed_process_is_removed_by_the_next_batch(tmp_path, monkeypatch):
    """A process killed with SIGKILL cannot remove its batch folder (its datasets' files,
    in memory where the temporary folder is a tmpfs): the next Handoff removes it, and only
    folders whose owner is gone (a live process's, one whose owner file is not written
    yet, another name, a file of that name are all left alone)."""
    import signal
    import subprocess
    import sys
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    code = ("import time\nfrom gonio.fitting.batch.handoff import Handoff\nh = Handoff()\n"
            "print(h.folder, flush=True)\ntime.sleep(120)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "TMPDIR": str(tmp_path)})
    try:
        killed = proc.stdout.readline().strip()
        assert os.path.dirname(killed) == str(tmp_path) and os.path.isdir(killed)
        Path(killed, "dataset000000.bin").write_bytes(b"x" * 4096)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(30)
        proc.stdout.close()
    assert os.path.isdir(killed)                                   # SIGKILL left it behind
    starting = tmp_path / f"{_handoff.PREFIX}starting"               # mkdtemp done, owner not yet written
    starting.mkdir()
    reused = tmp_path / f"{_handoff.PREFIX}reused"                   # this process's id, another start time
    reused.mkdir()
    (reused / _handoff.OWNER).write_text(f"{os.getpid()} 1\n")
    garbled = tmp_path / f"{_handoff.PREFIX}garbled"
    garbled.mkdir()
    (garbled / _handoff.OWNER).write_text("not a process\n")
    not_a_folder = tmp_path / f"{_handoff.PREFIX}file"
    not_a_folder.write_text("1 1\n")
    other = tmp_path / "other-batch"
    other.mkdir()
    (other / _handoff.OWNER).write_text("999999999 1\n")
    with Handoff() as live:
        assert not os.path.exists(killed)
        assert not reused.exists() or _handoff._start_time(os.getpid()) is None
        assert starting.is_dir() and garbled.is_dir() and not_a_folder.is_file() and other.is_dir()
        with Handoff() as second:                                  # a live batch's folder stays
            assert os.path.isdir(live.folder) and os.path.isdir(second.folder)
            owner = (Path(second.folder) / _handoff.OWNER).read_text().split()
            assert int(owner[0]) == os.getpid()
    assert _handoff.sweep_stale(tmp_path / "missing") == []        # a folder that is not there: nothing, no error
