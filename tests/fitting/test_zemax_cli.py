"""Zemax tabular BSDF through the command line (issue 37): `gonio fit FILE.bsdf` tells a Zemax
file from an RGL one by its content, and `gonio convert FIT --to zemax` writes files that read
back as the model's values (both sides for a model that transmits)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import gonio.models as gm
from gonio.cli.main import main
from gonio.fitting.formats.zemax import read_zemax, zemax_measurements

EXAMPLE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "zemax"


def _fit_file(path: Path, name: str, options: dict, params: dict) -> Path:
    from gonio.fitting.formats.fitfile import fit_document
    from gonio.fitting import fit, write_json_atomic
    from gonio.perf.fit import simulate_capture

    model = gm.get(name, **options)
    meas, _ = simulate_capture(model, params, 80, np.random.default_rng(2))
    result = fit(meas, model, rng=np.random.default_rng(0))
    return write_json_atomic(path, fit_document(result, meas, seed=0))


def test_convert_to_zemax_writes_what_the_model_gives(tmp_path, capsys):
    fit_path = _fit_file(tmp_path / "fit.json", "roughplastic", {"distribution": "ggx"},
                         {"diffuse_reflectance": np.array([0.5, 0.4, 0.3]), "alpha": 0.2, "int_ior": 1.5})
    assert main(["convert", str(fit_path), "--to", "zemax", "--out", str(tmp_path / "out" / "paint.bsdf")]) == 0
    assert "1 Zemax tabular BSDF file(s)" in capsys.readouterr().out
    written = tmp_path / "out" / "paint_brdf.bsdf"
    table = read_zemax(written)
    assert table.scatter_type == "BRDF"
    meas = zemax_measurements(written)
    doc = json.loads(fit_path.read_text())
    model = gm.get("roughplastic", distribution="ggx")
    params = {n: (np.array([doc["parameters"][f"{n}[{c}]"]["value"] for c in "RGB"])
                  if f"{n}[R]" in doc["parameters"] else doc["parameters"][n]["value"])
              for n in ("diffuse_reflectance", "alpha", "int_ior")}
    luminance = model.eval(meas.wi, meas.wo, params) @ np.array([0.2126, 0.7152, 0.0722])
    np.testing.assert_allclose(meas.brdf[:, 0], luminance, rtol=1e-5, atol=1e-9)


def test_fit_reads_a_zemax_file_by_its_content(tmp_path):
    if not EXAMPLE.is_dir() or not any(EXAMPLE.iterdir()):
        pytest.skip("../shared/data/zemax is not beside this checkout")
    src = next(p for p in sorted(EXAMPLE.iterdir()) if p.is_file())
    renamed = tmp_path / "example.bsdf"          # an RGL-looking name: the content decides
    renamed.write_bytes(src.read_bytes())
    out = tmp_path / "fit.json"
    assert main(["fit", str(renamed), "--model", "diffuse", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["model"]["name"] == "diffuse"


def test_a_dataset_is_not_converted_to_zemax(tmp_path, capsys):
    bad = tmp_path / "dataset.nc"
    bad.write_bytes(b"CDF\x01")
    assert main(["convert", str(bad), "--to", "zemax", "--out", str(tmp_path / "z.bsdf")]) == 2
    assert "--to zemax converts a fit file" in capsys.readouterr().err
    assert not any(tmp_path.glob("z*"))
