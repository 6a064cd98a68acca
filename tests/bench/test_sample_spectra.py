"""Samples with spectra (issue 39): a sample TOML gives a colour parameter as a spectrum
(``[params.diffuse_reflectance]`` with ``wavelengths`` in nm and ``values``); the RGB simulator
gets its linear sRGB under D65 (colour-science), the spectrum is kept, bad tables get one line."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.bench.samples import load_sample
from gonio.core.errors import GonioError

HEAD = 'model = "roughplastic"\n[options]\ndistribution = "ggx"\n[params]\nalpha = 0.15\nint_ior = 1.5\n'


def _sample(tmp_path, table: str):
    path = tmp_path / "sample.toml"
    path.write_text(HEAD + "[params.diffuse_reflectance]\n" + table)
    return load_sample(path)


def test_a_spectrum_becomes_its_linear_srgb_and_is_kept(tmp_path):
    wl = list(range(400, 701, 10))
    flat = _sample(tmp_path, f"wavelengths = {wl}\nvalues = {[0.5] * len(wl)}\n")
    # a flat reflector under D65 (sRGB's own white) is neutral: R = G = B = 0.5 (to the 400-700 nm cut, 0.3 %)
    np.testing.assert_allclose(flat["params"]["diffuse_reflectance"], [0.5, 0.5, 0.5], rtol=3e-3)
    assert flat["spectra"]["diffuse_reflectance"]["wavelengths"][0] == 400.0
    red = _sample(tmp_path, "wavelengths = [400, 450, 500, 550, 600, 650, 700]\n"
                            "values = [0.05, 0.06, 0.08, 0.15, 0.45, 0.6, 0.62]\n")
    r, g, b = red["params"]["diffuse_reflectance"]
    assert r > 3 * g > 3 * b > 0          # a red paint's spectrum stays red


@pytest.mark.parametrize("table, says", [
    ("wavelengths = [400, 500, 600, 700]\nvalues = [0.1, 0.2, 0.3]\n", "3 values for 4 wavelengths"),
    ("wavelengths = [-400, 500, 600, 700]\nvalues = [0.1, 0.2, 0.3, 0.4]\n", "200-2500 nm"),
    ("wavelengths = [400, 500, 500, 700]\nvalues = [0.1, 0.2, 0.3, 0.4]\n", "increasing"),
    ("wavelengths = [400, 500, 600, 700]\nvalues = [0.1, 0.2, 1.3, 0.4]\n", r"in \[0, 1\]"),
    ("wavelengths = [400, 500, 600, 700]\nvalues = [0.1, nan, 0.3, 0.4]\n", "finite"),
    ("wavelengths = [400, 450, 500, 550]\nvalues = [0.1, 0.2, 0.3, 0.4]\n", "do not cover the visible"),
    ("wavelengths = [400, 500, 600, 700]\nvalues = [0.1, 0.2, 0.3, 0.4]\nunits = 'nm'\n", "takes wavelengths"),
    ("wavelengths = ['a', 'b', 'c']\nvalues = [0.1, 0.2, 0.3]\n", "diffuse_reflectance"),
])
def test_bad_spectra_get_one_line(tmp_path, table, says):
    with pytest.raises(GonioError, match=says) as info:
        _sample(tmp_path, table)
    assert "\n" not in str(info.value)


def test_a_scalar_parameter_is_no_spectrum(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text('model = "roughplastic"\n[params.alpha]\nwavelengths = [400, 500, 600, 700]\n'
                    'values = [0.1, 0.2, 0.3, 0.4]\n')
    with pytest.raises(GonioError, match="alpha is one number"):
        load_sample(path)
