"""The CLI says what exists and how to call it, in 80 columns (issue 41).

Every command's help (all of them, walked from the parser, `gonio estop`'s own parser too) is at
most 80 columns wide whatever the terminal, and shows examples that the real parser accepts;
``gonio models`` and ``gonio plans`` list the model catalogue, the example samples, the plan and
error presets from where they are declared; ``gonio settings show`` prints each value's unit;
an error is one line in a pipe and wrapped to the terminal's width on one.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys

import pytest

from gonio.cli.main import build_parser, main, walk_parsers

WIDTH = 80


def _parsers():
    return list(walk_parsers(build_parser()))


def _examples(text: str) -> list[str]:
    """The example commands of a help text (continuation lines joined)."""
    lines = text.split("examples:\n", 1)[1].split("\n\n", 1)[0].splitlines()
    out, current = [], ""
    for line in lines:
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        current = f"{current} {line}".strip()
        if current.endswith("\\"):
            current = current[:-1].strip()
            continue
        out.append(current)
        current = ""
    return out


@pytest.mark.parametrize("columns", ["200", "80"])
def test_every_help_fits_80_columns_and_shows_examples_that_parse(monkeypatch, columns):
    monkeypatch.setenv("COLUMNS", columns)
    parsers = _parsers()
    progs = {p.prog for p in parsers}
    assert {"gonio", "gonio models", "gonio plans", "gonio fit", "gonio capture", "gonio sim serve",
            "gonio perf capture", "gonio shot", "gonio estop"} <= progs
    for parser in parsers:
        text = parser.format_help()
        wide = [line for line in text.splitlines() if len(line) > min(WIDTH, int(columns))]
        assert not wide, (parser.prog, wide)
        assert "examples:\n" in text, parser.prog
        assert parser.description, parser.prog
        for example in _examples(text):
            argv = shlex.split(example, comments=True)
            assert argv[0] == "gonio", (parser.prog, example)
            try:
                build_parser().parse_args(argv[1:])
            except SystemExit as exc:
                pytest.fail(f"{parser.prog}: its example `{example}` does not parse (exit {exc.code})")


def test_help_as_printed_by_the_command(tmp_path):
    """The real processes, on a wide terminal's COLUMNS: `gonio --help`, `gonio estop --help`
    (dispatched to its own light parser), `gonio fit --help`."""
    env = dict(os.environ, COLUMNS="200")
    for args in (["--help"], ["estop", "--help"], ["fit", "--help"], ["plans"], ["models"]):
        proc = subprocess.run([sys.executable, "-m", "gonio.cli.main", *args], capture_output=True, text=True,
                              env=env, timeout=120, cwd=tmp_path)
        assert proc.returncode == 0, (args, proc.stderr[-1000:])
        assert max(map(len, proc.stdout.splitlines())) <= WIDTH, args
        if "--help" in args:
            assert "examples:" in proc.stdout, args


def test_models_lists_the_catalogue_and_the_example_samples(capsys):
    import gonio.models as gm
    from gonio.cli.listing import example_samples

    assert main(["models"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert max(map(len, lines)) <= WIDTH
    for name in gm.names():
        model = gm.get(name)
        star = " *" if getattr(type(model), "auto_candidate", True) else ""
        assert any(line.startswith(f"  {name}{star} ") for line in lines), name
    assert "options: distribution=beckmann|ggx; nonlinear=false|true" in " ".join(out.split())
    samples = example_samples()
    assert {"orange-plastic", "black-gloss", "white-matte", "clay", "gold"} <= set(samples)
    for name in samples:
        assert any(line.startswith(f"  {name} ") for line in lines), name


def test_example_samples_are_valid_and_named_on_the_command_line(tmp_path, capsys):
    """Each packaged sample TOML loads (its model, options and parameters checked); --sample
    takes its name; a file of that name in the folder wins."""
    from gonio.bench.samples import DEMO_SAMPLE, check_sample, load_sample
    from gonio.cli.listing import example_samples, sample_path

    for name, (path, doc) in example_samples().items():
        assert doc["description"] and load_sample(path)["model"] == doc["model"], name
    assert load_sample(sample_path("orange-plastic")) == check_sample(DEMO_SAMPLE)
    assert sample_path("no-such-sample") == "no-such-sample" and sample_path(None) is None
    assert main(["capture", "--sim", "--sample", "gold", "--plan", "quick", "--dry-run"]) == 0
    assert main(["capture", "--sim", "--sample", "no-such-sample", "--plan", "quick", "--out",
                 str(tmp_path / "s")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_plans_lists_every_preset_with_its_point_count(capsys):
    from gonio.bench.plan.plans import load_plan, preset_names
    import gonio.sim.physics.errors as errors

    assert main(["plans"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert max(map(len, lines)) <= WIDTH
    for name in preset_names():
        assert any(line.startswith(f"  {name} ") and f" {len(load_plan(name))} pts " in line for line in lines), name
    for name in errors.PRESETS:
        assert any(line.startswith(f"  {name} ") for line in lines), name
    assert "adaptive" in out and "repeat_deg 0.01" in out         # the typical preset's terms, from its model


def test_settings_show_prints_a_unit_for_every_number(capsys):
    import re

    assert main(["settings", "show"]) == 0
    lines = capsys.readouterr().out.splitlines()
    numbers = [line for line in lines if re.match(r"^\w+ = [-\d\[]", line)]
    assert len(numbers) > 30
    for line in numbers:
        assert re.search(r"  # [^;]+; (default|preset \w+|option|file .+)$", line), line
    assert "exposure_max_s = " in " ".join(lines) and any(line.startswith("exposure_max_s") and "# s;" in line
                                                          for line in lines)
    assert any(line.startswith("wavelength_nm") and "# nm;" in line for line in lines)


def test_an_error_is_one_line_in_a_pipe_and_wrapped_on_a_terminal(tmp_path):
    from pty_run import run_in_pty

    argv = [sys.executable, "-m", "gonio.cli.main", "capture", "--sim", "--plan", "nosuch-" + "x" * 60,
            "--out", str(tmp_path / "s")]
    piped = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert piped.returncode == 2 and len(piped.stderr.strip().splitlines()) == 1 and len(piped.stderr) > WIDTH
    rc, screen = run_in_pty(argv, cols=WIDTH)
    lines = [line for line in screen.replace("\r", "").splitlines() if line.strip()]
    assert rc == 2 and len(lines) >= 2 and max(map(len, lines)) <= WIDTH, screen
    assert " ".join(" ".join(lines).split()) == " ".join(piped.stderr.split())


def test_argparse_errors_wrap_too(tmp_path):
    from pty_run import run_in_pty

    rc, screen = run_in_pty([sys.executable, "-m", "gonio.cli.main", "frobnicate"], cols=WIDTH)
    lines = [line for line in screen.replace("\r", "").splitlines() if line.strip()]
    assert rc == 2 and "invalid choice" in screen and max(map(len, lines)) <= WIDTH, screen
