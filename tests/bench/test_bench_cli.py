"""The command line: every bad input gets one line on stderr, exit status 2, nothing written.

Each case runs the real ``gonio`` console script in its own process, as a user would.
"""

import os
import subprocess
import sys


GONIO = [sys.executable, "-m", "gonio.cli.main"]


def run(*args, cwd=None, timeout=120):
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run(GONIO + list(args), capture_output=True, text=True, cwd=cwd, timeout=timeout, env=env)


def assert_one_line_error(proc, *needles):
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("gonio: error:"), lines[0]
    assert "Traceback" not in proc.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_version_and_help():
    proc = run("--version")
    assert proc.returncode == 0 and proc.stdout.startswith("gonio ")
    for cmd in (["demo"], ["capture"], ["export"], ["fit"], ["render"], ["report"], ["sim", "serve"], ["estop"]):
        proc = run(*cmd, "--help")
        assert proc.returncode == 0, cmd
        assert "usage: gonio" in proc.stdout


def test_unknown_command_and_missing_flag():
    assert_one_line_error(run("frobnicate"), "invalid choice")
    assert_one_line_error(run("fit", "x.nc"), "--out")


def test_missing_dataset(tmp_path):
    proc = run("fit", str(tmp_path / "nope.nc"), "--out", str(tmp_path / "fit.json"))
    assert_one_line_error(proc, "does not exist")
    assert not (tmp_path / "fit.json").exists()


def test_unknown_preset_and_malformed_plan(tmp_path):
    proc = run("capture", "--sim", "--plan", "nonesuch", "--out", str(tmp_path / "s"))
    assert_one_line_error(proc, "nonesuch")
    bad = tmp_path / "plan.toml"
    bad.write_text("name = 'x'\n[[points\ntheta_i = 10\n")
    proc = run("capture", "--sim", "--plan", str(bad), "--out", str(tmp_path / "s"))
    assert_one_line_error(proc, "TOML")
    assert not (tmp_path / "s").exists()


def test_unreachable_angle(tmp_path):
    plan = tmp_path / "plan.toml"
    # wi == wo: the lamp would sit in front of the camera
    plan.write_text('name = "backscatter"\npoints = [[30.0, 0.0, 30.0, 0.0], [20.0, 0.0, 40.0, 180.0]]\n')
    proc = run("capture", "--sim", "--plan", str(plan), "--out", str(tmp_path / "s"))
    assert_one_line_error(proc)
    assert "unreachable" in proc.stderr.lower() or "camera" in proc.stderr.lower()
    assert not (tmp_path / "s").exists() or not any((tmp_path / "s").iterdir())


def test_unknown_model_and_bad_sample(tmp_path):
    sample = tmp_path / "sample.toml"
    sample.write_text('model = "velvet"\n')
    proc = run("capture", "--sim", "--sample", str(sample), "--plan", "quick", "--out", str(tmp_path / "s"))
    assert_one_line_error(proc, "velvet")
    sample.write_text('model = "diffuse"\n[params]\nreflectance = -0.5\n')
    proc = run("capture", "--sim", "--sample", str(sample), "--plan", "quick", "--out", str(tmp_path / "s"))
    assert_one_line_error(proc, "reflectance")
    assert not (tmp_path / "s").exists()


def test_dead_serial_port(tmp_path):
    proc = run("capture", "--port", "/dev/ttyNOPE0", "--meter-port", "/dev/ttyNOPE1", "--camera", "/dev/ttyNOPE2",
               "--plan", "quick", "--out", str(tmp_path / "s"))
    assert_one_line_error(proc, "/dev/ttyNOPE0")
    assert not (tmp_path / "s" / "session.toml").exists()


def test_fit_rejects_a_non_dataset(tmp_path):
    junk = tmp_path / "junk.nc"
    junk.write_bytes(b"not netcdf at all")
    proc = run("fit", str(junk), "--out", str(tmp_path / "fit.json"))
    assert_one_line_error(proc)
    assert not (tmp_path / "fit.json").exists()


def test_resume_of_a_non_session(tmp_path):
    assert_one_line_error(run("capture", "--resume", str(tmp_path)), "session")


def test_report_needs_a_dataset(tmp_path):
    assert_one_line_error(run("report", str(tmp_path)), "dataset.nc")
