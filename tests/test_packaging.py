"""What a wheel and a citation need: LICENSE matches pyproject's licence, CITATION.cff is
CFF 1.2.0 with the package's version, every package-data pattern names files that exist, and
the package installs anywhere (issue 41): the wheel, built offline from a copy of the source
with no setuptools warning, holds every non-Python file under gonio/; installed in a fresh
virtual environment outside the checkout (its dependencies taken from this venv through a
``.pth`` file, no network) the ``gonio`` command finds its presets, example samples, settings
and report templates from another folder. The whole demo from that install is a ``long`` test
(about 30-60 s: ``make test-long``); ``make test`` runs the rest.

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
    assert PYPROJECT["project"]["license"] == "BSD-3-Clause"           # SPDX (PEP 639)
    assert PYPROJECT["project"]["license-files"] == ["LICENSE"]
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
    assert cff["license"] == PYPROJECT["project"]["license"]


def test_every_package_data_pattern_matches_files():
    for package, patterns in PYPROJECT["tool"]["setuptools"]["package-data"].items():
        folder = ROOT.joinpath(*package.split("."))
        assert (folder / "__init__.py").is_file(), f"{package} is not a package folder"
        for pattern in patterns:
            assert [p for p in folder.glob(pattern) if p.is_file()], f"{package}: {pattern} matches no file"


# --------------------------------------------------------------------------- the wheel, installed
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import zipfile

import pytest

_SKIP = shutil.ignore_patterns(".venv*", ".git", ".hypothesis", "__pycache__", ".pytest_cache", "*.egg-info",
                               "build", "dist", "api", "gonio-out", "*.pyc")


def _data_files():
    """Every non-Python file of the package in the checkout (what the installed package may read)."""
    return sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "gonio").rglob("*")
                  if p.is_file() and p.suffix not in (".py", ".pyc") and "__pycache__" not in p.parts)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """The wheel, built with this venv's setuptools (no build isolation: no network) from a copy
    of the source tree; returns (wheel path, the build's output)."""
    import setuptools

    if tuple(int(x) for x in setuptools.__version__.split(".")[:2]) < (77, 0):
        pytest.fail(f"setuptools {setuptools.__version__} in this venv: the test extra needs >= 77 (make install)")
    root = tmp_path_factory.mktemp("wheel")
    src = root / "src"
    shutil.copytree(ROOT, src, ignore=_SKIP)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    proc = subprocess.run([sys.executable, "-W", "default", "-c",
                           "import sys; from setuptools import build_meta as b; print(b.build_wheel(sys.argv[1]))",
                           str(root / "dist")], cwd=src, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return root / "dist" / proc.stdout.strip().splitlines()[-1], proc.stdout + proc.stderr


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory):
    """A fresh venv outside the checkout with the wheel installed (no dependencies: a .pth file
    adds this venv's site-packages after its own); returns its bin folder."""
    root = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root / "venv")], check=True, timeout=120)
    py = root / "venv" / "bin" / "python"
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    (Path(site) / "gonio-test-dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    proc = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index",
                           "--quiet", str(wheel[0])], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    where = subprocess.run([str(py), "-c", "import gonio; print(gonio.__file__)"], capture_output=True, text=True,
                           cwd=root).stdout
    assert where.startswith(site) and str(ROOT) not in where, where       # the wheel's, not the checkout's
    return root / "venv" / "bin"


def _gonio(bin_dir, *args, cwd, timeout=300):
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run([str(bin_dir / "gonio"), *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout, env=env)


@pytest.mark.slow
def test_the_wheel_builds_without_warnings_and_holds_every_data_file(wheel):
    path, output = wheel
    warnings = [line for line in output.splitlines() if re.search(r"warn|deprecat", line, re.I)]
    assert not warnings, warnings
    with zipfile.ZipFile(path) as zf:
        names = set(zf.namelist())
    missing = [f for f in _data_files() if f not in names]
    assert not missing, f"package data the wheel lacks (pyproject [tool.setuptools.package-data]): {missing}"
    assert "gonio-0.1.0.dist-info/licenses/LICENSE" in names
    assert {"gonio/cli/samples/gold.toml", "gonio/bench/report/templates/report.html.j2"} <= names


@pytest.mark.slow
def test_the_installed_command_finds_its_data_from_another_folder(installed, tmp_path):
    """From an empty folder: the presets, the example samples and the settings (listings), a
    capture with an example sample, its export, and a report (the templates), all from the
    wheel's files."""
    for args, says in ((["plans"], "glossy"), (["models"], "orange-plastic"),
                       (["settings", "show"], "settle_s = 0.2  # s; default")):
        proc = _gonio(installed, *args, cwd=tmp_path)
        assert proc.returncode == 0 and says in proc.stdout, (args, proc.stderr[-2000:])
    plan = tmp_path / "two.toml"
    plan.write_text('name = "two"\npoints = [[30, 0, 20, 180], [30, 0, 40, 180]]\n')
    for args in (["capture", "--sim", "--sample", "gold", "--plan", plan, "--out", "s"], ["export", "s"],
                 ["report", "s"]):
        proc = _gonio(installed, *args, cwd=tmp_path)
        assert proc.returncode == 0, (args, proc.stderr[-2000:])
    assert (tmp_path / "s" / "report.html").stat().st_size > 10_000


@pytest.mark.long
def test_the_demo_runs_from_the_installed_wheel(installed, tmp_path):
    """`gonio demo` (quick plan, no posterior: the whole loop, calibrate to report) from a venv
    that holds the wheel and nothing of the checkout, in another folder."""
    proc = _gonio(installed, "demo", "--plan", "quick", "--no-posterior", "--out", "out", cwd=tmp_path, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "within 3 sigma" in proc.stdout
    for name in ("calibration.toml", "dataset.nc", "fit.json", "render/render.json", "report.html"):
        assert (tmp_path / "out" / name).is_file(), name
