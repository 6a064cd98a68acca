"""Files a user gives, read as hostile (issue 36, probes 5 and 6): a FIFO or a device where a
file is wanted, TOML nested thousands deep, integers of thousands of digits or beyond int64,
a seed beyond 2**63. Each is one line and exit status 2, before anything is written; none
hangs (a FIFO opened for reading blocks until a writer comes: each call runs in a thread
with a deadline, and the FIFO is released if it was opened)."""

from __future__ import annotations

import os
import threading

import pytest

from gonio.cli.main import main
from gonio.core.errors import GonioError, PlanError

NESTED = "a = " + "[" * 5000 + "]" * 5000 + "\n"
DIGITS = "[capture]\nexposure = " + "9" * 5000 + "\n"
INT128 = "[capture]\nexposure = " + "9" * 30 + "\n"


def gonio(capsys, *args, deadline=60.0, release=None):
    """``gonio ARGS`` in a thread: (status, stderr lines); fails if it is still running at the deadline."""
    out = {}

    def run():
        try:
            out["rc"] = main([str(a) for a in args])
        except SystemExit as exc:       # argparse's refusals exit 2 themselves
            out["rc"] = exc.code
    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(deadline)
    if t.is_alive():
        if release is not None:         # let the blocked open return, so the thread ends
            fd = os.open(release, os.O_WRONLY | os.O_NONBLOCK)
            os.close(fd)
        pytest.fail(f"gonio {' '.join(map(str, args))} still ran after {deadline} s")
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    return out.get("rc"), err


def refused(capsys, *args, needle, release=None):
    rc, err = gonio(capsys, *args, release=release)
    assert rc == 2 and len(err) == 1 and err[0].startswith("gonio: error:"), (rc, err)
    assert needle in err[0], err[0]


@pytest.fixture
def fifo(tmp_path):
    def make(name):
        path = tmp_path / name
        os.mkfifo(path)
        return path
    return make


def test_a_fifo_or_a_device_where_a_file_is_wanted_is_refused(capsys, tmp_path, fifo):
    out = tmp_path / "out"
    for name, args in [("d.nc", ["fit", "{}", "--model", "diffuse", "--out", out / "f.json"]),
                       ("d2.nc", ["convert", "{}", "--to", "csv", "--out", out / "d.csv"]),
                       ("s.toml", ["capture", "--sim", "--plan", "quick", "--sample", "{}", "--out", out / "s"]),
                       ("p.toml", ["capture", "--sim", "--plan", "{}", "--out", out / "s"]),
                       ("set.toml", ["settings", "show", "--settings", "{}"])]:
        path = fifo(name)
        refused(capsys, *[str(path) if a == "{}" else a for a in args], needle="not a regular file", release=path)
    refused(capsys, "fit", "/dev/zero", "--model", "diffuse", "--out", out / "f.json", needle="not a regular file")
    assert not out.exists()


@pytest.mark.parametrize("text,needle", [(NESTED, "deep"), (DIGITS, "digits"), (INT128, "2**63 - 1")],
                         ids=["nested-5000", "5000-digits", "30-digits"])
def test_toml_beyond_any_gonio_input_is_one_line(capsys, tmp_path, text, needle):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    refused(capsys, "settings", "show", "--settings", path, needle=needle)
    refused(capsys, "capture", "--sim", "--plan", "quick", "--sample", path, "--out", tmp_path / "s", needle=needle)
    refused(capsys, "capture", "--sim", "--plan", path, "--out", tmp_path / "s", needle=needle)
    refused(capsys, "capture", "--sim", "--plan", "quick", "--settings", path, "--out", tmp_path / "s",
            needle=needle)
    assert not (tmp_path / "s").exists()


def test_the_readers_raise_the_projects_one_line_errors(tmp_path):
    """The library's readers (what the commands call): GonioError, or PlanError for a plan."""
    from gonio.bench.calibrate import read_calibration
    from gonio.bench.plan.plans import load_plan
    from gonio.sim.physics.faults import FaultSchedule

    path = tmp_path / "bad.toml"
    path.write_text(NESTED)
    with pytest.raises(PlanError, match="deep"):
        load_plan(path)
    with pytest.raises(GonioError, match="not a calibration TOML file .*deep"):
        read_calibration(path)
    with pytest.raises(GonioError, match="deep"):
        FaultSchedule.from_toml(path)
    with pytest.raises(GonioError, match="digits"):
        FaultSchedule.from_toml(DIGITS)


def test_a_seed_beyond_int64_is_refused_by_every_command(capsys, tmp_path):
    """`capture --seed 2**80` was accepted, and `export` then failed with a TypeError."""
    big = str(2 ** 80)
    for args in (["capture", "--sim", "--plan", "quick", "--out", tmp_path / "s", "--seed", big],
                 ["calibrate", "--sim", "--out", tmp_path / "c.toml", "--seed", big],
                 ["demo", "--out", tmp_path / "d", "--seed", big]):
        refused(capsys, *args, needle="--seed")
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("alpha", [1e300, -0.5])
def test_a_fit_file_with_values_outside_their_bounds_is_one_line(capsys, tmp_path, alpha):
    """A fit.json edited to alpha 1e300 or -0.5: convert, render and report ended in a traceback
    (the model's bound check, deep inside); now the reader refuses it, naming the value."""
    import json

    from gonio.core.atomic import atomic_open

    doc = {"format": "gonio-fit/1", "model": {"name": "roughconductor", "options": {"distribution": "ggx"}},
           "params": {"alpha": alpha, "eta": [0.2, 0.4, 1.5], "k": [3.0, 2.5, 1.9]}}
    from gonio.fitting.formats.fitfile import FIT_FORMAT

    doc["format"] = FIT_FORMAT
    fit = tmp_path / "fit.json"
    with atomic_open(fit, "w") as fh:
        json.dump(doc, fh)
    from gonio.fitting import load_fit

    with pytest.raises(ValueError, match=r"alpha=.* outside its bounds"):
        load_fit(fit)
    refused(capsys, "convert", fit, "--to", "mitsuba-xml", "--out", tmp_path / "o.xml", needle="outside its bounds")
    assert not (tmp_path / "o.xml").exists()
