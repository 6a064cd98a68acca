"""Every example in the docs (README.md, docs/*.md) is checked by the suite, so none goes stale.

A fenced block says what it is: ``python`` runs (docs/tutorial.md's in tests/test_tutorial.py,
the others here, each in an empty folder); ``sh`` is commands: every ``gonio`` line is parsed
by the real argument parser (an option that is gone, a value it refuses, fails here) and every
``make`` line names a target of the Makefile; a block marked ``<!-- runs: ... -->`` just above it
is also run, line by line, in an empty folder; ``toml`` is parsed (the default settings'
excerpt must agree with gonio/bench/instrument.toml); ``text`` or no language is a listing,
a tree or a diagram, not an example. A block of another language fails the suite until it is
handled here.
"""

from __future__ import annotations

import re
import shlex
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
KINDS = {"python", "sh", "toml", "text", ""}
RUNS = "<!-- runs:"


def fenced(path: Path):
    """``(language, code, line number, marked to run)`` of each fenced block of ``path``."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out, k = [], 0
    while k < len(lines):
        m = re.match(r"^```(\w*)\s*$", lines[k])
        if not m:
            k += 1
            continue
        start = k
        end = next(j for j in range(k + 1, len(lines)) if lines[j].startswith("```"))
        marked = start > 0 and lines[start - 1].startswith(RUNS)
        out.append((m.group(1), "\n".join(lines[start + 1:end]) + "\n", start + 1, marked))
        k = end + 1
    return out


def commands(code: str):
    """The command lines of an ``sh`` block, comments and continuation lines dropped."""
    for line in code.splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            yield line


def all_blocks():
    return [(path, *block) for path in DOCS for block in fenced(path)]


def test_every_block_is_of_a_kind_the_suite_checks():
    blocks = all_blocks()
    unknown = [(p.name, line, lang) for p, lang, _, line, _ in blocks if lang not in KINDS]
    assert not unknown, unknown
    assert sum(lang == "python" for _, lang, _, _, _ in blocks) >= 6          # the tutorial's 5, interfaces' 1


@pytest.mark.parametrize("where", [f"{p.name}:{line}" for p, lang, _, line, _ in all_blocks()
                                   if lang == "python" and p.name != "tutorial.md"])
def test_python_examples_run(where, tmp_path, monkeypatch):
    name, line = where.split(":")
    path = next(p for p in DOCS if p.name == name)
    code = next(c for lang, c, n, _ in fenced(path) if n == int(line))
    monkeypatch.chdir(tmp_path)
    exec(compile(code, where, "exec"), {"__name__": "docs_example"})


def test_every_gonio_command_in_the_docs_parses():
    from gonio.cli.main import build_parser

    makefile = (ROOT / "Makefile").read_text()
    seen = 0
    for path, lang, code, line, _ in all_blocks():
        if lang != "sh":
            continue
        for command in commands(code):
            argv = shlex.split(command, comments=True)
            where = f"{path.name}:{line}: {command.strip()[:60]}"
            if argv[0] == "make":
                assert all(re.search(rf"^{t}:", makefile, re.M) for t in argv[1:]), where
                continue
            assert argv[0] == "gonio", where
            try:
                build_parser().parse_args(argv[1:])
            except SystemExit as exc:
                pytest.fail(f"{where}: the parser refuses it (exit {exc.code})")
            seen += 1
    assert seen >= 40


def test_the_settings_excerpt_is_the_default():
    """docs/interfaces.md's toml block: every value as gonio/bench/instrument.toml has it."""
    defaults = tomllib.loads((ROOT / "gonio" / "bench" / "instrument.toml").read_text())
    (code,) = [c for p, lang, c, _, _ in all_blocks() if lang == "toml"]
    for table, values in tomllib.loads(code).items():
        for key, value in values.items():
            assert defaults[table][key] == value, (table, key)


def test_every_preset_and_example_sample_is_documented():
    """The plan presets and example samples (found where they are declared) appear in the README
    and in `gonio plans` / `gonio models`."""
    from gonio.bench.plan.plans import preset_names
    from gonio.cli.listing import example_samples

    readme = (ROOT / "README.md").read_text()
    for name in preset_names():
        assert f"`{name}`" in readme, name
    for name in example_samples():
        assert f"`{name}`" in readme, name


@pytest.mark.slow
def test_marked_blocks_run(tmp_path, monkeypatch, capsys):
    """The blocks marked to run (README's loop on the simulated instrument), each line through
    `gonio.cli.main.main` in an empty folder: exit status 0, and the files they name exist."""
    from gonio.cli.main import main

    marked = [(p, code) for p, lang, code, _, runs in all_blocks() if runs and p.name == "README.md"]
    assert marked and all(lang == "sh" for p, lang, _, _, runs in all_blocks() if runs)
    monkeypatch.chdir(tmp_path)
    for path, code in marked:
        for command in commands(code):
            argv = shlex.split(command, comments=True)
            assert main(argv[1:]) == 0, (command, capsys.readouterr().err[-2000:])
    for name in ("s1/dataset.nc", "s1/fit.json", "s1/render/render.json", "s1/report.html", "scene/fit.xml"):
        assert (tmp_path / name).is_file(), name
