"""Issue 39's proof: a simulated spectral capture of a coloured lacquer recovers its alpha within
its uncertainty. The red lacquer (gonio/cli/samples/red-lacquer.toml: roughplastic, GGX alpha
0.12, int_ior 1.5, diffuse albedo a 400-700 nm spectrum) is captured through the simulated
monochromator with the ``spectral`` preset (the quick geometry x 400-700 nm every 50 nm),
exported (brdf(point, wavelength)) and fitted with one diffuse albedo per wavelength, as
``gonio fit dataset.nc`` fits it: with the file's own uncertainty budget."""

import numpy as np
import pytest

from gonio.bench.dataset.export import export
from gonio.bench.dataset.reader import open_fit_input
from gonio.bench.plan.plans import load_plan
from gonio.bench.samples import load_sample
from gonio.bench.settings import default_settings
from gonio.cli.capture import capture_sim
from gonio.cli.fit import fit_dataset
from gonio.fitting import load_dataset

LACQUER = "gonio/cli/samples/red-lacquer.toml"


@pytest.mark.long        # 210 points and a 7-channel fit: about 25 s
def test_a_spectral_capture_of_a_lacquer_recovers_alpha(tmp_path):
    from pathlib import Path

    sample = load_sample(Path(__file__).parents[2] / LACQUER)
    settings = {**default_settings(), "monochromator": {}}
    summary = capture_sim(tmp_path / "s", sample=sample, plan=load_plan("spectral"), seed=11, settings=settings,
                          progress=False)
    assert summary.complete and summary.n_done == 210
    path = export(tmp_path / "s")
    meas = load_dataset(path)
    wl = np.arange(400.0, 701.0, 50.0)
    assert meas.attrs["wavelengths_nm"] == wl.tolist() and meas.n_points == 30
    _, doc, _ = fit_dataset(open_fit_input(path, seed=11), model=sample["model"], options=sample["options"], seed=11)
    assert "reference_certificate" in doc["uncertainty"]["components"]
    par = doc["parameters"]
    alpha = par["alpha"]
    # within its uncertainty: the expanded U (k = 2) and 3 standard uncertainties
    assert abs(alpha["value"] - 0.12) <= alpha["U"], alpha
    assert abs(alpha["value"] - 0.12) < 3 * alpha["std"], alpha
    assert abs(par["int_ior"]["value"] - 1.5) < 3 * par["int_ior"]["std"]
    spectrum = sample["spectra"]["diffuse_reflectance"]
    for nm in wl:                                  # the albedo spectrum, one channel per wavelength
        p, truth = par[f"diffuse_reflectance[{nm:g}nm]"], np.interp(nm, spectrum["wavelengths"], spectrum["values"])
        assert abs(p["value"] - truth) < 3 * p["std"], (nm, p, truth)
    assert 0.5 < doc["goodness"]["chi2_dof"] < 1.5
