"""A session is one consistent record (issue 14): the lock comes before any write; session.toml
is checked against its journalled copy on every resume; a missing, emptied or truncated journal
(or a lost -wal) next to RAW files is refused with a recovery command that works; RAW files are
never overwritten; lost or corrupt RAW files are measured again; plans hold each point once
whatever their format."""

import hashlib
import json
import os
import shutil
import sqlite3

import numpy as np
import pytest

sim = pytest.importorskip("gonio.sim")

from gonio.bench.session import capture as capture_mod
from gonio.bench.plan import plans
from benchfakes.cameras import InterruptingCamera
from gonio.bench.measure.hdr import ladder
from gonio.bench.session.journal import Journal, SessionLock
from gonio.bench.settings import default_settings
from gonio.bench.session.capture import capture, resume
from gonio.core.errors import SessionError
from gonio.bench.dataset.export import export

S = default_settings()
GLOSSY = {"model": "roughplastic", "params": {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": 0.15}}
PLAN = plans.Plan("five", [[30, 0, 40, 180], [20, 0, 50, 90], [45, 0, 20, 0], [30, 0, 30, 180],
                           [10, 0, 70, 135]])


_count = [0]


def instrument(seed=1):
    _count[0] += 1
    return sim.Instrument(S, sample=GLOSSY, seed=seed).register(f"integ{os.getpid()}-{_count[0]}")


def urls(inst):
    return inst.url("zaber"), inst.url("meter"), inst.url("camera")


def n_darks():
    return len(ladder(S["capture"]["exposure_min_s"], S["capture"]["exposure_max_s"]))


def one_line(exc, *needles):
    msg = str(exc.value)
    assert "\n" not in msg
    for n in needles:
        assert n in msg, msg
    return msg


def raw_hashes(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in (folder / "raw").iterdir()
            if p.is_file() and not p.name.startswith(".")}


def idx_rows(folder):
    return [r[0] for r in sqlite3.connect(folder / "journal.sqlite").execute("SELECT idx FROM points ORDER BY idx")]


def resume_on(folder, **kw):
    inst = instrument()
    try:
        z, m, c = urls(inst)
        return resume(folder, z, m, kw.pop("camera", c), progress=False, sleep=inst.clock.advance, **kw)
    finally:
        inst.unregister()


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """Complete sessions ``complete`` and ``walsnap``, and ``partial``, stopped by Ctrl-C once after
    a point or two; copy before use. ``snap.sqlite`` is walsnap's journal.sqlite as it was on disk
    mid-run, its recent commits still only in the -wal."""
    base = tmp_path_factory.mktemp("sessions")
    inst = instrument()
    try:
        z, m, c = urls(inst)
        res = capture(base / "complete", PLAN, S, z, m, c, seed=1, progress=False, sleep=inst.clock.advance)
        assert res.complete
        snap = base / "snap.sqlite"

        def hook(n, path):
            if not snap.exists() and len(idx_rows(base / "walsnap")) >= 1:
                shutil.copyfile(base / "walsnap" / "journal.sqlite", snap)
        res = capture(base / "walsnap", PLAN, S, z, m, InterruptingCamera(c, after=0, hook=hook), seed=1, progress=False,
                      sleep=inst.clock.advance)
        assert res.complete
        # the same again, stopped by Ctrl-C once a few exposures into the points
        res = capture(base / "partial", PLAN, S, z, m, InterruptingCamera(c, after=n_darks() + 3), seed=1,
                      progress=False, sleep=inst.clock.advance)
        assert not res.complete and 0 < res.n_done < len(PLAN)
    finally:
        inst.unregister()
    return base


def copy(sessions, name, tmp_path):
    shutil.copytree(sessions / name, tmp_path / name)
    return tmp_path / name


# -- 1. the lock before anything is written -------------------------------------------------------

def test_second_capture_meets_the_lock_before_writing(tmp_path, monkeypatch):
    """Two captures into one folder: the loser must not touch what the winner wrote."""
    folder = tmp_path / "D"
    winner = b'# the winner\'s session\n[session]\nseed = 1\n'
    real = capture_mod.Bench

    class Racing(real):                      # while the loser opens its ports, the winner starts
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            folder.mkdir()
            self.lock = SessionLock(folder).__enter__()
            (folder / "session.toml").write_bytes(winner)
    monkeypatch.setattr(capture_mod, "Bench", Racing)
    inst = instrument()
    try:
        with pytest.raises(SessionError) as e:
            capture(folder, PLAN, S, *urls(inst), seed=2, progress=False, sleep=inst.clock.advance)
    finally:
        inst.unregister()
    one_line(e)
    assert "in use by another capture" in str(e.value) or "already holds a session" in str(e.value)
    assert (folder / "session.toml").read_bytes() == winner
    assert sorted(p.name for p in folder.iterdir()) == [".lock", "session.toml"]


def test_two_captures_started_together_one_wins(tmp_path):
    """The real race, in two processes: exactly one session, and it is the winner's."""
    import subprocess
    import sys

    folder = tmp_path / "D"
    plan = tmp_path / "p.csv"
    plan.write_text("theta_i,phi_i,theta_o,phi_o\n30,0,40,180\n20,0,50,90\n")
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    cmds = [[sys.executable, "-m", "gonio.cli.main", "capture", "--sim", "--plan", p, "--seed", str(s),
             "--out", str(folder), "--quiet"] for p, s in ((str(plan), 1), ("quick", 2))]
    procs = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for c in cmds]
    outs = [p.communicate(timeout=300) for p in procs]
    rcs = [p.returncode for p in procs]
    assert sorted(rcs) == [0, 2], (rcs, outs)
    loser = outs[rcs.index(2)][1].strip().splitlines()
    assert len(loser) == 1 and ("in use by another capture" in loser[0] or "already holds a session" in loser[0])
    seed = 1 if rcs[0] == 0 else 2
    n = 2 if seed == 1 else 30
    doc = Journal(folder / "journal.sqlite").session_record()
    assert json.loads(doc["doc"])["session"]["seed"] == seed
    assert idx_rows(folder) == list(range(n))
    ds = export(folder)
    import xarray as xr
    with xr.open_dataset(ds, engine="h5netcdf") as d:
        assert int(d.attrs["seed"]) == seed and d.sizes["point"] == n and int(d.attrs["complete"]) == 1


# -- 2. session.toml as journalled ----------------------------------------------------------------

def _edit(folder, fn):
    import tomllib

    from gonio.bench.session.journal import dumps_toml
    doc = tomllib.loads((folder / "session.toml").read_text())
    fn(doc)
    (folder / "session.toml").write_text(dumps_toml(doc))


def _pose(doc):
    doc["plan"]["points"][1][2] = 55.0


def _seed(doc):
    doc["session"]["seed"] = 7


def _shorter(doc):
    doc["plan"]["points"].pop()


def _longer(doc):
    doc["plan"]["points"].append([25.0, 0.0, 35.0, 180.0])


def _dup_order(doc):
    doc["order"]["order"][1] = doc["order"]["order"][0]


def _no_ports(doc):
    del doc["ports"]


def _settings(doc):
    doc["settings"]["capture"]["exposure_max_s"] = 2.0


def _stage(doc):
    doc["order"]["stage_deg"][2][0] += 1.0


@pytest.mark.parametrize("edit, says", [
    (_pose, "plan point 1 is [20.0, 0.0, 55.0, 90.0] instead of [20.0, 0.0, 50.0, 90.0]"),
    (_seed, "its seed is 7 instead of 1"),
    (_shorter, "its plan has 4 points instead of 5 (shorter)"),
    (_longer, "its plan has 6 points instead of 5 (longer)"),
    (_dup_order, "its order lists point"),
    (_no_ports, "its [ports] table is missing"),
    (_settings, "settings.capture.exposure_max_s is 2.0 instead of"),
    (_stage, "the stage pose of point 2 is"),
])
def test_changed_session_toml_is_refused_with_what_differs(sessions, tmp_path, edit, says):
    folder = copy(sessions, "partial", tmp_path)
    before, done = raw_hashes(folder), idx_rows(folder)
    _edit(folder, edit)
    with pytest.raises(SessionError) as e:
        resume_on(folder)
    one_line(e, "session.toml was changed after the session started", says, "--restore-session")
    assert raw_hashes(folder) == before and idx_rows(folder) == done        # nothing measured, nothing written
    with pytest.raises(SessionError) as e:                                   # nor exported as if it were so
        export(folder)
    one_line(e, says)


def test_comment_or_garbage_in_session_toml_then_restore(sessions, tmp_path):
    folder = copy(sessions, "partial", tmp_path)
    original = (folder / "session.toml").read_bytes()
    (folder / "session.toml").write_bytes(original + b"# a note\n")
    with pytest.raises(SessionError) as e:
        resume_on(folder)
    one_line(e, "formatting or comments only")
    (folder / "session.toml").write_bytes(b"\xff\xfe garbage [[[")
    with pytest.raises(SessionError) as e:
        resume_on(folder)
    one_line(e, "no longer valid TOML", "--restore-session")
    from gonio.bench.session.integrity import restore_session
    line = restore_session(folder)
    assert "restored" in line and (folder / "session.toml").read_bytes() == original
    assert any(p.name.startswith("session.toml.changed-") for p in folder.iterdir())
    res = resume_on(folder)
    assert res.complete and idx_rows(folder) == list(range(len(PLAN)))


def test_session_toml_is_written_once(tmp_path):
    from gonio.bench.session.journal import write_session
    write_session(tmp_path / "s", {"a": 1})
    with pytest.raises(SessionError, match="already holds a session"):
        write_session(tmp_path / "s", {"a": 2})
    assert (tmp_path / "s" / "session.toml").read_text().strip() == "a = 1"


def test_session_toml_is_written_once_without_hard_links(tmp_path, monkeypatch):
    from gonio.core import files as _files
    from gonio.bench.session.journal import write_session

    def no_links(*a):
        raise PermissionError(1, "Operation not permitted")
    monkeypatch.setattr(_files.os, "link", no_links)
    write_session(tmp_path / "s", {"a": 1})
    with pytest.raises(SessionError, match="already holds a session"):
        write_session(tmp_path / "s", {"a": 2})
    assert (tmp_path / "s" / "session.toml").read_text().strip() == "a = 1"
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["raw", "session.toml"]


# -- 3. the journal is the only record of what is done ---------------------------------------------

def _drop_journal(folder):
    for s in ("", "-wal", "-shm"):
        p = folder / f"journal.sqlite{s}"
        if p.exists():
            p.unlink()


def test_missing_journal_next_to_raw_files_is_refused_then_rebuilt(sessions, tmp_path):
    folder = copy(sessions, "partial", tmp_path)
    before = raw_hashes(folder)
    _drop_journal(folder)
    with pytest.raises(SessionError) as e:
        resume_on(folder)
    one_line(e, "journal.sqlite is missing", f"raw/ holds {len(before)} RAW file(s)",
             f"gonio capture --resume {folder} --rebuild-journal")
    assert raw_hashes(folder) == before and not (folder / "journal.sqlite").exists()
    with pytest.raises(SessionError, match="--rebuild-journal"):
        export(folder)
    notes = []
    res = resume_on(folder, rebuild_journal=True, notify=notes.append)
    assert res.complete and res.n_new == len(PLAN)
    assert notes[0].startswith("rebuilt the journal: 0 point(s) recovered") and "no old journal" in notes[0]
    after = raw_hashes(folder)
    assert all(after[k] == v for k, v in before.items())                    # no RAW file overwritten
    assert idx_rows(folder) == list(range(len(PLAN)))


def test_emptied_journal_is_refused(sessions, tmp_path):
    folder = copy(sessions, "partial", tmp_path)
    _drop_journal(folder)
    (folder / "journal.sqlite").write_bytes(b"")
    with pytest.raises(SessionError) as e:
        resume_on(folder)
    one_line(e, "journal.sqlite is empty", "--rebuild-journal")


def test_truncated_journal_is_refused_by_export_and_resume_then_rebuilt(sessions, tmp_path):
    folder = copy(sessions, "complete", tmp_path)
    before = raw_hashes(folder)
    j = folder / "journal.sqlite"
    data = j.read_bytes()
    j.write_bytes(data[: len(data) // 2])
    for call in (export, resume_on):
        with pytest.raises(SessionError) as e:
            call(folder)
        one_line(e, "journal.sqlite", "--rebuild-journal")
    assert not (folder / "dataset.nc").exists()
    notes = []
    res = resume_on(folder, rebuild_journal=True, notify=notes.append)
    assert res.complete and idx_rows(folder) == list(range(len(PLAN)))
    assert "rebuilt the journal" in notes[0] and "journal.sqlite.damaged-" in notes[0]
    assert any(p.name.startswith("journal.sqlite.damaged-") for p in folder.iterdir())
    after = raw_hashes(folder)
    assert all(after[k] == v for k, v in before.items())
    export(folder)


def test_lost_wal_is_refused_then_rebuilt(sessions, tmp_path):
    """journal.sqlite as it was on disk mid-run (its last commits only in the -wal), the -wal gone."""
    folder = copy(sessions, "walsnap", tmp_path)
    before = raw_hashes(folder)
    _drop_journal(folder)
    shutil.copyfile(sessions / "snap.sqlite", folder / "journal.sqlite")
    with pytest.raises(SessionError) as e:
        resume_on(folder)
    one_line(e, "--rebuild-journal")
    res = resume_on(folder, rebuild_journal=True)
    assert res.complete and idx_rows(folder) == list(range(len(PLAN)))
    after = raw_hashes(folder)
    assert all(after[k] == v for k, v in before.items())


def test_rebuild_keeps_points_whose_raw_files_verify(sessions, tmp_path):
    """A journal that is readable but lost its session record: the points survive a rebuild."""
    folder = copy(sessions, "partial", tmp_path)
    done = idx_rows(folder)
    db = sqlite3.connect(folder / "journal.sqlite")
    db.execute("DELETE FROM session")
    db.commit()
    db.close()
    with pytest.raises(SessionError, match="has no session record"):
        resume_on(folder)
    notes = []
    res = resume_on(folder, rebuild_journal=True, notify=notes.append)
    assert notes[0].startswith(f"rebuilt the journal: {len(done)} point(s) recovered")
    assert res.complete and res.n_new == len(PLAN) - len(done)
    with pytest.raises(SessionError, match="nothing to rebuild"):
        resume_on(folder, rebuild_journal=True)


def test_raw_files_are_never_overwritten(sessions, tmp_path):
    """A RAW file the journal does not know (e.g. left by a kill) keeps its bytes: new names are fresh."""
    folder = copy(sessions, "partial", tmp_path)
    missing = sorted(set(range(len(PLAN))) - set(idx_rows(folder)))
    # every name an exposure of a missing point would have had before (one per rung)
    planted = [f"raw/p{k:05d}_{t * 1e6:010.0f}us.dng" for k in missing
               for t in ladder(S["capture"]["exposure_min_s"], S["capture"]["exposure_max_s"])]
    with Journal(folder / "journal.sqlite") as j:
        j.reserve_all(planted)
    for f in planted:
        (folder / f).write_bytes(b"an operator's file")
    res = resume_on(folder)
    assert res.complete
    assert all((folder / f).read_bytes() == b"an operator's file" for f in planted)
    with Journal(folder / "journal.sqlite") as j:
        used = {e["file"] for r in j.points() for e in r["detail"]["exposures"]}
    assert not used & set(planted)


# -- 4. lost or corrupt RAW files are measured again ----------------------------------------------

def test_lost_and_corrupt_raw_files_are_measured_again(sessions, tmp_path):
    folder = copy(sessions, "complete", tmp_path)
    rows = Journal(folder / "journal.sqlite").points()
    lost = folder / rows[1]["detail"]["exposures"][0]["file"]
    bad = folder / rows[3]["detail"]["exposures"][-1]["file"]
    lost.unlink()
    bad.write_bytes(bad.read_bytes()[:-7] + b"garbage")
    notes = []
    res = resume_on(folder, notify=notes.append)
    assert notes == [f"measuring again 2 point(s) whose RAW files are missing or corrupt: 1, 3 "
                     f"(first file: {rows[1]['detail']['exposures'][0]['file']})"]
    assert res.complete and res.n_new == 2 and res.notes == notes
    assert idx_rows(folder) == list(range(len(PLAN)))
    db = sqlite3.connect(folder / "journal.sqlite")
    assert sorted(r[0] for r in db.execute("SELECT idx FROM superseded")) == [1, 3]
    assert resume_on(folder).n_new == 0                                  # whole again
    export(folder)


def test_lost_dark_frame_is_taken_again(sessions, tmp_path):
    folder = copy(sessions, "partial", tmp_path)
    with Journal(folder / "journal.sqlite") as j:
        name, (_, file, _) = next(iter(j.frames("dark").items()))
    (folder / file).unlink()
    notes = []
    res = resume_on(folder, notify=notes.append)
    assert res.complete and notes[0].startswith("1 calibration frame(s) are missing or corrupt")
    with Journal(folder / "journal.sqlite") as j:
        assert len(j.frames("dark")) == n_darks() and (folder / j.frames("dark")[name][1]).is_file()


def test_remeasure_points_on_request(sessions, tmp_path):
    folder = copy(sessions, "complete", tmp_path)
    notes = []
    res = resume_on(folder, remeasure="0,2-3", notify=notes.append)
    assert notes == ["measuring again 3 point(s) as asked (3 had been measured)"]
    assert res.complete and res.n_new == 3 and idx_rows(folder) == list(range(len(PLAN)))
    for spec in ("9", "x", "3-1", "-1"):
        with pytest.raises(SessionError) as e:
            resume_on(folder, remeasure=spec)
        one_line(e, "--remeasure")


# -- 5. plans hold each point once, whatever their format -----------------------------------------

def test_duplicate_points_are_dropped_the_same_way_in_every_format(tmp_path):
    csv = tmp_path / "p.csv"
    csv.write_text("theta_i,phi_i,theta_o,phi_o\n30,0,40,180\n20,0,50,90\n30,0,40,180\n30,360,40,-180\n")
    toml = tmp_path / "p.toml"
    toml.write_text("points = [[30, 0, 40, 180], [20, 0, 50, 90], [30, 0, 40, 180], [30, 360, 40, -180]]\n")
    a, b = plans.load_plan(csv), plans.load_plan(toml)
    c = plans.Plan("direct", [[30, 0, 40, 180], [20, 0, 50, 90], [30, 0, 40, 180]])
    for p in (a, b, c):
        assert len(p) == 2 and p.duplicates >= 1
        assert np.array_equal(p.angles, a.angles)
    assert "repeated point(s) in the plan dropped" in plans.dry_run(a, S).summary()


def test_csv_plan_with_a_duplicate_row_captures_and_resumes(tmp_path):
    csv = tmp_path / "p.csv"
    csv.write_text("theta_i,phi_i,theta_o,phi_o\n30,0,40,180\n30,0,40,180\n20,0,50,90\n")
    inst = instrument()
    try:
        z, m, c = urls(inst)
        res = capture(tmp_path / "s", plans.load_plan(csv), S, z, m, c, seed=1, progress=False,
                      sleep=inst.clock.advance)
    finally:
        inst.unregister()
    assert res.complete and res.n_points == 2
    assert resume_on(tmp_path / "s").complete
    assert idx_rows(tmp_path / "s") == [0, 1]
