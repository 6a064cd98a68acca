"""The house's layering is a checked contract (pyproject.toml, [tool.importlinter]):

* layers: ``gonio.bench`` on top, ``gonio.sim`` and ``gonio.fitting`` beside each other (neither
  imports the other), ``gonio.models`` at the bottom (imports nothing else of gonio);
* no import cycles between sibling modules, at any depth (acyclic_siblings);
* a folder's private modules (``_name``) are imported only inside that folder.

Imports inside functions count (grimp reads them all), so a lazy import cannot hide a
dependency. A change that breaks the contract fails here with import-linter's explanation.
"""

from __future__ import annotations

import ast
from pathlib import Path

from importlinter.cli import lint_imports

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {name: f"gonio.{name}" for name in ("core", "models", "sim", "fitting", "bench", "perf", "cli")}


def test_import_contracts_are_kept(capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    status = lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True)
    out = capsys.readouterr().out
    assert status == 0, out[out.find("Broken contracts"):][-6000:]


def test_no_private_name_is_imported_from_another_folder():
    """``from gonio.perf.fit import _scipy_lsq`` in bench/ is a private import too."""
    found = []
    for folder, package in FOLDERS.items():
        for path in sorted((ROOT / "gonio" / folder).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
            for node in ast.walk(tree):
                if not (isinstance(node, ast.ImportFrom) and node.level == 0 and node.module):
                    continue
                if not node.module.startswith("gonio.") or node.module.startswith(package):
                    continue
                for alias in node.names:
                    if alias.name.startswith("_"):
                        found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.module}.{alias.name}")
    assert not found, "private names imported across folders:\n" + "\n".join(found)
