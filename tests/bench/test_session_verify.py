"""Integrity you can verify (issue 36, items 2-3; issue 34's NetCDF writer): every journalled
point carries a checksum checked on export and resume; `gonio verify` says which points are
intact and how to recover; a flipped bit in a stored value is never exported; dataset.nc is
read back before it is written."""

import fcntl
import hashlib
import os
import shutil
import sqlite3

import pytest
import xarray as xr

pytest.importorskip("gonio.sim")

from cli_refusal import gonio, listing, refused
from gonio.bench.dataset import export as export_mod
from gonio.bench.samples import load_sample
from gonio.bench.session import integrity
from gonio.bench.session.journal import Journal, point_checksum
from gonio.bench.session.verify import verify_session
from gonio.cli import main as cli
from gonio.cli.capture import capture_sim
from gonio.core.errors import GonioError, SessionError

_OLD_POINTS = """CREATE TABLE points (idx INTEGER PRIMARY KEY, theta_i REAL, phi_i REAL, theta_o REAL,
phi_o REAL, yaw REAL, tilt REAL, azimuth REAL, lamp REAL, brdf TEXT NOT NULL, brdf_std TEXT NOT NULL,
saturated INTEGER NOT NULL, detail TEXT NOT NULL, finished REAL NOT NULL)"""


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished quick simulated session (30 points); copy before use."""
    root = tmp_path_factory.mktemp("verify")
    capture_sim(root / "session", sample=load_sample(None), plan="quick", seed=1, progress=False)
    return root / "session"


def copy(finished, tmp_path):
    shutil.copytree(finished, tmp_path / "s")
    return tmp_path / "s"


def stored_brdf(folder, idx):
    db = sqlite3.connect(folder / "journal.sqlite")
    try:
        return db.execute("SELECT brdf FROM points WHERE idx = ?", (idx,)).fetchone()[0]
    finally:
        db.close()


def flip_in_brdf(folder, idx):
    """Flip one bit of a digit of point ``idx``'s stored brdf, in the file's bytes (0.1138 -> 0.1038)."""
    text = stored_brdf(folder, idx).encode()
    path = folder / "journal.sqlite"
    data = bytearray(path.read_bytes())
    at = data.find(text)
    assert at > 0 and data.find(text, at + 1) < 0
    digit = at + text.index(b".") + 2
    data[digit] ^= 0x01
    path.write_bytes(bytes(data))
    return digit


def test_checksum_covers_every_stored_value():
    row = (3, 30.0, 0.0, 40.0, 180.0, 1.0, 2.0, 3.0, 4.0, "[0.248, 0.2, 0.1]", "[0.001, 0.001, 0.001]", 0,
           '{"exposures": []}', 1.5e9)
    base = point_checksum(row)
    assert point_checksum([*row[:9], row[9].encode(), *row[10:]]) == base         # text as SQLite's bytes
    assert point_checksum([*row[:1], 30, *row[2:]]) == base                      # a REAL stored as an integer
    for k in range(len(row)):
        changed = list(row)
        changed[k] = changed[k] + (1 if not isinstance(changed[k], str) else "x")
        assert point_checksum(changed) != base, k
    assert point_checksum([*row[:9], "[0.348, 0.2, 0.1]", *row[10:]]) != base   # the 0.248 -> 0.348


def test_flipped_bit_in_a_stored_value_is_damage_everywhere(finished, tmp_path, capsys):
    """One bit of point 1's brdf: verify names it, export and resume refuse it in one line, nothing
    written; the rebuild keeps the other 29 and the resume measures point 1 again."""
    folder = copy(finished, tmp_path)
    before = stored_brdf(folder, 1)
    flip_in_brdf(folder, 1)
    assert stored_brdf(folder, 1) != before
    rc, err = gonio(capsys, "verify", folder)
    assert rc == 1 and not err
    verdict = verify_session(folder)
    assert verdict.intact == [k for k in range(30) if k != 1] and list(verdict.damaged) == [1]
    assert "checksum" in verdict.damaged[1] and "--rebuild-journal" in verdict.lines()[-1]
    files = listing(folder)
    refused(capsys, "export", folder, needles=("point(s) are damaged", "gonio verify", "--rebuild-journal"))
    refused(capsys, "capture", "--resume", folder, needles=("damaged", "--rebuild-journal"))
    assert listing(folder) == files and not (folder / "dataset.nc").exists()
    rc, err = gonio(capsys, "capture", "--resume", folder, "--rebuild-journal", "--quiet")
    assert rc == 0, err
    assert any("29 point(s) recovered" in line and "damaged: 1;" in line for line in err), err
    assert verify_session(folder).ok
    rc, _ = gonio(capsys, "export", folder)
    assert rc == 0
    with xr.open_dataset(folder / "dataset.nc", engine="h5netcdf") as ds:
        assert ds.sizes["point"] == 30


def test_verify_output_names_points_and_recovery(finished, tmp_path, capsys):
    folder = copy(finished, tmp_path)
    rc, _ = gonio(capsys, "verify", folder)
    assert rc == 0
    flip_in_brdf(folder, 7)
    sorted((folder / "raw").glob("p00004_*"))[0].unlink()
    capsys.readouterr()
    rc = cli.main(["verify", str(folder)])
    out = capsys.readouterr().out
    assert rc == 1
    assert "30 point(s) planned: 28 intact, 2 damaged" in out and "damaged: point 7:" in out
    assert "damaged: point 4: its RAW file" in out
    assert f"recover: gonio capture --resume {folder} --rebuild-journal" in out


def test_raw_damage_alone_is_recovered_by_a_plain_resume(finished, tmp_path):
    folder = copy(finished, tmp_path)
    raw = sorted((folder / "raw").glob("p00003_*"))[0]
    raw.write_bytes(raw.read_bytes()[:-1] + b"\0")
    verdict = verify_session(folder)
    assert list(verdict.damaged) == [3] and "RAW file" in verdict.damaged[3]
    assert verdict.recovery() == f"gonio capture --resume {folder}"


@pytest.mark.parametrize("where", ["header", "schema", "points_root"])
def test_damaged_header_schema_or_points_root_loses_no_point(finished, tmp_path, where):
    """The issue's '0 recovered': pages SQLite needs to find anything, read without it."""
    folder = copy(finished, tmp_path)
    with Journal(folder / "journal.sqlite") as j:
        rows = j.points()
        root = j.db.execute("SELECT rootpage, (SELECT page_size FROM pragma_page_size) FROM sqlite_master "
                            "WHERE name = 'points'").fetchone()
    at = {"header": 0, "schema": 100, "points_root": (root[0] - 1) * root[1]}[where]
    path = folder / "journal.sqlite"
    data = bytearray(path.read_bytes())
    data[at] ^= 0x40
    path.write_bytes(bytes(data))
    data_, doc, why = integrity.load_session(folder)
    with pytest.raises(SessionError, match="--rebuild-journal"):
        integrity.open_journal(folder, data_, doc, why, write=False)
    verdict = verify_session(folder)
    assert not verdict.ok and len(verdict.intact) == 30
    line = integrity.rebuild_journal(folder, data_, doc, why)
    assert line.startswith("rebuilt the journal: 30 point(s) recovered"), line
    with Journal(folder / "journal.sqlite") as j:
        assert j.points() == rows


def test_journal_from_before_checksums_is_read_unchecked_then_gets_them(finished, tmp_path, capsys):
    folder = copy(finished, tmp_path)
    db = sqlite3.connect(folder / "journal.sqlite")
    db.executescript(f"ALTER TABLE points RENAME TO p2; {_OLD_POINTS}; INSERT INTO points SELECT idx, theta_i, "
                     "phi_i, theta_o, phi_o, yaw, tilt, azimuth, lamp, brdf, brdf_std, saturated, detail, finished "
                     "FROM p2 WHERE idx != 5; DROP TABLE p2;")
    db.close()
    verdict = verify_session(folder)
    assert verdict.ok and verdict.unchecked == 29 and verdict.missing == [5]
    assert any("before checksums" in line for line in verdict.lines())
    rc, err = gonio(capsys, "capture", "--resume", folder, "--quiet")
    assert rc == 0, err
    db = sqlite3.connect(folder / "journal.sqlite")
    sums = dict(db.execute("SELECT idx, checksum FROM points"))
    db.close()
    assert sums[5] is not None and sum(v is None for v in sums.values()) == 29
    assert verify_session(folder).unchecked == 29


def test_verify_bad_inputs_one_line_exit_2_nothing_written(finished, tmp_path, capsys):
    refused(capsys, "verify", tmp_path / "nowhere", needles=("not a gonio session",))
    (tmp_path / "file").write_text("x")
    refused(capsys, "verify", tmp_path / "file", needles=("not a gonio session",))
    (tmp_path / "empty").mkdir()
    refused(capsys, "verify", tmp_path / "empty", needles=("not a gonio session",))
    assert listing(tmp_path / "empty") == []
    folder = copy(finished, tmp_path)
    files = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.rglob("*") if p.is_file()}
    fd = os.open(folder / ".lock", os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        refused(capsys, "verify", folder, needles=("in use by a capture",))
    finally:
        os.close(fd)
    toml = folder / "session.toml"
    good = toml.read_bytes()
    toml.write_bytes(b"\xff\xfe garbage [[[")
    refused(capsys, "verify", folder, needles=("session.toml", "--restore-session"))
    toml.write_bytes(good)
    rc, _ = gonio(capsys, "verify", folder)
    assert rc == 0
    after = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.rglob("*") if p.is_file()}
    assert after == files                     # verify wrote nothing, not even beside the journal
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        cli.main(["verify"])
    err = capsys.readouterr().err.splitlines()
    assert e.value.code == 2 and len(err) == 1 and "required: session" in err[0]


def test_netcdf_writer_that_loses_a_point_writes_nothing(finished, tmp_path, monkeypatch, capsys):
    """Issue 34: the writer's output is read back; a lost point fails loudly and leaves no file."""
    folder = copy(finished, tmp_path)
    real = export_mod._serialise
    monkeypatch.setattr(export_mod, "_serialise", lambda ds: real(ds.isel(point=slice(1, None))))
    files = listing(folder)
    with pytest.raises(GonioError, match="reads back 29 point"):
        export_mod.export(folder)
    refused(capsys, "export", folder, needles=("was not written", "29 point(s) of the 30"))
    assert listing(folder) == files
    monkeypatch.setattr(export_mod, "_serialise", real)
    export_mod.export(folder)
    old = (folder / "dataset.nc").read_bytes()

    def nudged(ds):                       # same point count, one value changed on the way
        ds = ds.copy(deep=True)
        ds["brdf"].values[3, 1] *= 1.0 + 1e-9
        return real(ds)
    monkeypatch.setattr(export_mod, "_serialise", nudged)
    refused(capsys, "export", folder, needles=("other values of brdf",))
    assert (folder / "dataset.nc").read_bytes() == old
