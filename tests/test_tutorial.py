"""docs/tutorial.md runs: its Python blocks, in order, in one namespace, in an empty folder."""

import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

TUTORIAL = Path(__file__).resolve().parents[1] / "docs" / "tutorial.md"


def blocks(text):
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_tutorial_runs(tmp_path, monkeypatch, capsys):
    code = blocks(TUTORIAL.read_text(encoding="utf-8"))
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


def test_blocks_are_found():
    """The extractor sees every fenced python block (none silently skipped)."""
    text = TUTORIAL.read_text(encoding="utf-8")
    assert text.count("```python") == len(blocks(text))
