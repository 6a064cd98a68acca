"""Environment errors and hostile sizes: one line on stderr, exit status 2, checked before the
work starts, and nothing written (no output, no half-written or temporary file).

Runs ``main()`` in this process (the dataset and the fit file are made once per module).
"""

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gonio.core.preflight import check_output_dir, check_output_file
from gonio.core.errors import GonioError

from cli_refusal import gonio, listing, quick_session, refused

RGL = Path("/work/shared/data/rgl/paper_white_rgb.bsdf")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A quick simulated dataset.nc and a diffuse fit of it."""
    return quick_session(tmp_path_factory.mktemp("envdata"))


def _is_unwritable(folder: Path) -> bool:
    try:
        check_output_dir(folder / "probe")
    except GonioError:
        return True
    return False


@pytest.fixture
def unwritable(tmp_path):
    """A folder nobody here can write to (a 0555 folder, or /sys where the tests run as root)."""
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    if _is_unwritable(ro):
        yield ro
    elif _is_unwritable(Path("/sys")):
        yield Path("/sys")
    else:
        pytest.skip("no unwritable folder on this machine")
    ro.chmod(0o755)


@pytest.fixture
def no_fit(monkeypatch):
    """Fail the test if a fit starts: the output must be checked before."""
    import gonio.cli.fit as fr

    def boom(*a, **k):
        raise AssertionError("the fit ran before the output was checked")
    monkeypatch.setattr(fr, "fit_dataset", boom)


# ------------------------------------------------------------------- output checked first
def test_fit_out_unwritable_folder_file_refused_before_fitting(capsys, data, unwritable, tmp_path, no_fit):
    refused(capsys, "fit", data["dataset"], "--model", "diffuse", "--out", unwritable / "fit.json",
            needles=("not writable",))
    (tmp_path / "adir").mkdir()
    refused(capsys, "fit", data["dataset"], "--model", "diffuse", "--out", tmp_path / "adir",
            needles=("is a folder",))
    (tmp_path / "afile").write_text("x")
    refused(capsys, "fit", data["dataset"], "--model", "diffuse", "--out", tmp_path / "afile" / "fit.json",
            needles=("is a file, not a folder",))
    refused(capsys, "fit", data["dataset"], "--model", "diffuse", "--out", "", needles=("--out is empty",))
    refused(capsys, "fit", data["dataset"], "--model", "diffuse", "--out", "/dev/null",
            needles=("not a regular file",))            # a rename would have replaced the device node
    refused(capsys, "fit", tmp_path, "--model", "diffuse", "--out", tmp_path / "x.json", needles=("is a folder",))
    assert listing(tmp_path) == ["adir", "afile", "ro"]


def test_batch_out_and_workers_and_scheduler(capsys, data, unwritable, tmp_path, no_fit):
    ds = data["dataset"]
    refused(capsys, "fit", "--batch", ds, "--model", "diffuse", "--out", unwritable / "b", needles=("not writable",))
    (tmp_path / "f").write_text("x")
    refused(capsys, "fit", "--batch", ds, "--model", "diffuse", "--out", tmp_path / "f", needles=("not a folder",))
    t0 = time.monotonic()
    refused(capsys, "fit", "--batch", ds, "--model", "diffuse", "--out", tmp_path / "b", "--workers", "0",
            needles=("--workers 0",))                   # hung on 15e620e
    refused(capsys, "fit", "--batch", ds, "--model", "diffuse", "--out", tmp_path / "b", "--workers", "100000",
            needles=("--workers",))
    line = refused(capsys, "fit", "--batch", ds, "--model", "diffuse", "--out", tmp_path / "b",
                   "--scheduler", "not a url", needles=("--scheduler",))
    assert "tls://HOST:PORT" in line
    refused(capsys, "fit", "--batch", ds, "--model", "diffuse", "--out", tmp_path / "b", "--loss", "nosuch",
            needles=("unknown loss",))               # a traceback from the workers on 15e620e
    refused(capsys, "fit", "--batch", ds, "--model", "diffuse", "--out", tmp_path / "b", "--dashboard", "x y",
            needles=("--dashboard",))
    assert time.monotonic() - t0 < 10
    assert not (tmp_path / "b").exists()


def test_render_options_checked_before_render_json(capsys, data, unwritable, tmp_path):
    fit, ds = data["fit"], data["dataset"]
    out = tmp_path / "render"
    refused(capsys, "render", fit, "--dataset", ds, "--out", out, "--variant", "nosuch", needles=("--variant",))
    refused(capsys, "render", fit, "--dataset", ds, "--out", out, "--preview", "--size", "0", needles=("--size 0",))
    refused(capsys, "render", fit, "--dataset", ds, "--out", out, "--preview", "--spp", "-1", needles=("--spp -1",))
    refused(capsys, "render", fit, "--dataset", ds, "--out", out, "--preview", "--size", "2048", "--spp", "16384",
            needles=("size^2",))
    garbage = tmp_path / "g.bsdf"
    garbage.write_bytes(b"tensor_file\x00" + os.urandom(300))
    refused(capsys, "render", fit, "--dataset", ds, "--out", out, "--measured", garbage, needles=("g.bsdf",))
    refused(capsys, "render", fit, "--dataset", ds, "--out", unwritable / "r", needles=("not writable",))
    assert not out.exists()


def test_report_and_convert_out(capsys, data, unwritable, tmp_path):
    folder = data["root"]
    refused(capsys, "report", folder, "--out", unwritable / "report.html", needles=("not writable",))
    refused(capsys, "report", folder, "--out", tmp_path, needles=("is a folder",))
    refused(capsys, "convert", data["fit"], "--to", "mitsuba-xml", "--out", unwritable / "x.xml",
            needles=("not writable",))
    refused(capsys, "convert", data["fit"], "--to", "mitsuba-xml", "--out", tmp_path, needles=("is a folder",))
    refused(capsys, "convert", data["dataset"], "--to", "csv", "--out", data["dataset"], needles=("source file",))
    assert listing(tmp_path) == ["ro"]


def test_demo_out_refused_before_capture(capsys, unwritable, tmp_path, monkeypatch):
    import gonio.cli.capture as sr

    monkeypatch.setattr(sr, "capture_sim", lambda *a, **k: pytest.fail("captured before checking --out"))
    refused(capsys, "demo", "--out", unwritable / "demo", "--plan", "quick", needles=("not writable",))
    (tmp_path / "f").write_text("x")
    refused(capsys, "demo", "--out", tmp_path / "f", "--plan", "quick", needles=("not a folder",))
    refused(capsys, "demo", "--out", tmp_path / "d", "--plan", "nosuch", needles=("nosuch",))
    assert listing(tmp_path) == ["f", "ro"]


# ------------------------------------------------------------------- disk full
def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


@pytest.mark.parametrize("to,suffix", [("mitsuba-xml", ".xml"), ("mitsuba-dict", ".json")])
def test_disk_full_while_converting_leaves_nothing(capsys, data, tmp_path, monkeypatch, to, suffix):
    import gonio.core.atomic as io

    monkeypatch.setattr(io.os, "fsync", _enospc)
    out = tmp_path / "out" / f"x{suffix}"
    line = refused(capsys, "convert", data["fit"], "--to", to, "--out", out, needles=("full", str(out)))
    assert "No space left on device" in line
    assert listing(tmp_path / "out") == []            # 15e620e left a 0-byte .tmp-x.xml


def test_disk_full_while_writing_the_fit(capsys, data, tmp_path, monkeypatch):
    import gonio.core.atomic as io

    monkeypatch.setattr(io.os, "fsync", _enospc)
    refused(capsys, "fit", data["dataset"], "--model", "diffuse", "--out", tmp_path / "fit.json",
            needles=("full", "fit.json"))
    assert listing(tmp_path) == []


def test_too_little_free_space_is_refused_up_front(capsys, data, tmp_path, monkeypatch):
    import shutil

    import gonio.core.preflight as pf

    real = shutil.disk_usage
    monkeypatch.setattr(pf.shutil, "disk_usage", lambda p: real(p)._replace(free=2 ** 20))
    refused(capsys, "convert", data["fit"], "--to", "merl", "--out", tmp_path / "x.binary",
            needles=("not enough space", "MiB free"))
    refused(capsys, "demo", "--out", tmp_path / "demo", "--plan", "quick", needles=("not enough space",))
    assert listing(tmp_path) == []


# ------------------------------------------------------------------- garbage inputs
def test_binary_garbage_where_text_is_expected(capsys, tmp_path):
    g = tmp_path / "g"
    g.mkdir()
    for name in ("s.toml", "set.toml", "p.toml", "p.csv", "f.json"):
        (g / name).write_bytes(b"\xff\xfe\x80" + os.urandom(200))
    out = tmp_path / "session"
    refused(capsys, "capture", "--sim", "--sample", g / "s.toml", "--plan", "quick", "--out", out, "--quiet",
            needles=("UTF-8",))
    refused(capsys, "capture", "--sim", "--settings", g / "set.toml", "--plan", "quick", "--out", out, "--quiet",
            needles=("UTF-8",))
    refused(capsys, "capture", "--sim", "--plan", g / "p.toml", "--out", out, "--quiet", needles=("UTF-8",))
    refused(capsys, "capture", "--sim", "--plan", g / "p.csv", "--out", out, "--quiet", needles=("UTF-8",))
    refused(capsys, "sim", "serve", "--sample", g / "s.toml", "--clock", "instant", needles=("UTF-8",))
    refused(capsys, "convert", g / "f.json", "--to", "mitsuba-xml", "--out", tmp_path / "x.xml")
    assert not out.exists() and not (tmp_path / "x.xml").exists()


def test_garbage_and_truncated_rgl_files(capsys, tmp_path):
    bad = tmp_path / "garbage.bsdf"
    bad.write_bytes(b"tensor_file\x00\x01\x00" + os.urandom(2000))
    refused(capsys, "fit", bad, "--model", "diffuse", "--out", tmp_path / "f.json", needles=("garbage.bsdf",))
    if RGL.exists():
        cut = tmp_path / "cut.bsdf"
        cut.write_bytes(RGL.read_bytes()[:100_000])
        refused(capsys, "fit", cut, "--model", "diffuse", "--out", tmp_path / "f.json", needles=("truncated",))
        refused(capsys, "capture", "--sim", "--sample", cut, "--plan", "quick", "--out", tmp_path / "s", "--quiet",
                needles=("truncated",))
    assert not (tmp_path / "f.json").exists() and not (tmp_path / "s").exists()


def test_non_ascii_paths_work(capsys, data, tmp_path):
    folder = tmp_path / "données ü"
    folder.mkdir()
    ds = folder / "jeu é.nc"
    ds.write_bytes(Path(data["dataset"]).read_bytes())
    rc, err = gonio(capsys, "fit", ds, "--model", "diffuse", "--out", folder / "résultat" / "fit ø.json")
    assert rc == 0, err
    assert (folder / "résultat" / "fit ø.json").exists()


# ------------------------------------------------------------------- hostile sizes and values
def test_sizes_and_values_bounded(capsys, tmp_path):
    huge = tmp_path / "huge.toml"
    huge.write_text('name = "huge"\n[[scan]]\nkind = "hemisphere"\ntheta_i = [30]\nn = 1000000000000\n')
    t0 = time.monotonic()
    refused(capsys, "capture", "--sim", "--plan", huge, "--dry-run", "--out", tmp_path / "s", needles=("1000000000000",))
    rows = "\n".join(f"{10 + (k % 70)},0,{(k * 7) % 80},{k % 360 - 180}.5" for k in range(10_000))
    big = tmp_path / "big.csv"
    big.write_text("theta_i,phi_i,theta_o,phi_o\n" + rows + "\n")
    refused(capsys, "capture", "--sim", "--plan", big, "--dry-run", "--out", tmp_path / "s", needles=("MiB", "4000"))
    assert time.monotonic() - t0 < 20
    refused(capsys, "sim", "serve", "--clock", "-1", needles=("--clock",))
    refused(capsys, "sim", "serve", "--clock", "inf", needles=("--clock",))
    refused(capsys, "bench", "models", "-n", "0", needles=("-n 0",))


# ------------------------------------------------------------------- sim serve cleans up
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_sim_serve_removes_its_temporary_folder(tmp_path, sig):
    env = dict(os.environ, TMPDIR=str(tmp_path), PYTHONWARNINGS="ignore")
    proc = subprocess.Popen([sys.executable, "-m", "gonio.cli.main", "sim", "serve", "--clock", "instant"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        seen = []
        deadline = time.monotonic() + 90
        while not any(line.startswith("camera ") for line in seen) and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            seen.append(line)
        assert any(line.startswith("camera ") for line in seen), seen
        made = [p.name for p in tmp_path.iterdir() if p.name.startswith("gonio-sim-")]
        assert len(made) == 1
        proc.send_signal(sig)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "Traceback" not in proc.stderr.read()
    assert proc.returncode == 0
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("gonio-sim-")] == []


def test_check_helpers_directly(tmp_path):
    assert check_output_file(tmp_path / "new" / "deeper" / "x.json") == tmp_path / "new" / "deeper" / "x.json"
    assert not (tmp_path / "new").exists()          # a check creates nothing
    with pytest.raises(GonioError, match="NUL"):
        check_output_file(str(tmp_path / "a\x00b"))
    with pytest.raises(GonioError, match="255 bytes"):
        check_output_dir(tmp_path / ("x" * 300))
    with pytest.raises(GonioError, match="not a file name"):
        check_output_file(tmp_path / "..")


def test_disk_full_while_writing_a_preview_image(capsys, data, tmp_path, monkeypatch):
    import matplotlib.image as mpimg

    def half_then_full(fname, *a, **k):
        with open(fname, "wb") as fh:
            fh.write(b"\x89PNG half")
        raise OSError(errno.ENOSPC, "No space left on device", str(fname))
    monkeypatch.setattr(mpimg, "imsave", half_then_full)
    out = tmp_path / "render"
    refused(capsys, "render", data["fit"], "--dataset", data["dataset"], "--out", out, "--preview",
            "--size", "16", "--spp", "1", needles=("full",))
    left = [p.name for p in (out / "preview").iterdir()] if (out / "preview").exists() else []
    assert not [n for n in left if n.endswith(".png") or ".tmp" in n], left


def test_capture_into_a_non_ascii_folder(capsys, tmp_path):
    """The simulated camera read its command line as ASCII: 'no such directory' and a dead session."""
    plan = tmp_path / "one.toml"
    plan.write_text('name = "one"\npoints = [[30, 0, 30, 180]]\n')
    out = tmp_path / "séance ü" / "s"
    rc, err = gonio(capsys, "capture", "--sim", "--plan", plan, "--out", out, "--quiet")
    assert rc == 0, err
    assert any(p.suffix == ".dng" for p in (out / "raw").iterdir())
