"""PAB-Opto files as Radiance's ``pabopto2bsdf`` reads them.

Radiance is not installable here (no Debian package in bookworm), so :func:`read_pabopto`
re-implements the reader's rules from ``src/cv/pabopto2bsdf.c`` (init_pabopto_inp,
add_pabopto_inp) and ``bsdfrep.c`` (add_bsdf_data): header lines are those whose first
character is ``#``, each parsed as sscanf does with the keyword right after the ``#``
(``format: theta phi %s``, ``colorimetry: %s``, ``intheta %lf``, ``inphi %lf``, ``upphi %lf``,
``sample_name "%[^"]"``); unknown ``#`` lines are skipped; the data are whitespace-separated
numbers, 2 angles + 3 values per record under ``colorimetry: CIE-XYZ``; every phi gets
90 - upphi added; a direction is (sin t cos p, sin t sin p, cos t); BRDF values become the DSF
f_r cos(theta_out); the incident file is refused without a format or an incident angle.
"""

import re

import numpy as np
import pytest

import gonio.models as gm
from gonio.cli import main as cli
from gonio.fitting import Measurements, fit, fit_document, write_json_atomic
from gonio.fitting.formats import model_pabopto, pabopto_files, write_pabopto
from gonio.fitting.formats.pabopto import SRGB_TO_XYZ
from gonio.core.geometry import directions_deg


def read_pabopto(text):
    """(header dict, incident direction, outgoing directions (N, 3), values (N, nspec), DSF of Y)."""
    head = {"isDSF": -1, "nspec": 0, "up_phi": 0.0, "theta": -10001.0, "phi": -10001.0}
    lines = text.splitlines(keepends=True)
    k = 0
    while k < len(lines) and lines[k].startswith("#"):
        buf = lines[k][1:]
        k += 1
        if m := re.match(r'sample_name "([^"]*)"', buf):
            head["name"] = m.group(1)
        elif m := re.match(r"colorimetry: (\S+)", buf):
            head["nspec"] = {"CIE-XYZ": 3, "CIE-Y": 1}.get(m.group(1).upper(), head["nspec"])
        elif m := re.match(r"format: theta phi (\S+)", buf):
            head["isDSF"] = 1 if m.group(1).upper() == "DSF" else 0 if m.group(1).upper() in ("BSDF", "BRDF", "BTDF") else -1
        elif m := re.match(r"(upphi|intheta|inphi) ([-+0-9.eE]+)", buf):
            head[{"upphi": "up_phi", "intheta": "theta", "inphi": "phi"}[m.group(1)]] = float(m.group(2))
    assert head["isDSF"] >= 0, "unknown format"
    assert head["theta"] > -10000 and head["phi"] > -10000, "unknown incident angle"
    numbers = np.array("".join(lines[k:]).split(), float)
    n_val = max(head["nspec"], 1)
    rec = numbers.reshape(-1, 2 + n_val)
    turn = 90.0 - head["up_phi"]
    wi = directions_deg(head["theta"], head["phi"] + turn)
    wo = directions_deg(rec[:, 0], rec[:, 1] + turn)
    y = rec[:, 2 + (head["nspec"] == 3)]
    dsf = y if head["isDSF"] else y * wo[:, 2]
    return head, wi, wo, rec[:, 2:], dsf


def _meas():
    rng = np.random.default_rng(3)
    wi = directions_deg(np.repeat([0.0, 30.0, 60.0], 8), np.repeat([0.0, 0.0, 45.0], 8))
    wo = directions_deg(rng.uniform(0, 85, 24), rng.uniform(-180, 180, 24))
    f = gm.get("roughplastic", distribution="ggx").eval(wi, wo, {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": 0.2})
    use = np.ones(f.shape, bool)
    use[5, 1] = False                                     # a flagged value: its point is left out
    return Measurements(wi, wo, f, 0.01 * f, use)


def test_measured_files_read_back_as_radiance_reads_them(tmp_path):
    meas = _meas()
    paths = write_pabopto(tmp_path, meas, sample_name='lab "A"\nsample')
    assert len(paths) == 3                                # one file per incident direction
    got_wo, got_xyz = [], []
    for p in paths:
        text = p.read_text(encoding="ascii")
        assert text.startswith('#sample_name "lab Asample"\n#format: theta phi BRDF\n#colorimetry: CIE-XYZ\n')
        head, wi, wo, values, dsf = read_pabopto(text)
        assert head["up_phi"] == 90.0 and head["nspec"] == 3
        match = np.all(np.isclose(meas.wi, wi, atol=1e-9), axis=1)
        assert match.sum() in (7, 8)                     # the file's incident direction is the data's
        np.testing.assert_allclose(dsf, values[:, 1] * wo[:, 2])
        got_wo.append(wo)
        got_xyz.append(values)
    got_wo, got_xyz = np.concatenate(got_wo), np.concatenate(got_xyz)
    keep = meas.use.all(axis=1)
    assert got_wo.shape == (keep.sum(), 3)
    want = meas.brdf[keep] @ SRGB_TO_XYZ.T
    for w, v in zip(meas.wo[keep], want):                 # every kept point, once, with its XYZ to 9 digits
        row = np.flatnonzero(np.all(np.isclose(got_wo, w, atol=1e-6), axis=1))
        assert row.size == 1
        np.testing.assert_allclose(got_xyz[row[0]], v, rtol=5e-9)      # %.9g: half a unit of the 9th digit


def test_xyz_data_are_written_as_measured_and_bad_directions_refused():
    xyz = np.array([[0.1, 0.2, 0.3], [0.2, 0.3, 0.4]])
    files = pabopto_files([30, 30], [0, 0], [20, 40], [180, -90], xyz)
    (text,) = files.values()
    _, _, wo, values, _ = read_pabopto(text)
    np.testing.assert_allclose(values, xyz)
    np.testing.assert_allclose(wo, directions_deg([20, 40], [180, 270]), atol=1e-9)
    with pytest.raises(ValueError, match="above the surface"):
        pabopto_files([30], [0], [95], [0], xyz[:1])
    with pytest.raises(ValueError, match="finite"):
        pabopto_files([30], [0], [20], [0], [[np.nan, 1, 1]])


def test_model_grid_of_a_lambertian():
    """f_r = rho / pi everywhere: Y = (0.2126, 0.7152, 0.0722) . rho / pi (IEC 61966-2-1's Y row)."""
    rho = np.array([0.6, 0.4, 0.2])
    files = model_pabopto(gm.get("diffuse"), {"reflectance": rho}, theta_i=(0, 40), theta_step=15, phi_step=90)
    assert len(files) == 2
    for text in files.values():
        _, _, wo, values, _ = read_pabopto(text)
        assert wo.shape == (6 * 4, 3)
        np.testing.assert_allclose(values[:, 1], SRGB_TO_XYZ[1] @ rho / np.pi, rtol=5e-9)   # %.9g


def test_convert_cli_writes_a_folder_from_a_fit(tmp_path, capsys):
    meas = _meas()
    result = fit(meas, gm.get("diffuse"), rng=np.random.default_rng(0), n_starts=2)
    fit_path = write_json_atomic(tmp_path / "fit.json", fit_document(result, meas, seed=0))
    out = tmp_path / "radiance" / "pab"
    assert cli.main(["convert", str(fit_path), "--to", "pabopto", "--out", str(out)]) == 0
    assert "6 PAB-Opto files" in capsys.readouterr().out
    texts = [p.read_text() for p in sorted(out.glob("gonio_t*.dat"))]
    assert len(texts) == 6 and all(read_pabopto(t)[0]["theta"] in (0, 15, 30, 45, 60, 75) for t in texts)
    (tmp_path / "afile").write_text("x")
    assert cli.main(["convert", str(fit_path), "--to", "pabopto", "--out", str(tmp_path / "afile")]) == 2
    assert "not a folder" in capsys.readouterr().err
