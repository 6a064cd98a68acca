"""The disk during a capture and an export (issue 14, environment errors).

* ``gonio capture`` (and ``--resume``) checks before anything is written that the session folder
  is writable and that its disk has room for the plan's RAW files (points x frames per point,
  darks, flats, the camera's frame size): one line naming the disk and the sizes, exit 2.
* A disk that fills during a capture (the camera's DNG write, its rename, a RAW placeholder,
  the journal's commit) stops it resumably: exit 3, the stages stopped, the LED off, the journal
  consistent, one line naming the disk and how to resume; the resume then measures every point
  once.
* ``gonio export`` checks the dataset's size against the free space, writes through a temporary
  name and renames: a full disk is one line, exit 2, and no partial (or replaced) dataset.nc.

``main()`` runs in this process on the simulated instrument (instant clock).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from gonio.cli import main as cli
from gonio.core.preflight import mount_of

ENOSPC = "No space left on device"


def gonio(capsys, *args):
    """(exit status, stdout, the stderr lines) of ``gonio ARGS`` in this process."""
    rc = cli.main([str(a) for a in args])
    cap = capsys.readouterr()
    return rc, cap.out, [line for line in cap.err.splitlines() if line.strip()]


def listing(folder):
    return sorted(str(p.relative_to(folder)) for p in Path(folder).rglob("*"))


def journal(session: Path):
    db = sqlite3.connect(str(session / "journal.sqlite"))
    try:
        points = [r[0] for r in db.execute("SELECT idx FROM points ORDER BY idx")]
        superseded = db.execute("SELECT COUNT(*) FROM superseded").fetchone()[0]
        events = [(k, t) for k, t in db.execute("SELECT kind, text FROM events ORDER BY id")]
        used = {r[0] for r in db.execute("SELECT file FROM calibration")}
        for (detail,) in db.execute("SELECT detail FROM points"):
            used |= {e["file"] for e in json.loads(detail)["exposures"]}
    finally:
        db.close()
    return {"points": points, "superseded": superseded, "events": events, "used": used}


@pytest.fixture
def little_space(monkeypatch):
    """The disk of every path has 2 MiB free."""
    import gonio.core.preflight as pf

    real = shutil.disk_usage
    monkeypatch.setattr(pf.shutil, "disk_usage", lambda p: real(p)._replace(free=2 << 20))


@pytest.fixture
def plan_file(tmp_path):
    """Twelve points (a quick capture of the simulated bench)."""
    p = tmp_path / "plan.toml"
    pts = [[th, 0, 30, 180] for th in (10, 20, 30, 40)] + [[30, 0, th, 180] for th in (10, 20, 40, 50)] + \
          [[20, 0, 40, 90], [40, 0, 20, 90], [35, 0, 35, 150], [50, 0, 10, 180]]
    p.write_text('name = "twelve"\npoints = ' + json.dumps(pts) + "\n")
    return p


# ------------------------------------------------------------------- checked up front
def test_capture_refused_up_front_when_the_disk_is_too_small(capsys, tmp_path, little_space):
    out = tmp_path / "s"
    rc, _, err = gonio(capsys, "capture", "--sim", "--plan", "quick", "--out", out, "--quiet")
    assert rc == 2, err
    assert len(err) == 1, err
    line = err[0]
    assert line.startswith("gonio: error: not enough space for the RAW files of session"), line
    # names the disk and the sizes: free, needed, the frames behind the estimate
    for needle in (f"the disk at {mount_of(tmp_path)} has 2 MiB free", "MiB are needed", "30 point(s) x ~4 RAW frames",
                   "528 dark/flat frames", "~12 KiB each", "free some space or give another --out"):
        assert needle in line, line
    assert not out.exists()                       # nothing written, not even the folder
    assert listing(tmp_path) == []


def test_capture_refused_when_the_out_folder_is_read_only(capsys, tmp_path):
    from gonio.core.preflight import check_output_dir
    from gonio.core.errors import GonioError

    def unwritable(folder):
        try:
            check_output_dir(folder / "probe")
        except GonioError:
            return True
        return False
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        target = ro if unwritable(ro) else Path("/sys")     # as root, a 0555 folder is writable
        if not unwritable(target):
            pytest.skip("no unwritable folder on this machine")
        rc, _, err = gonio(capsys, "capture", "--sim", "--plan", "quick", "--out", target / "s", "--quiet")
        assert rc == 2 and len(err) == 1, err
        assert err[0].startswith("gonio: error: session folder (--out)") and "write to" in err[0], err
    finally:
        ro.chmod(0o755)
    assert listing(ro) == []


def test_the_estimate_follows_the_plan_the_ladder_and_the_frame_size(tmp_path):
    from gonio.bench.measure.point import FRAMES_PER_POINT, raw_estimate
    from gonio.bench.settings import default_settings, merge_settings

    s = default_settings()
    e = raw_estimate(s, 100, has_flat=True)
    assert (e.points, e.per_point, e.calibration, e.frame_bytes) == (100, FRAMES_PER_POINT, 15 + 512 + 1, 12288)
    assert raw_estimate(s, 100, has_flat=False).calibration == 15            # no flat source: darks only
    big = merge_settings(s, {"camera": {"width": 6000, "height": 4000}, "capture": {"exposure_max_s": 1.0}})
    e = raw_estimate(big, 1053, has_flat=False)
    assert e.calibration == 13 and e.frame_bytes == 50_401_280 and e.bytes > 1053 * 4 * 48e6


def test_resume_refused_up_front_for_what_is_left(capsys, tmp_path, plan_file, monkeypatch):
    import gonio.core.preflight as pf
    from gonio.bench.session.journal import Journal

    out = tmp_path / "s"
    real_record = Journal.record_point
    calls = []

    def record_then_stop(self, *a, **k):            # a Ctrl-C once after the 5th point
        real_record(self, *a, **k)
        calls.append(1)
        if len(calls) == 5:
            import signal
            os.kill(os.getpid(), signal.SIGINT)
    monkeypatch.setattr(Journal, "record_point", record_then_stop)
    rc, _, err = gonio(capsys, "capture", "--sim", "--plan", plan_file, "--out", out, "--quiet")
    assert rc == 3, err
    monkeypatch.setattr(Journal, "record_point", real_record)
    before = listing(out), journal(out)["points"], (out / "journal.sqlite").read_bytes()
    real = shutil.disk_usage
    monkeypatch.setattr(pf.shutil, "disk_usage", lambda p: real(p)._replace(free=1 << 20))
    rc, _, err = gonio(capsys, "capture", "--resume", out, "--quiet")
    assert rc == 2 and len(err) == 1, err
    line = err[0]
    for needle in (f"not enough space for the 7 point(s) left to measure in {out}", f"the disk at {mount_of(out)}",
                   "1 MiB free", "MiB are needed", f"free some space, then resume with `gonio capture --resume {out}`"):
        assert needle in line, line
    assert (listing(out), journal(out)["points"], (out / "journal.sqlite").read_bytes()) == before
    monkeypatch.setattr(pf.shutil, "disk_usage", real)
    rc, _, err = gonio(capsys, "capture", "--resume", out, "--quiet")
    assert rc == 0, err
    assert journal(out)["points"] == list(range(12))


# ------------------------------------------------------------------- the disk fills during the capture
def _full(path=None):
    return OSError(errno.ENOSPC, ENOSPC, *([str(path)] if path is not None else []))


SITES = ["camera-dng", "camera-rename", "raw-placeholder", "journal-commit", "journal-reserve"]


@pytest.mark.parametrize("site", SITES)
def test_disk_full_during_a_capture_stops_resumably(capsys, tmp_path, plan_file, monkeypatch, site):
    import gonio.bench.drivers.camera as camera
    import gonio.bench.drivers.stages as zaber
    import gonio.bench.session.run as session
    import gonio.bench.session.simulated as runner     # where capture_sim builds its instrument
    import gonio.sim.devices.camera_port as port
    from gonio.bench.session.journal import Journal

    out = tmp_path / "s"
    done = []
    full = {"on": False}
    real_record = Journal.record_point

    def record(self, *a, **k):
        if full["on"] and site == "journal-commit":
            raise sqlite3.OperationalError("database or disk is full")
        real_record(self, *a, **k)
        done.append(a[0])
        if len(done) == 6:
            full["on"] = True                        # the disk fills after the 6th point
    monkeypatch.setattr(Journal, "record_point", record)

    def when_full(real, make):
        def wrapped(*a, **k):
            if full["on"]:
                raise make(*a)
            return real(*a, **k)
        return wrapped
    if site == "camera-dng":                        # the (simulated) camera's own write of the DNG
        monkeypatch.setattr(port, "write_dng", when_full(port.write_dng, lambda p, d: _full(p)))
    elif site == "camera-rename":                   # the fsync/rename of the verified file
        monkeypatch.setattr(camera, "commit_file", when_full(camera.commit_file, lambda t, p: _full()))
    elif site == "raw-placeholder":                 # the empty placeholder of a reserved RAW name
        monkeypatch.setattr(session, "create_exclusive", when_full(session.create_exclusive, lambda p: _full(p)))
    elif site == "journal-reserve":
        def boom(self, *a):
            raise sqlite3.OperationalError("database or disk is full")
        monkeypatch.setattr(Journal, "reserve", when_full(Journal.reserve, boom))
    stops, insts = [], []
    real_stop = zaber.Goniometer.stop
    monkeypatch.setattr(zaber.Goniometer, "stop", lambda self: (stops.append(1), real_stop(self))[1])
    real_inst = runner.sim_instrument
    monkeypatch.setattr(runner, "sim_instrument", lambda *a, **k: insts.append(real_inst(*a, **k)) or insts[-1])

    rc, _, err = gonio(capsys, "capture", "--sim", "--plan", plan_file, "--out", out, "--quiet")
    assert rc == 3, err
    assert len(err) == 1, err
    line = err[0]
    assert line.startswith(f"gonio: stopped: the disk at {mount_of(out)} is full"), line
    for needle in ("6/12 points are measured and the session is consistent", "free at least",
                   "MiB for the 6 point(s) left", f"then resume with `gonio capture --resume {out}`"):
        assert needle in line, line
    assert ("journal.sqlite" if site.startswith("journal") else "raw/p0") in line, line
    assert stops, "the stages were not stopped"
    assert insts[-1].lamp.on is False, "the LED was left on"
    j = journal(out)
    assert len(j["points"]) == 6
    kinds = [k for k, _ in j["events"]]
    assert ("lamp", "LED off") in j["events"] and "stop" in kinds
    raw = listing(out / "raw")
    assert not [n for n in raw if n.startswith(".tmp-") or n.endswith(".part")], raw    # nothing half-written

    monkeypatch.setattr(Journal, "record_point", real_record)      # space freed
    full["on"] = False
    done.clear()
    rc, stdout, err = gonio(capsys, "capture", "--resume", out, "--quiet")
    assert rc == 0, err
    assert "12/12 points (6 new)" in stdout
    j = journal(out)
    assert j["points"] == list(range(12)) and j["superseded"] == 0   # every point measured once
    raw, used = set(listing(out / "raw")), {f.split("/", 1)[1] for f in j["used"]}
    assert used <= raw
    extra = raw - used          # no stray RAW file: the frames of the point whose commit failed are deleted by
    assert not extra, extra     # the resume (issue 36: a stopped run leaves no orphan; they were kept before)
    rc, _, err = gonio(capsys, "export", out)
    assert rc == 0, err


def test_disk_full_while_the_session_is_created(capsys, tmp_path, plan_file, monkeypatch):
    """session.toml written, the journal's first commit fails: stopped, and the resume starts it."""
    from gonio.bench.session.journal import Journal

    out = tmp_path / "s"
    real = Journal.record_session

    def boom(self, *a):
        raise sqlite3.OperationalError("database or disk is full")
    monkeypatch.setattr(Journal, "record_session", boom)
    rc, _, err = gonio(capsys, "capture", "--sim", "--plan", plan_file, "--out", out, "--quiet")
    assert rc == 3 and len(err) == 1, err
    assert err[0].startswith(f"gonio: stopped: the disk at {mount_of(out)} is full (database or disk is full) "
                             "while writing journal.sqlite"), err
    assert f"--resume {out}" in err[0]
    monkeypatch.setattr(Journal, "record_session", real)
    rc, _, err = gonio(capsys, "capture", "--resume", out, "--quiet")
    assert rc == 0, err
    assert journal(out)["points"] == list(range(12))


def test_disk_full_writing_session_toml_leaves_a_folder_to_capture_into(capsys, tmp_path, plan_file, monkeypatch):
    import gonio.core.files as files

    out = tmp_path / "s"
    real = files.os.fsync
    monkeypatch.setattr(files.os, "fsync", lambda fd: (_ for _ in ()).throw(_full()))
    rc, _, err = gonio(capsys, "capture", "--sim", "--plan", plan_file, "--out", out, "--quiet")
    assert rc == 2 and len(err) == 1, err
    assert f"the disk at {mount_of(out)} is full ({ENOSPC}); free some space and run the command again" in err[0], err
    assert not [n for n in listing(out) if n.endswith("session.toml")], listing(out)
    monkeypatch.setattr(files.os, "fsync", real)
    rc, _, err = gonio(capsys, "capture", "--sim", "--plan", plan_file, "--out", out, "--quiet")
    assert rc == 0, err


# ------------------------------------------------------------------- export
@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from gonio.bench.samples import load_sample
    from gonio.cli.capture import capture_sim

    root = tmp_path_factory.mktemp("disk")
    capture_sim(root / "s", sample=load_sample(None), plan="quick", seed=1, progress=False)
    return root / "s"


def test_export_refused_up_front_on_a_small_disk(capsys, session, monkeypatch, little_space):
    (session / "dataset.nc").unlink(missing_ok=True)
    before = listing(session)
    rc, _, err = gonio(capsys, "export", session)
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith(f"gonio: error: not enough space for {session / 'dataset.nc'}"), err
    assert f"the disk at {mount_of(session)} has 2 MiB free" in err[0] and "MiB are needed" in err[0]
    assert listing(session) == before


@pytest.mark.parametrize("where", ["write", "fsync", "rename"])
def test_export_disk_full_at_the_write_leaves_no_partial_file(capsys, session, monkeypatch, where):
    import builtins

    import gonio.core.files as files
    import gonio.bench.dataset.export as export

    (session / "dataset.nc").unlink(missing_ok=True)
    rc, _, err = gonio(capsys, "export", session)             # a first export: kept as it was
    assert rc == 0, err
    old = (session / "dataset.nc").read_bytes()
    before = listing(session)
    if where == "write":
        real_open = builtins.open

        class Half:
            def __init__(self, fh):
                self.fh = fh

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                self.fh.close()

            def write(self, data):
                self.fh.write(bytes(data[: len(data) // 2]))
                raise _full(self.fh.name)

        monkeypatch.setattr(export, "open", lambda p, m="r", *a, **k: Half(real_open(p, m, *a, **k)) if "w" in m
                            else real_open(p, m, *a, **k), raising=False)
    elif where == "fsync":
        monkeypatch.setattr(files.os, "fsync", lambda fd: (_ for _ in ()).throw(_full()))
    else:
        monkeypatch.setattr(files.os, "replace", lambda a, b: (_ for _ in ()).throw(_full(b)))
    rc, _, err = gonio(capsys, "export", session)
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith(f"gonio: error: {session / 'dataset.nc'}: the disk at {mount_of(session)} is full "
                             f"({ENOSPC}); nothing was left half-written"), err
    assert listing(session) == before                            # no .tmp-dataset.nc
    assert (session / "dataset.nc").read_bytes() == old


def test_h5py_never_writes_to_the_disk(session, monkeypatch):
    """The dataset is serialised in memory: h5py (which crashed on a full disk) gets no path."""
    import xarray as xr

    from gonio.bench.dataset.export import export

    seen = []
    real = xr.Dataset.to_netcdf
    monkeypatch.setattr(xr.Dataset, "to_netcdf", lambda self, path=None, *a, **k: (seen.append(path),
                                                                                  real(self, path, *a, **k))[1])
    path = export(session)
    assert seen == [None]
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        assert ds.sizes["point"] == 30


def _tmpfs(folder: Path, size: str) -> bool:
    folder.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                          capture_output=True).returncode == 0


def test_a_real_full_disk(tmp_path, session):
    """On a real (tmpfs) disk too small for them: capture and export refuse in one line, no crash."""
    disk = tmp_path / "disk"
    if not _tmpfs(disk, "1m"):
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        env = {**os.environ, "COLUMNS": "200"}
        run = [sys.executable, "-m", "gonio.cli.main"]
        r = subprocess.run(run + ["capture", "--sim", "--plan", "quick", "--out", str(disk / "s"), "--quiet"],
                           capture_output=True, text=True, env=env, timeout=120)
        assert r.returncode == 2 and len(r.stderr.splitlines()) == 1, r.stderr
        assert f"the disk at {disk} has" in r.stderr, r.stderr
        shutil.copytree(session, disk / "e", ignore=shutil.ignore_patterns("raw", "dataset.nc"))
        def export():
            return subprocess.run(run + ["export", str(disk / "e")], capture_output=True, text=True, env=env,
                                  timeout=120)

        with open(disk / "fill", "wb", buffering=0) as fh:
            while shutil.disk_usage(disk).free > 256 << 10:      # room to read the journal, not for the dataset
                fh.write(b"\0" * (16 << 10))
            r = export()
            assert r.returncode == 2, (r.returncode, r.stderr)          # 15e620e: 139, a segfault in h5py
            assert len(r.stderr.splitlines()) == 1, r.stderr
            assert f"not enough space for {disk / 'e' / 'dataset.nc'}" in r.stderr, r.stderr
            assert f"the disk at {disk} has 0 MiB free" in r.stderr, r.stderr
            try:
                while True:                                      # no room at all
                    fh.write(b"\0" * 4096)
            except OSError:
                pass
        r = export()
        assert r.returncode == 2 and len(r.stderr.splitlines()) == 1, (r.returncode, r.stderr)
        assert "journal.sqlite cannot be read: the disk at" in r.stderr and "rebuild" not in r.stderr, r.stderr
        assert not [n for n in os.listdir(disk / "e") if "dataset" in n]
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True)


def test_a_real_disk_filling_during_a_capture(capsys, tmp_path, plan_file, monkeypatch):
    """A tmpfs that passes the up-front check fills after the 6th point: the real ENOSPC / SQLITE_FULL
    of the camera's write or the journal stops the capture resumably; space freed, the resume finishes."""
    from gonio.bench.session.journal import Journal

    disk = tmp_path / "disk"
    if not _tmpfs(disk, "32m"):
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        out = disk / "s"
        real = Journal.record_point
        n = []

        def record(self, *a, **k):
            real(self, *a, **k)
            n.append(1)
            if len(n) == 6:
                with open(disk / "fill", "wb", buffering=0) as fh:
                    try:
                        while True:
                            fh.write(b"\0" * (64 << 10))
                    except OSError:
                        pass
        monkeypatch.setattr(Journal, "record_point", record)
        rc, _, err = gonio(capsys, "capture", "--sim", "--plan", plan_file, "--out", out, "--quiet")
        assert rc == 3 and len(err) == 1, err
        assert err[0].startswith(f"gonio: stopped: the disk at {disk} is full"), err
        assert "6/12 points are measured" in err[0] and f"--resume {out}" in err[0], err
        (disk / "fill").unlink()
        monkeypatch.setattr(Journal, "record_point", real)
        rc, stdout, err = gonio(capsys, "capture", "--resume", out, "--quiet")
        assert rc == 0, err
        assert "12/12 points (6 new)" in stdout
        j = journal(out)
        assert j["points"] == list(range(12)) and j["superseded"] == 0
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True)
