"""`gonio report` against hostile input folders (issue 14, "the report reads only what it wrote").

Every input file the report reads (dataset.nc, fit.json, speed.json, render/render.json,
render/preview/preview.json) gets hostile strings, wrong types and hostile paths; the report
must escape every string it shows, refuse wrong types and outside paths with one line
(GonioError, exit status 2) before writing anything, and never open a file outside the folder.
"""

from __future__ import annotations

import base64
import html.parser
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import report_folder
from gonio.core.errors import GonioError
from gonio.bench.report import write_report

SCRIPT = "<script>alert(1)</script>"
IMG = '"><img src=x onerror=alert(1)>'
HOSTILE = [SCRIPT, IMG, "</pre></table><script>alert(2)</script>", "{{ 7*7 }}{% raw %}", "\x1b]0;x\x07\u202e",
           "x" * 200_000]
PREVIEW = Path("render/preview/preview.json")
NUMERIC = [("fit.json", ("goodness", "dof")), ("fit.json", ("optimiser", "evaluations")),
           ("fit.json", ("selection", 0, "k")), ("render/render.json", ("points",)),
           ("render/render.json", ("scene_check", "poses")), ("render/render.json", ("summary", "worst", 0, "point")),
           ("speed.json", ("points",)), ("speed.json", ("rows", 0, "evaluations"))]
BAD_NUMBERS = [SCRIPT, IMG, "12", [1], {"a": 1}, True, "y" * 100_000]


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return report_folder.build(tmp_path_factory.mktemp("pristine") / "out")


@pytest.fixture
def out(pristine, tmp_path):
    return report_folder.copy(pristine, tmp_path)


@pytest.fixture
def secret(tmp_path):
    """A file outside the output folder whose content must never reach the report."""
    path = tmp_path / "secret.png"
    marker = b"\x89PNG\r\n\x1a\nSECRET-MARKER-0123456789"
    path.write_bytes(marker)
    return path


def edit(folder: Path, name, change) -> None:
    path = folder / name
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def dotted(keys) -> str:
    """("summary", "worst", 0, "point") -> "summary.worst[0].point", as the refusal names it."""
    out = ""
    for k in keys:
        out += f"[{k}]" if isinstance(k, int) else (f".{k}" if out else k)
    return out


def set_at(doc, keys, value):
    for k in keys[:-1]:
        doc = doc[k]
    doc[keys[-1]] = value


def poison_strings(value, keep=()):
    """Every string in a JSON value replaced by hostile ones (cycled), keys included."""
    counter = iter(range(10 ** 9))

    def walk(v, path):
        if path in keep:
            return v
        if isinstance(v, dict):
            return {(HOSTILE[next(counter) % 3] + k if path and path[-1] in ("parameters", "delta_e") else k):
                    walk(x, path + (k,)) for k, x in v.items()}
        if isinstance(v, list):
            return [walk(x, path + (i,)) for i, x in enumerate(v)]
        if isinstance(v, str):
            return HOSTILE[next(counter) % len(HOSTILE)]
        return v

    return walk(value, ())


class Tags(html.parser.HTMLParser):
    """The elements and attributes a browser would build from the page."""

    def __init__(self):
        super().__init__()
        self.tags, self.attrs, self.scripts, self.script_types = [], [], [], []
        self._in_script = False

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        if tag == "script":
            self.script_types.append(dict(attrs).get("type"))
        self.attrs.extend(name for name, _ in attrs)
        self._in_script = tag == "script"

    def handle_endtag(self, tag):
        self._in_script = False

    def handle_data(self, data):
        if self._in_script:
            self.scripts.append(data)


def assert_inert(page: str):
    tags = Tags()
    tags.feed(page)
    # the report's own script, and the view's data in a JSON element (never executed)
    assert tags.tags.count("script") == 2 and tags.script_types == ["application/json", None], tags.script_types
    assert "data-images-decoded" in tags.scripts[1] and "alert" not in tags.scripts[1]
    json.loads(tags.scripts[0])
    assert not [a for a in tags.attrs if a.startswith("on")], "no event-handler attribute"
    assert tags.tags.count("img") == page.count('src="data:image/png;base64,')
    for bad in (SCRIPT, IMG, "<img src=x", "alert(2)</script>", "\x1b", "49{% raw"):
        assert bad not in page


def assert_refused(folder, *needles):
    with pytest.raises(GonioError) as err:
        write_report(folder)
    line = str(err.value)
    assert "\n" not in line
    for needle in needles:
        assert needle in line, line
    assert not (folder / "report.html").exists()
    assert not (folder / "report_files").exists()
    return line


def test_hostile_strings_in_every_input_are_escaped(out):
    keep = {("format",), ("model", "name"), ("model", "options"), ("side_by_side_png",)}
    for name in ("fit.json", "speed.json", "render/render.json", PREVIEW):
        edit(out, name, lambda d: d.update(poison_strings(d, keep)))
    edit(out, "fit.json", lambda d: d["model"]["options"].update())  # diffuse takes no options
    import xarray as xr

    with xr.open_dataset(out / "dataset.nc", engine="h5netcdf") as ds:
        ds.load()
    ds.attrs.update(gonio_version=SCRIPT, seed=IMG, capture_wall_s=HOSTILE[2],
                    plan=json.dumps({"name": SCRIPT, "points": [1, 2], "description": IMG}),
                    sample_truth=json.dumps({"model": "diffuse", "options": {"a": SCRIPT},
                                             "params": {"reflectance": [IMG, SCRIPT, 1]}}))
    ds = ds.assign_coords(channel=[SCRIPT, "$\\frac{$", IMG])
    (out / "dataset.nc").unlink()
    ds.to_netcdf(out / "dataset.nc", engine="h5netcdf")

    page = write_report(out).read_text()
    assert_inert(page)
    # shown, escaped: the operator sees what the file holds
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert "&#34;&gt;&lt;img src=x onerror=alert(1)&gt;" in page
    assert "characters, cut)" in page and len(page) < 3_000_000
    assert page.count('src="data:image/png;base64,') == 8  # every figure still drawn


@pytest.mark.parametrize("name, keys", NUMERIC, ids=["/".join(map(str, k)) for _, k in NUMERIC])
def test_non_numbers_where_numbers_belong_are_refused(out, name, keys):
    for bad in BAD_NUMBERS:
        edit(out, name, lambda d: set_at(d, keys, bad))
        line = assert_refused(out, Path(name).name, dotted(keys), "must be", "re-run")
        assert "<script>" not in line or "'<script>" in line  # quoted, cut, ASCII
        assert len(line) < 400 and line.isascii()


def test_nan_numbers_are_shown_and_nan_counts_refused(out):
    edit(out, "render/render.json", lambda d: d["summary"].update(residual_rms_sigma=float("nan"),
                                                                  export_max_rel=float("inf")))
    page = write_report(out).read_text()
    assert "rms residual nan sigma" in page and "= inf." in page
    edit(out, "speed.json", lambda d: d["rows"][0].update(evaluations=float("nan")))
    shutil.rmtree(out / "report_files")
    (out / "report.html").unlink()
    assert_refused(out, "speed.json", "rows[0].evaluations", "whole number")


def test_values_written_as_null_are_said_in_the_report(out):
    edit(out, "fit.json", lambda d: (d["goodness"].update(chi2_dof=None), d.update(non_finite=["goodness.chi2_dof", 3])))
    page = write_report(out).read_text()
    assert "chi<sup>2</sup>/dof = – (" in page and "NaN or infinite: goodness.chi2_dof." in page
    edit(out, "fit.json", lambda d: d.update(non_finite=7))
    assert "NaN or infinite" not in write_report(out).read_text()


def test_fit_file_with_nan_tokens_is_refused(out):
    text = (out / "fit.json").read_text()
    doc = json.loads(text)
    doc["goodness"]["chi2"] = float("nan")
    (out / "fit.json").write_text(json.dumps(doc))
    assert_refused(out, "fit.json", "NaN", "re-run `gonio fit")


@pytest.mark.parametrize("change, needle", [
    (lambda d: d.update(model="<script>"), "'model' must hold"),
    (lambda d: d["model"].update(name=SCRIPT), "unknown model"),
    (lambda d: d["model"].update(options={"x": IMG}), "options"),
    (lambda d: d["params"].update(reflectance=[SCRIPT]), "params.reflectance"),
    (lambda d: d.update(parameters=[1, 2]), "parameters must be an object"),
    (lambda d: d["posterior"].update(samples=[[SCRIPT]]), "posterior.samples"),
    (lambda d: d["posterior"].update(names=[1, 2]), "posterior.names"),
    (lambda d: d.update(format=SCRIPT), "not a gonio fit file"),
])
def test_malformed_fit_files_are_refused(out, change, needle):
    edit(out, "fit.json", change)
    line = assert_refused(out, needle)
    assert "<script>" not in line.replace("'<script>", "")


def test_garbage_inputs_are_refused(out):
    (out / "speed.json").write_bytes(b"\xff\xfe\x00garbage")
    assert_refused(out, "speed.json", "not UTF-8")
    (out / "speed.json").write_text("[1, 2]")
    assert_refused(out, "speed.json", "JSON object")
    (out / "speed.json").write_text("[" * 100_000)
    assert_refused(out, "speed.json")
    (out / "speed.json").write_text('{"points": ' + "9" * 5000 + "}")
    assert_refused(out, "speed.json", "not valid JSON")
    (out / "speed.json").unlink()
    edit(out, "render/render.json", lambda d: d.update(brdf_render=d["brdf_render"][:5]))
    assert_refused(out, "render.json", "5 rendered points", "40")


@pytest.mark.parametrize("how", ["absolute", "dotdot", "symlink", "symlinked-folder", "relative-symlink"])
def test_preview_image_outside_the_folder_is_refused(out, secret, how):
    preview_dir = out / "render" / "preview"
    if how == "absolute":
        ref = str(secret)
    elif how == "dotdot":
        ref = os.path.relpath(secret, preview_dir)
        assert ref.startswith("..")
    elif how == "symlink":
        (preview_dir / "side_by_side.png").unlink()
        (preview_dir / "side_by_side.png").symlink_to(secret)
        ref = str(preview_dir / "side_by_side.png")
    elif how == "symlinked-folder":
        (out / "linked").symlink_to(secret.parent, target_is_directory=True)
        ref = str(out / "linked" / secret.name)
    else:
        (preview_dir / "evil.png").symlink_to(os.path.relpath(secret, preview_dir))
        ref = "evil.png"
    edit(out, PREVIEW, lambda d: d.update(side_by_side_png=ref))
    line = assert_refused(out, "preview.json", "side_by_side_png", "outside")
    assert "inside the output folder" in line or "'..'" in line


def test_etc_passwd_is_never_embedded(out):
    edit(out, PREVIEW, lambda d: d.update(side_by_side_png="/etc/passwd"))
    assert_refused(out, "preview.json", "/etc/passwd", "outside")


def test_preview_image_must_be_a_png_and_may_be_missing(out):
    edit(out, PREVIEW, lambda d: d.update(side_by_side_png=str(out / "fit.json")))
    assert_refused(out, "side_by_side_png", "not a PNG")
    for bad in (["a.png"], 7, "", "a\x00b"):
        edit(out, PREVIEW, lambda d: d.update(side_by_side_png=bad))
        assert_refused(out, "side_by_side_png", "must name a file inside")
    edit(out, PREVIEW, lambda d: d.update(side_by_side_png="gone.png"))
    page = write_report(out).read_text()
    assert 'class="note"' in page and "gone.png" in page and "is missing" in page
    assert "preview_side_by_side.png" not in page
    # a relative name is taken from the preview's own folder
    edit(out, PREVIEW, lambda d: d.update(side_by_side_png="side_by_side.png"))
    assert "preview_side_by_side.png" in write_report(out).read_text()


@pytest.mark.parametrize("name", ["fit.json", "speed.json", "render/render.json", str(PREVIEW), "dataset.nc"])
def test_input_file_linked_from_outside_is_refused(out, tmp_path, name):
    outside = tmp_path / "elsewhere" / Path(name).name
    outside.parent.mkdir()
    shutil.move(out / name, outside)
    (out / name).symlink_to(outside)
    assert_refused(out, Path(name).name, "outside", "copy the file in")


def test_no_outside_file_is_opened(out, secret):
    """Hostile paths in every input file; an audit hook records every file opened."""
    ref = str(secret)
    for name, change in (
            ("fit.json", lambda d: (d["provenance"].update(dataset=ref), d["mitsuba"].update(filename=ref),
                                    d["model"].update(file=ref))),
            ("speed.json", lambda d: d.update(file=ref, rows=[dict(r, file=ref) for r in d["rows"]])),
            ("render/render.json", lambda d: (d["provenance"].update(fit=ref), d.update(png=ref))),
            (PREVIEW, lambda d: d.update(images={"env": {k: ref for k in ("model_png", "model_exr", "delta_e_png")}})),
    ):
        edit(out, name, change)
    opened = []
    armed = [True]

    def hook(event, args):
        if armed[0] and event == "open" and args and isinstance(args[0], (str, bytes, os.PathLike)):
            opened.append(os.fsdecode(args[0]))

    sys.addaudithook(hook)
    try:
        path = write_report(out)
    finally:
        armed[0] = False
    assert not [p for p in opened if Path(p).name == secret.name]
    blob = path.read_text() + "".join(p.read_bytes().hex() for p in (out / "report_files").iterdir())
    assert "SECRET-MARKER" not in blob and base64.b64encode(secret.read_bytes()).decode()[:20] not in blob


def test_report_files_links_are_replaced_not_followed(out, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    (out / "report_files").mkdir()
    (out / "report_files" / "coverage.png").symlink_to(victim)
    write_report(out)
    assert victim.read_text() == "keep me"
    assert not (out / "report_files" / "coverage.png").is_symlink()
    shutil.rmtree(out / "report_files")
    (out / "report.html").unlink()
    (out / "report_files").symlink_to(tmp_path, target_is_directory=True)
    with pytest.raises(GonioError, match="not a plain folder"):
        write_report(out)
    assert not (out / "report.html").exists() and not (tmp_path / "coverage.png").exists()


def test_report_and_figures_get_the_umask_mode(out):
    old = os.umask(0o022)
    try:
        path = write_report(out)
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o644
    modes = {p.name: p.stat().st_mode & 0o777 for p in (out / "report_files").iterdir()}
    assert len(modes) == 9 and set(modes.values()) == {0o644}, modes       # 8 figures, certificate.json


def test_interrupted_report_leaves_no_temporary(out, monkeypatch):
    write_report(out)
    before = (out / "report.html").read_text()
    real = os.fsync
    calls = []

    def interrupt(fd):
        calls.append(fd)
        if len(calls) == 9:  # the eight figures went through; the page is being written
            raise KeyboardInterrupt
        return real(fd)

    monkeypatch.setattr(os, "fsync", interrupt)
    with pytest.raises(KeyboardInterrupt):
        write_report(out)
    monkeypatch.undo()
    assert (out / "report.html").read_text() == before
    assert not [p for p in out.rglob("*.tmp")], list(out.rglob("*"))


def test_cli_prints_one_line_and_exits_2(out):
    edit(out, "fit.json", lambda d: d["goodness"].update(dof=SCRIPT))
    proc = subprocess.run([sys.executable, "-m", "gonio.cli.main", "report", str(out)], capture_output=True,
                          text=True, timeout=120, env=dict(os.environ, PYTHONWARNINGS="ignore"))
    assert proc.returncode == 2, proc.stderr
    lines = [x for x in proc.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("gonio: error: fit.json: goodness.dof must be a"), proc.stderr
    assert "Traceback" not in proc.stderr and not (out / "report.html").exists()
