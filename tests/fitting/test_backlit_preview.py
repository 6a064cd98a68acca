"""The backlit preview (issue 37): a lamp behind the sample, the camera in front."""

import numpy as np
import pytest

import gonio.models as gm

mi = pytest.importorskip("mitsuba")

from gonio.fitting.render.preview import backlit_png, render_backlit  # noqa: E402


def test_backlit_diffuser_is_linear_in_tau_and_the_backlight_shows_around(tmp_path):
    d = gm.get("difftrans")
    half = render_backlit(d.to_mitsuba({"transmittance": [0.5] * 3}), 32, 16)
    full = render_backlit(d.to_mitsuba({"transmittance": [1.0] * 3}), 32, 16)
    # same seed, f_t = tau / pi: the panel's radiance doubles with tau, to rounding
    np.testing.assert_allclose(full[12:20, 12:20], 2.0 * half[12:20, 12:20], rtol=1e-5)
    # outside the panel the camera sees the checkered backlight itself: radiance 1 or 0.1
    corner = full[0, 0, 1]
    assert corner == pytest.approx(1.0, rel=1e-6) or corner == pytest.approx(0.1, rel=1e-6)
    # a frosted glass blurs the checks that a nearly clear film keeps: less contrast across the panel
    rd = gm.get("roughdielectric", distribution="beckmann")
    frosted = render_backlit(rd.to_mitsuba({"alpha": 0.5, "int_ior": 1.5}), 32, 16)[10:22, 10:22, 1]
    clear = render_backlit(rd.to_mitsuba({"alpha": 0.02, "int_ior": 1.5}), 32, 16)[10:22, 10:22, 1]
    assert np.percentile(frosted, 90) / np.percentile(frosted, 10) < 0.5 * np.percentile(clear, 90) / np.percentile(clear, 10)
    path = backlit_png([(d, {"transmittance": [0.8] * 3})], tmp_path / "backlit.png", size=16, spp=4)
    assert (tmp_path / "backlit.png").stat().st_size > 100 and path.endswith("backlit.png")
