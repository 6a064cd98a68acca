"""docs/tutorial.md runs: its Python blocks, in order, in one namespace, in an empty folder; then
its command-line block, line by line, in the same folder (on the fit file the Python wrote)."""

import re
import shlex
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

TUTORIAL = Path(__file__).resolve().parents[1] / "docs" / "tutorial.md"


def blocks(text, lang="python"):
    return re.findall(rf"^```{lang}\n(.*?)^```", text, flags=re.S | re.M)


def test_tutorial_runs(tmp_path, monkeypatch, capsys):
    from gonio.cli.main import main

    text = TUTORIAL.read_text(encoding="utf-8")
    code = blocks(text)
    assert len(code) == 5
    monkeypatch.chdir(tmp_path)
    ns = {"__name__": "tutorial"}
    for k, block in enumerate(code):
        exec(compile(block, f"{TUTORIAL.name} block {k + 1}", "exec"), ns)
    out = capsys.readouterr().out
    assert out.startswith("Measurements: 300 direction pairs x 3 channels")
    assert "roughplastic(distribution=ggx" in out and "array(" not in out
    assert ns["image"].shape == (32, 32, 3) and ns["image"].mean() > 0
    assert (tmp_path / "fit.json").is_file() and (tmp_path / "residuals.png").stat().st_size > 1000
    assert ns["result"].converged
    (commands,) = blocks(text, "sh")
    for line in commands.splitlines():
        argv = shlex.split(line, comments=True)
        assert argv[0] == "gonio" and main(argv[1:]) == 0, line
    assert (tmp_path / "scene" / "fit.xml").is_file() and (tmp_path / "fit.nc").is_file()
    assert list((tmp_path / "radiance").glob("*.dat"))


def test_blocks_are_found():
    """The extractor sees every fenced python block (none silently skipped)."""
    text = TUTORIAL.read_text(encoding="utf-8")
    assert text.count("```python") == len(blocks(text))
