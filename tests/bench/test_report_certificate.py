"""`gonio report` as a calibration certificate (issue 41; ISO/IEC 17025:2017 7.8.2 and 7.8.4).

Every item of clause 7.8 the report must carry is checked in the page: a unique number
(deterministic from the data and the issue date, on every printed page and recorded in
report_files/certificate.json), "Page x of y" from the print stylesheet's page counters, the
issue date and the approval (name, role, a line to sign; blank lines when none is given), the
laboratory, customer and sample, the method, the conditions (apertures and solid angles,
polarisation, ambient temperature and humidity, or "not recorded"), the data file's SHA-256
(equal to hashlib's), results with U and k, the budget as a table whose rows are the fit
file's budget, traceability (the calibration record, or "no calibration applied"), the
statement that the results relate only to the item, and the end of the certificate. Headless
Chromium prints it on A4: more than one page, each with "Page k of N", no text under 8 pt, and
every figure's text at least 8 pt as printed.
"""

from __future__ import annotations

import hashlib
import html
import json
import math
import re
import shutil
import subprocess

import pytest

import pdftext
import report_folder
from gonio.bench.report import certificate as cert
from gonio.bench.report import figures as figs
from gonio.bench.report import write_report

SCRIPT = "<script>alert(1)</script>"
DAY = "2026-12-04"


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return report_folder.build(tmp_path_factory.mktemp("certificate") / "out")


@pytest.fixture
def out(pristine, tmp_path):
    return report_folder.copy(pristine, tmp_path)


@pytest.fixture
def no_figures(monkeypatch):
    monkeypatch.setattr(figs, "draw", lambda images, notes, name, fn, *args: None)


def edit_attrs(folder, **attrs):
    import xarray as xr

    with xr.open_dataset(folder / "dataset.nc", engine="h5netcdf") as ds:
        ds.load()
    ds.attrs.update(attrs)
    (folder / "dataset.nc").unlink()
    ds.to_netcdf(folder / "dataset.nc", engine="h5netcdf")


def refit(folder):
    """Fit the folder's dataset again (after its attributes changed), as `gonio fit` would."""
    from gonio.cli.fit import fit_dataset
    from gonio.fitting import load_dataset, write_json_atomic

    _, doc, _ = fit_dataset(load_dataset(folder / "dataset.nc"), model="diffuse", seed=1,
                            dataset_path=folder / "dataset.nc")
    write_json_atomic(folder / "fit.json", doc)


def text_of(fragment: str) -> str:
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", fragment)).split())


def section(page: str, start: str, end: str) -> str:
    return page[page.index(start):page.index(end, page.index(start))]


def row(page: str, label: str) -> str:
    m = re.search(r"<tr><th>" + re.escape(label) + r"</th><td[^>]*>(.*?)</td></tr>", page, re.S)
    assert m, label
    return text_of(m[1])


SETTINGS = {"session": {"sample_id": "tile " + SCRIPT, "sample_description": "white PTFE tile, lot 7",
                        "operator": "A. Tester", "customer": "ACME Optics <b>Ltd</b>, 1 Lens Road",
                        "institution": "gonio test laboratory, 2 Bench Street"},
            "conditions": {"polarisation": "unpolarised source, no analyser", "temperature_c": 23.4,
                           "humidity_pct": 41.0},
            "reference": {"reflectance": 0.99, "rel_std": 0.005, "certificate": "NPL-2026-117"},
            "aperture": {"source_half_deg": 0.5, "detector_half_deg": 1.5, "profile": "uniform disk"}}


def test_the_certificate_carries_every_item_of_clause_7_8(out, no_figures):
    edit_attrs(out, settings=json.dumps(SETTINGS), versions=json.dumps({"created": "2026-11-30T10:00:00+00:00"}))
    refit(out)
    path = write_report(out, approver="Dr. B. Approver", approver_role="Head of photometry " + SCRIPT,
                        issue_date=DAY)
    page = path.read_text()
    # every string from a file or the user is escaped: the sample name, the role, the customer
    assert SCRIPT not in page and "<b>Ltd" not in page
    assert "tile &lt;script&gt;alert(1)&lt;/script&gt;" in page and "ACME Optics &lt;b&gt;Ltd&lt;/b&gt;" in page
    # 7.8.2.1 d: a unique number, deterministic from the data (dataset.nc's and fit.json's SHA-256)
    # and the issue date; j: the date of issue
    data_sha = hashlib.sha256((out / "dataset.nc").read_bytes()).hexdigest()
    fit_sha = hashlib.sha256((out / "fit.json").read_bytes()).hexdigest()
    number = cert.report_number(data_sha, fit_sha, cert.issue_date(DAY))
    assert cert.NUMBER_PATTERN.match(number)
    assert row(page, "Certificate number") == number and row(page, "Date of issue") == DAY
    # the data file's SHA-256, equal to hashlib's; the fit file's too
    assert f'<code class="sha" data-file="dataset.nc">{data_sha}</code>' in page
    assert data_sha in row(page, "Data file") and fit_sha in row(page, "Fit file")
    # b, e, g, i: the laboratory, the customer, the item, the date of the measurement
    assert row(page, "Laboratory (issued by)") == "gonio test laboratory, 2 Bench Street"
    assert row(page, "Customer") == "ACME Optics <b>Ltd</b>, 1 Lens Road"
    assert row(page, "Sample id") == "tile " + SCRIPT and row(page, "Operator") == "A. Tester"
    assert row(page, "Date of measurement (session start, UTC)") == "2026-11-30T10:00:00+00:00"
    # f: the method
    method = text_of(section(page, '<p id="method">', "</p>"))
    assert "Relative goniometric BRDF measurement" in method and "diffuse" in method and "JCGM 100:2008" in method
    # 7.8.4.1 b: the conditions, as recorded
    conditions = section(page, '<table class="ident" id="conditions">', "</table>")
    assert f"half-angle 0.5 deg (uniform disk), solid angle {cert.solid_angle(0.5):.3g} sr" in text_of(conditions)
    assert f"solid angle {2 * math.pi * (1 - math.cos(math.radians(1.5))):.3g} sr" in text_of(conditions)
    assert row(conditions, "Polarisation") == "unpolarised source, no analyser"
    assert row(conditions, "Ambient temperature") == "23.4 °C"
    assert row(conditions, "Ambient relative humidity") == "41 %"
    # 7.8.4.1 a: the results with the expanded uncertainty and its coverage factor
    results = section(page, "<h2>Results", "<h3>Uncertainty budget")
    assert "U (expanded)</th><th>k</th>" in results and '<td class="num">2</td>' in results
    # 7.8.4.1 c: traceability: the reference's certificate; no calibration in this session
    trace = text_of(section(page, '<div id="traceability">', "</div>"))
    assert "certificate NPL-2026-117" in trace and "No calibration applied" in trace
    # 7.8.2.1 l: the results relate only to the item; no statement of conformity (7.8.6)
    statements = text_of(section(page, '<ul id="statements">', "</ul>"))
    assert "The results relate only to the item calibrated" in statements and "7.8.6" in statements
    # o: the approval: name, role, date and a cell to sign
    approval = section(page, '<table class="approval" id="approval">', "</table>")
    assert "Dr. B. Approver" in approval and "Head of photometry &lt;script&gt;" in approval
    assert f"<td>{DAY}</td>" in approval and '<td class="sign">' in approval
    # d: the number on every printed page with "Page x of y" (the print stylesheet's counters),
    # and the end of the certificate
    style = page[page.index("<style>"):page.index("</style>")]
    margin = re.search(r"@page\s*\{(.*?)\}\}", style, re.S)[1]
    assert f'"Calibration certificate {number}"' in margin
    assert re.search(r'content:\s*"Page "\s*counter\(page\)\s*" of "\s*counter\(pages\)', margin)
    assert f'<p class="end" id="end">End of certificate {number}.</p>' in page
    assert page.index('id="end"') > page.index('<div class="appendix">')
    # the number is recorded beside the report with what it certifies
    record = json.loads((out / "report_files" / "certificate.json").read_text())
    assert record["number"] == number and record["issued"] == DAY
    assert {f["name"]: f["sha256"] for f in record["files"]} == {"dataset.nc": data_sha, "fit.json": fit_sha}
    assert record["approval"] == {"name": "Dr. B. Approver", "role": "Head of photometry " + SCRIPT}
    assert record["report"]["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()


def test_what_is_not_given_is_said_and_left_blank_to_sign(out, no_figures):
    """Without settings: the laboratory, customer and conditions are "not recorded", the
    approval's cells are blank lines to fill in; a fit of another dataset is flagged."""
    page = write_report(out, issue_date=DAY).read_text()
    for label in ("Laboratory (issued by)", "Customer"):
        assert row(page, label).startswith("not recorded"), label
    conditions = section(page, '<table class="ident" id="conditions">', "</table>")
    for label in ("Source aperture (illumination)", "Detector aperture (viewing)", "Polarisation",
                  "Ambient temperature", "Ambient relative humidity"):
        assert row(conditions, label).startswith("not recorded"), label
    approval = section(page, '<table class="approval" id="approval">', "</table>")
    cells = re.findall(r"<td[^>]*>(.*?)</td>", approval)
    assert len(cells) == 4 and all(c == '<span class="blank">&nbsp;</span>' for c in cells), cells
    assert json.loads((out / "report_files" / "certificate.json").read_text())["approval"] == \
        {"name": None, "role": None}
    # the approver from the settings the capture recorded, when the command gives none
    edit_attrs(out, settings=json.dumps({"session": {"approver": "C. Settings", "approver_role": "QM"}}))
    page = write_report(out, issue_date=DAY).read_text()
    approval = section(page, '<table class="approval" id="approval">', "</table>")
    assert "<td>C. Settings</td><td>QM</td>" in approval
    # the dataset changed after the fit: the fit file states another dataset's SHA-256
    box = section(page, '<div class="status bad">', "</div>")
    assert "The fit file states another dataset" in text_of(box)


def test_a_calibrated_session_states_its_calibration_and_simulation(out, no_figures):
    settings = {"calibration": {"sim": True, "seed": 3, "procedure": "specular cross-scans"},
                "alignment": {"yaw_zero_deg": 0.1, "u_yaw_zero_deg": 0.01, "tilt_zero_deg": 0.0,
                              "u_tilt_zero_deg": 0.01, "holder_tilt_x_deg": 0.0, "holder_tilt_y_deg": 0.0},
                "linearity": {"gamma": 0.003, "u_gamma": 0.0001},
                "reference": {"reflectance": [0.98, 0.99, 0.97], "rel_std": 0.004, "factor": [[1.0]]}}
    edit_attrs(out, settings=json.dumps(settings), aperture_source_half_deg=0.0, aperture_detector_half_deg=2.0)
    page = write_report(out, issue_date=DAY).read_text()
    trace = text_of(section(page, '<div id="traceability">', "</div>"))
    assert "Calibration applied: gonio calibrate on the simulated instrument, seed 3 (specular cross-scans)" in trace
    assert "detector's linearity" in trace and "non-Lambertian factor" in trace and "No calibration" not in trace
    assert "certified diffuse reflectance 0.98, 0.99, 0.97, relative standard uncertainty 0.4 %" in trace
    assert "certificate not recorded" in trace
    conditions = section(page, '<table class="ident" id="conditions">', "</table>")
    assert row(conditions, "Source aperture (illumination)").startswith("half-angle 0 deg as stated")
    assert f"solid angle {cert.solid_angle(2.0):.3g} sr" in row(conditions, "Detector aperture (viewing)")
    statements = text_of(section(page, '<ul id="statements">', "</ul>"))
    assert "simulated instrument" in statements


def test_the_budget_table_is_the_fit_files_budget(out, no_figures):
    """One row per component of the fit file's budget: its GUM type, and for each parameter its
    contribution sqrt(share) u_c and its share; then u_c, U and k of each parameter."""
    page = write_report(out, issue_date=DAY).read_text()
    fit = json.loads((out / "fit.json").read_text())
    unc = fit["uncertainty"]
    tables = re.findall(r'<table class="budget" id="budget-\d+">(.*?)</table>', page, re.S)
    assert len(tables) == 1                                   # 3 parameters: one table
    table = tables[0]
    rows = re.findall(r'<tr class="budget-row" data-component="([^"]*)"><td>([^<]*)</td><td>([^<]*)</td>'
                      r'<td>[^<]*</td><td>[^<]*</td>(.*?)</tr>', table)
    components = set().union(*(q["budget"] for q in unc["parameters"].values()))
    assert {html.unescape(r[0]) for r in rows} == components and len(rows) == len(components)
    types = {"statistical": "A", "reference_certificate": "B"}
    for comp, name, gum_type, cells in rows:
        assert name == comp and gum_type == types[comp]
        got = {html.unescape(p): (u, share) for p, u, share in re.findall(
            r'<td class="num" data-parameter="([^"]*)"><span class="u">([^<]*)</span>'
            r'(?: <span class="share">\(([^)]*)\)</span>)?</td>', cells)}
        assert set(got) == set(unc["parameters"]), got
        for param, q in unc["parameters"].items():
            share = q["budget"][comp]
            assert got[param] == (f"{math.sqrt(share) * q['u_combined']:.2g}", f"{100 * share:.2g} %"), (param, comp)
    total = re.search(r'<tr class="budget-total">(.*?)</tr>', table, re.S)[1]
    expanded = re.search(r'<tr class="budget-expanded">(.*?)</tr>', table, re.S)[1]
    for param, q in unc["parameters"].items():
        assert f'data-parameter="{param}">{q["u_combined"]:.2g}</td>' in total
        assert f'data-parameter="{param}">{q["U"]:.2g} (k = {q["k"]:g})</td>' in expanded
    # more parameters than fit side by side make further tables; a component a parameter's budget
    # lacks is "–" there
    doc = json.loads(json.dumps(fit))
    extra = {f"p{i}": dict(next(iter(unc["parameters"].values())), budget={"statistical": 1.0}) for i in range(3)}
    doc["uncertainty"]["parameters"].update(extra)
    doc["parameters"].update({n: dict(next(iter(fit["parameters"].values()))) for n in extra})
    (out / "fit.json").write_text(json.dumps(doc))
    page = write_report(out, issue_date=DAY).read_text()
    tables = re.findall(r'<table class="budget" id="budget-\d+">(.*?)</table>', page, re.S)
    assert len(tables) == 2 and 'data-parameter="p0"' in tables[0] and 'data-parameter="p2"' in tables[1]
    assert 'data-component="reference_certificate"' in tables[0]
    assert 'data-component="reference_certificate"' not in tables[1]     # in neither p1's nor p2's budget
    reference = re.search(r'data-component="reference_certificate">(.*?)</tr>', tables[0], re.S)[1]
    assert '<td class="num" data-parameter="p0"><span class="u">–</span></td>' in reference
    # a fit file without a budget says so instead of a table
    doc.pop("uncertainty")
    (out / "fit.json").write_text(json.dumps(doc))
    page = write_report(out, issue_date=DAY).read_text()
    assert '<table class="budget"' not in page and "carries no uncertainty budget" in page


def test_the_number_is_deterministic_and_unique(out, no_figures):
    first = re.search(r'id="certificate-number">([^<]*)<', write_report(out, issue_date=DAY).read_text())[1]
    again = re.search(r'id="certificate-number">([^<]*)<', write_report(out, issue_date=DAY).read_text())[1]
    other_day = re.search(r'id="certificate-number">([^<]*)<',
                          write_report(out, issue_date="2026-12-05").read_text())[1]
    doc = json.loads((out / "fit.json").read_text())
    doc["optimiser"]["time_s"] = 1.5                          # any change of the fit file
    (out / "fit.json").write_text(json.dumps(doc))
    other_fit = re.search(r'id="certificate-number">([^<]*)<', write_report(out, issue_date=DAY).read_text())[1]
    assert first == again and len({first, other_day, other_fit}) == 3
    assert first.startswith("GONIO-20261204-") and other_day.startswith("GONIO-20261205-")
    from gonio.core.errors import GonioError

    with pytest.raises(GonioError, match="not a date"):
        write_report(out, issue_date="04/12/2026")


def test_the_preview_caption_says_whether_a_measured_bsdf_was_given(out, no_figures):
    page = write_report(out).read_text()
    caption = re.search(r'alt="preview_side_by_side.png[^"]*".*?<figcaption>(.*?)</figcaption>', page, re.S)[1]
    assert "CIEDE2000 difference" in caption and "--measured" in caption
    preview = out / "render" / "preview" / "preview.json"
    doc = json.loads(preview.read_text())
    doc.update(delta_e={}, delta_e_mean=None, delta_e_p95=None)      # `gonio render --preview` alone
    preview.write_text(json.dumps(doc))
    page = write_report(out).read_text()
    caption = re.search(r'alt="preview_side_by_side.png[^"]*".*?<figcaption>(.*?)</figcaption>', page, re.S)[1]
    assert "no measured BSDF was given" in caption and "CIEDE2000 difference" not in caption
    assert "the fit alone" in text_of(section(page, "<h3>Preview renders", "</p>"))


def test_a_moved_report_folder_keeps_every_image(out, tmp_path, no_figures, monkeypatch):
    """The page embeds every image and report_files/ holds each of them; a folder moved after
    `gonio render` (its preview.json naming the old absolute path, or a path relative to another
    working folder) still finds its preview image beside preview.json."""
    path = write_report(out)
    page = path.read_text()
    names = re.findall(r'<img alt="([^":]+):', page)
    assert "preview_side_by_side.png" in names
    assert page.count('src="data:image/png;base64,') == len(names)
    assert not re.search(r'<img[^>]* src="(?!data:)', page)
    moved = tmp_path / "elsewhere" / "moved"
    moved.parent.mkdir()
    shutil.copytree(out, moved)                           # the old folder is still there, outside
    for name in names:
        assert (moved / "report_files" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    monkeypatch.chdir(tmp_path)
    page = write_report(moved).read_text()
    assert 'alt="preview_side_by_side.png' in page and "is missing" not in page
    doc = json.loads((moved / "render/preview/preview.json").read_text())
    doc["side_by_side_png"] = "out/render/preview/side_by_side.png"     # relative to where render ran
    (moved / "render/preview/preview.json").write_text(json.dumps(doc))
    monkeypatch.chdir(moved.parent)
    page = write_report(moved).read_text()
    assert 'alt="preview_side_by_side.png' in page and "is missing" not in page


# --------------------------------------------------------------------------- print
def _print_rules(style: str) -> tuple[str, str]:
    """(the @media print block, the rules outside it and @page)."""
    start = style.index("@media print{")
    depth, i = 0, start + len("@media print")
    while True:
        depth += {"{": 1, "}": -1}.get(style[i], 0)
        i += 1
        if depth == 0:
            break
    screen = style[:start] + style[i:]
    screen = re.sub(r"@page\s*\{.*?\}\}", "", screen, flags=re.S)
    return style[start:i], screen


def test_the_print_stylesheet_sets_no_font_under_8_pt(out, no_figures):
    page = write_report(out).read_text()
    style = page[page.index("<style>") + 7:page.index("</style>")]
    printed, screen = _print_rules(style)
    margin = re.search(r"@page\s*\{(.*?)\}\}", style, re.S)[1]
    sizes = re.findall(r"font-size:\s*([\d.]+)\s*([a-z%]+)", printed + margin)
    assert sizes and all(unit == "pt" and float(v) >= 8.0 for v, unit in sizes), sizes
    # a relative size of the screen rules is overridden in print by one in pt
    overridden = {sel.strip() for block in re.findall(r"([^{}]+)\{[^{}]*font-size", printed)
                  for sel in block.split(",")}
    for block in re.findall(r"([^{}]+)\{[^{}]*font-size", screen):
        for sel in block.split(","):
            assert sel.strip() in overridden, sel


def test_figures_print_with_text_of_at_least_8_pt(out, monkeypatch):
    """Every drawn figure, as saved, prints (at its own size, shrunk only to the A4 text width)
    with no text under 8 pt, tick labels included; and no two labels overlap."""
    seen = {}
    original = figs._save

    def check(fig):
        texts = figs._texts(fig)
        smallest = min(t.get_fontsize() for t in texts)
        overlaps = figs.text_overlaps(fig)
        data = original(fig)
        inches = figs.css_width(data) / 96.0
        seen[len(seen)] = (smallest * figs.printed_scale(inches), overlaps, inches)
        return data

    monkeypatch.setattr(figs, "_save", check)
    page = write_report(out).read_text()
    assert len(seen) == 7, seen
    for k, (pt, overlaps, inches) in seen.items():
        assert pt >= figs.MIN_PRINT_PT - 1e-6 and not overlaps, (k, pt, overlaps, inches)
    widths = [int(w) for w in re.findall(r'<img alt="[^"]*" width="(\d+)"', page)]
    assert len(widths) == 8 and all(w <= figs.PRINT_WIDTH_IN * 96 for w in widths[:-1]), widths


def _chromium():
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.slow
def test_the_report_prints_on_a4_with_page_x_of_y(out, tmp_path):
    """Headless Chromium (as tests/e2e/test_loop.py drives it) prints the report: more than one
    A4 page, each with the certificate's number and "Page k of N"; no text under 8 pt."""
    browser = _chromium()
    if browser is None:
        pytest.skip("Debian's chromium is not installed (`make chromium`)")
    path = write_report(out, issue_date=DAY)
    number = re.search(r'id="certificate-number">([^<]*)<', path.read_text())[1]
    pdf = tmp_path / "report.pdf"
    proc = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-sync",
                           "--disable-background-networking", "--disable-component-update",
                           f"--user-data-dir={tmp_path / 'p'}", "--no-pdf-header-footer", f"--print-to-pdf={pdf}",
                           path.as_uri()], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0 and pdf.read_bytes().startswith(b"%PDF"), proc.stderr[-2000:]
    pages = pdftext.read(pdf.read_bytes())
    assert len(pages) > 1
    for k, p in enumerate(pages, 1):
        words = " ".join(p.text.split())
        assert f"Page {k} of {len(pages)}" in words, (k, words[:300])
        assert number in words and f"Issued {DAY}" in words
    assert "End of certificate" in " ".join(pages[-1].text.split())
    smallest = min(size for p in pages for size, _ in p.sizes)
    assert smallest >= 8.0 - 0.05, [(s, t) for p in pages for s, t in p.sizes if s < 7.95][:5]
    if shutil.which("pdftotext"):                      # poppler reads the same pages and counters
        text = subprocess.run(["pdftotext", str(pdf), "-"], capture_output=True, text=True, check=True).stdout
        assert len(re.findall(r"Page \d+ of " + str(len(pages)), text)) == len(pages)


@pytest.mark.parametrize("measured", [True, False])
def test_the_preview_is_composed_to_print_legibly(out, monkeypatch, measured):
    """The preview's own images (fit; measured and CIEDE2000 with --measured) are composed by
    the report, titles and colour-bar labels at 8 pt or more as printed; the side-by-side PNG of
    `gonio render` (9.6 in wide: 6.7 pt titles on A4) is the fallback."""
    import matplotlib.pyplot as plt

    folder = out / "render" / "preview"
    names = {}
    for key in ("model_png", "measured_png", "delta_e_png"):
        fig, ax = plt.subplots(figsize=(1.28, 1.28), dpi=100)
        ax.imshow([[0.1, 0.9], [0.5, 0.3]])
        fig.savefig(folder / f"env_{key}", format="png")
        plt.close(fig)
        names[key] = f"env_{key}"
    doc = json.loads((folder / "preview.json").read_text())
    doc["images"] = {"env": names if measured else {"model_png": names["model_png"]}}
    if not measured:
        doc.update(delta_e={}, delta_e_mean=None, delta_e_p95=None)
    (folder / "preview.json").write_text(json.dumps(doc))
    monkeypatch.setattr(figs, "draw", lambda images, notes, name, fn, *args:
                        images.update(fn(*args)) if name == "preview_side_by_side.png" else None)
    seen = []
    original = figs._save

    def check(fig):
        smallest = min(t.get_fontsize() for t in figs._texts(fig))
        titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
        data = original(fig)
        seen.append((smallest * figs.printed_scale(figs.css_width(data) / 96.0), titles))
        return data

    monkeypatch.setattr(figs, "_save", check)
    page = write_report(out).read_text()
    assert len(seen) == 1 and seen[0][0] >= figs.MIN_PRINT_PT - 1e-6, seen
    assert seen[0][1] == (["fitted model (env)", "measured (env)", "CIEDE2000: mean 1.5, p95 3"] if measured
                          else ["fitted model (env)"]), seen
    assert 'alt="preview_side_by_side.png' in page
    drawn = (out / "report_files" / "preview_side_by_side.png").read_bytes()
    assert drawn != (folder / "side_by_side.png").read_bytes()


def test_the_certificates_settings_are_declared_and_checked(tmp_path):
    """The conditions, laboratory, customer and approver are settings the capture records
    (session.toml, dataset.nc's settings attribute): declared, checked, misspellings refused."""
    from gonio.bench.settings import load_settings
    from gonio.core.errors import GonioError

    f = tmp_path / "lab.toml"
    f.write_text('[conditions]\npolarisation = "unpolarised"\ntemperature_c = 23.1\nhumidity_pct = 45\n'
                 '[session]\ninstitution = "Lab, 1 Street"\ncustomer = "ACME"\napprover = "X"\napprover_role = "QM"\n')
    s = load_settings(f)
    assert s["conditions"] == {"polarisation": "unpolarised", "temperature_c": 23.1, "humidity_pct": 45}
    assert s["session"]["approver_role"] == "QM"
    for text, match in (("[conditions]\nhumidity_pct = 145\n", "conditions.humidity_pct"),
                        ("[conditions]\ntemperature_c = \"warm\"\n", "conditions.temperature_c"),
                        ("[conditions]\ntemprature_c = 20\n", "did you mean temperature_c?"),
                        ("[session]\ncustomer = \"\\u001b[2J\"\n", "printable text")):
        f.write_text(text)
        with pytest.raises(GonioError, match=re.escape(match)):
            load_settings(f)


def test_the_report_says_its_progress_figure_by_figure(out, no_figures):
    """write_report(progress=) is called before each figure and once at the end (gonio report
    draws a bar with steps and time left on a terminal: issue 41, every step over ~2 s)."""
    calls = []
    write_report(out, issue_date=DAY, progress=lambda done, total, label: calls.append((done, total, label)))
    assert len(calls) >= 3
    totals = {t for _, t, _ in calls}
    assert len(totals) == 1 and calls[-1][0] == calls[-1][1] == totals.pop()
    assert [d for d, _, _ in calls] == list(range(len(calls)))
    assert all(label.startswith("figure ") for _, _, label in calls[:-1])
