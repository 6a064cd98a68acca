"""Fit files and every atomically written file (issue 14): strict JSON, the user's umask mode,
and no temporary file left behind, whether the writer fails, is interrupted or is killed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from gonio.fitting import load_fit, write_json_atomic
from gonio.fitting.formats.fitfile import NonFiniteWarning, _jsonable
from gonio.core.atomic import atomic_open


def strict(text: str):
    def refuse(name):
        raise AssertionError(f"{name} in a file that must be strict JSON")

    return json.loads(text, parse_constant=refuse)


def temporaries(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_numpy_nan_and_inf_scalars_become_null_and_are_listed(tmp_path):
    doc = {"format": "gonio-fit/1", "goodness": {"chi2": np.float64("nan"), "chi2_dof": np.float32("inf"),
                                                 "dof": np.int64(3), "ok": np.bool_(True)},
           "covariance": {"matrix": np.array([[1.0, np.nan], [-np.inf, 2.0]])}, "tau": [np.float16("nan"), 1.5]}
    path = write_json_atomic(tmp_path / "fit.json", doc)
    loaded = strict(path.read_text())
    assert loaded["goodness"] == {"chi2": None, "chi2_dof": None, "dof": 3, "ok": True}
    assert loaded["covariance"]["matrix"] == [[1.0, None], [None, 2.0]]
    assert loaded["tau"] == [None, 1.5]
    assert loaded["non_finite"] == sorted(["goodness.chi2", "goodness.chi2_dof", "covariance.matrix[0][1]",
                                           "covariance.matrix[1][0]", "tau[0]"])
    bad = []
    assert _jsonable(np.float32("nan"), "x", bad) is None and bad == ["x"]


def test_other_documents_say_so_with_a_warning(tmp_path):
    with pytest.warns(NonFiniteWarning, match=r"render.json: NaN or infinite values written as null at summary.rms"):
        path = write_json_atomic(tmp_path / "render.json", {"summary": {"rms": np.float64("nan")}})
    assert strict(path.read_text()) == {"summary": {"rms": None}}


def test_unserialisable_document_writes_nothing(tmp_path):
    (tmp_path / "fit.json").write_text('{"old": 1}')
    with pytest.raises(TypeError):
        write_json_atomic(tmp_path / "fit.json", {"path": object()})
    assert (tmp_path / "fit.json").read_text() == '{"old": 1}' and not temporaries(tmp_path)


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_load_fit_refuses_non_json_numbers(tmp_path, token):
    path = tmp_path / "fit.json"
    path.write_text('{"format": "gonio-fit/1", "model": {"name": "diffuse", "options": {}}, '
                    f'"params": {{"reflectance": [0.5, {token}, 0.2]}}}}')
    with pytest.raises(ValueError, match=f"{token} is not JSON"):
        load_fit(path)


@pytest.mark.parametrize("params, needle", [({"reflectance": ["<script>"]}, "params.reflectance"),
                                            ({"reflectance": True}, "params.reflectance"),
                                            ({"reflectance": ["1e400"]}, "not finite"),
                                            ("x", "'params' must be")])
def test_load_fit_refuses_bad_values(tmp_path, params, needle):
    path = tmp_path / "fit.json"
    text = json.dumps({"format": "gonio-fit/1", "model": {"name": "diffuse", "options": {}}, "params": params})
    path.write_text(text.replace('"1e400"', "1e400"))  # a literal that JSON reads as inf
    with pytest.raises(ValueError, match=needle.replace("[", r"\[").replace("(", r"\(")):
        load_fit(path)


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_files_get_the_umask_mode(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        json_path = write_json_atomic(tmp_path / "fit.json", {"a": 1})
        with atomic_open(tmp_path / "x.bin", "wb") as fh:
            fh.write(b"x")
    finally:
        os.umask(old)
    assert json_path.stat().st_mode & 0o777 == mode
    assert (tmp_path / "x.bin").stat().st_mode & 0o777 == mode


@pytest.mark.parametrize("error", [KeyboardInterrupt, OSError, SystemExit])
def test_failed_write_removes_its_temporary_and_keeps_the_old_file(tmp_path, error):
    target = tmp_path / "report.html"
    target.write_text("old")
    with pytest.raises(error):
        with atomic_open(target, "w") as fh:
            fh.write("new, half")
            assert temporaries(tmp_path)
            raise error()
    assert target.read_text() == "old" and not temporaries(tmp_path)


def test_failed_rename_removes_its_temporary(tmp_path, monkeypatch):
    def refuse(*_):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(KeyboardInterrupt):
        write_json_atomic(tmp_path / "fit.json", {"a": 1})
    monkeypatch.undo()
    assert not (tmp_path / "fit.json").exists() and not temporaries(tmp_path)


def test_temporaries_of_killed_writers_are_removed_by_the_next_write(tmp_path):
    """A writer SIGKILLed mid-write leaves its temporary; the next write of that file removes
    it (and untagged ones older than ten minutes), but not one a live writer still owns."""
    target = tmp_path / "fit.json"
    code = ("import os, signal, sys\nfrom gonio.core.atomic import atomic_open\n"
            "with atomic_open(sys.argv[1], 'w') as fh:\n    fh.write('half'); fh.flush()\n"
            "    os.kill(os.getpid(), signal.SIGKILL)\n")
    proc = subprocess.run([sys.executable, "-c", code, str(target)], timeout=60)
    assert proc.returncode == -signal.SIGKILL
    (left,) = temporaries(tmp_path)
    assert left.startswith(".fit.json.") and not target.exists()
    old_untagged = tmp_path / ".fit.json.abc123.tmp"  # the name an older gonio used
    old_untagged.write_text("x")
    os.utime(old_untagged, (time.time() - 3600,) * 2)
    fresh_untagged = tmp_path / ".fit.json.def456.tmp"
    fresh_untagged.write_text("x")
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        live = tmp_path / f".fit.json.{sleeper.pid}-zzz.tmp"
        live.write_text("x")
        other = tmp_path / ".other.json.1-zzz.tmp"
        other.write_text("x")
        longer = tmp_path / ".fit.json.bak.abc123.tmp"  # an old temporary of fit.json.bak, not of fit.json
        longer.write_text("x")
        os.utime(longer, (time.time() - 3600,) * 2)
        write_json_atomic(target, {"a": 1})
        assert temporaries(tmp_path) == sorted([fresh_untagged.name, live.name, other.name, longer.name])
    finally:
        sleeper.kill()
        sleeper.wait()
    assert strict(target.read_text()) == {"a": 1}


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o002, 0o664)])
def test_write_once_files_are_atomic_with_the_umask_mode(tmp_path, umask, mode):
    """session.toml's writer (gonio/core/files.write_new_text) is the one atomic writer with
    ``replace=False``: the umask's mode, the one temporary scheme (none left behind), and a
    second write refused with the first file kept; a RAW placeholder gets the umask's mode too."""
    from gonio.core.files import create_exclusive, write_new_text
    from gonio.core.atomic import is_temporary

    old = os.umask(umask)
    try:
        write_new_text(tmp_path / "session.toml", "first")
        with pytest.raises(FileExistsError):
            write_new_text(tmp_path / "session.toml", "second")
        assert create_exclusive(tmp_path / "p.dng") and not create_exclusive(tmp_path / "p.dng")
    finally:
        os.umask(old)
    assert (tmp_path / "session.toml").read_text() == "first"
    assert (tmp_path / "session.toml").stat().st_mode & 0o777 == mode
    assert (tmp_path / "p.dng").stat().st_mode & 0o777 == mode
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.dng", "session.toml"]
    assert not any(is_temporary(p.name) for p in tmp_path.iterdir())


def test_a_folder_is_listed_for_stale_temporaries_once_per_process(tmp_path, monkeypatch):
    """Every write used to list the whole folder for the target's stale temporaries: a capture's
    raw/ grew by a frame per write, so its cost grew with the square of the frame count. The
    folder is listed once per process (and again once made anew); a stale temporary found then
    is still removed at its target's first write, and a writer's own temporary by the writer."""
    from gonio.core import atomic

    stale = tmp_path / ".p00007.dng.1-zzz.tmp"        # pid 1 is alive: kept, checked at each write
    dead = tmp_path / ".p00009.dng.999999999-zzz.tmp"  # no such pid: removed at p00009's first write
    stale.write_text("x")
    dead.write_text("x")
    listed = []
    real = os.scandir

    def scandir(path="."):
        listed.append(os.fspath(path))
        return real(path)

    monkeypatch.setattr(atomic.os, "scandir", scandir)
    for k in range(40):
        with atomic_open(tmp_path / f"p{k:05d}.dng", "wb") as fh:
            fh.write(b"raw")
    assert listed == [os.fspath(tmp_path)]
    assert stale.exists() and not dead.exists()
    assert temporaries(tmp_path) == [stale.name]
    (tmp_path / ".p00011.dng.999999999-zzz.tmp").write_text("x")   # a writer killed meanwhile:
    with atomic_open(tmp_path / "p00011.dng", "wb") as fh:            # left to the next process
        fh.write(b"raw")
    assert len(listed) == 1 and len(temporaries(tmp_path)) == 2
    atomic.remove_stale_temporaries(tmp_path / "p00011.dng", rescan=True)
    assert temporaries(tmp_path) == [stale.name] and len(listed) == 2


def test_a_file_its_reader_commits_is_written_atomically_without_fsync(tmp_path, monkeypatch):
    """``durable=False`` (the simulated camera's frames, which the bench checks, fsyncs and
    renames itself): no fsync, still never half-written under the name, nothing left behind."""
    calls = []
    monkeypatch.setattr(os, "fsync", lambda fd: calls.append(fd))
    with atomic_open(tmp_path / ".tmp-p.dng", "wb", durable=False) as fh:
        fh.write(b"half")
        assert not (tmp_path / ".tmp-p.dng").exists()
        fh.write(b" and the rest")
    assert (tmp_path / ".tmp-p.dng").read_bytes() == b"half and the rest" and calls == []
    assert sorted(p.name for p in tmp_path.iterdir()) == [".tmp-p.dng"]
    with atomic_open(tmp_path / "fit.json", "w") as fh:
        fh.write("{}")
    assert len(calls) == 2                              # the durable default: the file, the folder
