"""The CLI talks while it works, on a terminal only (issue 41).

On a pseudo-terminal of 80 columns a long step (``fit`` over several candidates, ``calibrate``,
``capture``) draws a bar with its steps and its time; piped, the same command writes nothing but
its results (no bar, no escape sequence, no status line), and ``--quiet`` silences the bar on a
terminal too. `gonio.cli.progress.Steps` itself: the count and time keep their width at 80
columns whatever the label, a new phase (renders after fits) restarts the count, a step that
never reports shows the time it has taken.
"""

from __future__ import annotations

import io
import re
import subprocess
import sys

import pytest

import report_folder
from pty_run import frames, run_in_pty

GONIO = [sys.executable, "-m", "gonio.cli.main"]
BAR = "━"


def _console(width=80):
    from rich.console import Console

    return Console(width=width, file=io.StringIO(), force_terminal=True, color_system=None)


def test_steps_keeps_count_and_time_at_80_columns_and_restarts_per_phase():
    from gonio.cli.progress import Steps

    console = _console()
    with Steps("fit", console=console) as progress:
        progress(3, 9, "roughplastic beckmann with a label far too long to fit the line " * 2)
        progress._p.refresh()
        task = progress._p.tasks[0]
        assert (task.completed, task.total) == (3, 9)
        progress(0, 4, "rendering the reference in product-shot")     # a new phase: its own count
        assert (task.completed, task.total) == (0, 4)
        progress(1, 4, "rendering diffuse")
        progress._p.refresh()
        progress(0, None, "fitting the fallback")                       # no count: the time taken
        assert task.total is None
        progress._p.refresh()
    lines = frames(console.file.getvalue())                   # each redraw of the bar
    assert any("3/9" in line for line in lines) and any("1/4" in line for line in lines), text
    assert any(" in" in line for line in lines) and max(map(len, lines)) <= 80, text
    assert any("…" in line and "fit: roughplastic" in line for line in lines)     # the label gives way
    text = "\n".join(lines)


def test_steps_does_nothing_off_a_terminal():
    from gonio.cli.progress import Steps

    with Steps("fit", stream=io.StringIO()) as progress:
        progress(1, 2, "x")
        assert progress._p is None
    with Steps("fit", enabled=False, console=_console()) as progress:
        assert progress._p is None


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("progress") / "d.nc"
    report_folder._dataset(path, n=40)
    return path


def _fits_80(screen):
    shown = frames(screen)
    return all(len(f.rstrip()) <= 80 for f in shown), [f for f in shown if len(f.rstrip()) > 80]


def test_fit_bar_on_a_terminal_nothing_in_a_pipe(dataset, tmp_path):
    """`gonio fit --model roughplastic` fits both distributions: the bar counts them. Every
    line on the terminal fits 80 columns (the output names are short: a path longer than the
    terminal cannot fit)."""
    argv = [*GONIO, "fit", str(dataset), "--model", "roughplastic", "--out"]
    rc, screen = run_in_pty([*argv, "a.json"], cwd=tmp_path)
    assert rc == 0, screen[-2000:]
    bars = [f for f in frames(screen) if BAR in f]
    assert any("fit roughplastic" in f and "/2" in f for f in bars), screen[-3000:]
    fits, wide = _fits_80(screen)
    assert fits, wide
    assert "wrote a.json" in screen and "\x1b[?25h" in screen            # the cursor shown again at the end

    piped = subprocess.run([*argv, "b.json"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert piped.returncode == 0, piped.stderr[-2000:]
    for stream in (piped.stdout, piped.stderr):
        assert BAR not in stream and "\x1b[" not in stream and "fit roughplastic:" not in stream
    assert "wrote b.json" in piped.stdout

    rc, quiet = run_in_pty([*argv, "c.json", "--quiet"], cwd=tmp_path)
    assert rc == 0 and BAR not in quiet and "wrote c.json" in quiet


@pytest.mark.slow
def test_capture_and_calibrate_bars_on_a_terminal_nothing_in_a_pipe(tmp_path):
    (tmp_path / "two.toml").write_text('name = "two"\npoints = [[30, 0, 20, 180], [30, 0, 40, 180]]\n')
    capture = [*GONIO, "capture", "--sim", "--plan", "two.toml", "--out"]
    rc, screen = run_in_pty([*capture, "s1"], cwd=tmp_path)
    assert rc == 0, screen[-2000:]
    shown = frames(screen)
    assert any("capture" in f and BAR in f and "2/2" in f for f in shown), screen[-3000:]
    # the status line before the points: its last phase, which the status draws as it stops (the
    # earlier ones, dark and flat frames, last less than a refresh on an idle machine)
    assert any("capture: lamp on, reading the source monitor" in f for f in shown), screen[-3000:]
    fits, wide = _fits_80(screen)
    assert fits, wide

    piped = subprocess.run([*capture, "s2"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert piped.returncode == 0 and piped.stderr == "", piped.stderr[-2000:]
    assert BAR not in piped.stdout and piped.stdout.startswith("session s2: 2/2 points")

    calibrate = [*GONIO, "calibrate", "--sim", "--out"]
    rc, screen = run_in_pty([*calibrate, "c1.toml"], cwd=tmp_path)
    assert rc == 0, screen[-2000:]
    shown = frames(screen)
    assert any("calibrate" in f and BAR in f and "/11" in f and "left" in f for f in shown), screen[-3000:]
    fits, wide = _fits_80(screen)
    assert fits, wide
    assert any(f.startswith("wrote c1.toml: yaw zero") for f in shown)   # the result, wrapped on the terminal
    piped = subprocess.run([*calibrate, "c2.toml"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert piped.returncode == 0 and piped.stderr == "" and BAR not in piped.stdout
    assert len(piped.stdout.splitlines()) == 1 and piped.stdout.startswith("wrote c2.toml: yaw zero")   # one line
