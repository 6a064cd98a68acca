"""What a wheel and a citation need: LICENSE matches pyproject's licence, CITATION.cff is
CFF 1.2.0 with the package's version, and every package-data pattern names files that exist.

CITATION.cff was validated with cffconvert 2.0.0 (``cffconvert --validate``, schema 1.2.0);
cffconvert pins jsonschema < 4, so the suite checks the schema's required keys and types
(Citation File Format 1.2.0, https://citation-file-format.github.io) itself.
"""

import tomllib
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_license_is_the_bsd_3_clause_text_pyproject_names():
    assert PYPROJECT["project"]["license"] == {"text": "BSD-3-Clause"}
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("BSD 3-Clause License") and "the gonio developers" in text
    # the three conditions of the SPDX BSD-3-Clause text
    for clause in ("Redistributions of source code must retain", "Redistributions in binary form must reproduce",
                   "Neither the name of the copyright holder"):
        assert clause in text


def test_citation_cff_is_cff_1_2_0_of_this_version():
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    # CFF 1.2.0's required keys: cff-version, message, title, authors (each a person or an entity)
    assert cff["cff-version"] == "1.2.0"
    assert isinstance(cff["message"], str) and cff["message"] and isinstance(cff["title"], str)
    assert cff["authors"] and all(isinstance(a, dict) and ("name" in a or "family-names" in a) for a in cff["authors"])
    assert str(cff["version"]) == PYPROJECT["project"]["version"]
    assert cff["license"] == PYPROJECT["project"]["license"]["text"]


def test_every_package_data_pattern_matches_files():
    for package, patterns in PYPROJECT["tool"]["setuptools"]["package-data"].items():
        folder = ROOT.joinpath(*package.split("."))
        assert (folder / "__init__.py").is_file(), f"{package} is not a package folder"
        for pattern in patterns:
            assert [p for p in folder.glob(pattern) if p.is_file()], f"{package}: {pattern} matches no file"
