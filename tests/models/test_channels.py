"""The channels are declared once (gonio.core.channels): RGB today, wavelengths next.

Reference values: Mitsuba 3's ``diffuse`` BSDF gives rho / pi at normal incidence and exit
(mitsuba3 src/bsdfs/diffuse.cpp); an irregular spectrum is interpolated linearly between its
wavelengths (src/spectra/irregular.cpp), so 500 nm between 0.2 at 450 nm and 0.5 at 550 nm is 0.35.
"""

from __future__ import annotations

import math

import pytest

from gonio.core.channels import CHANNELS, COLOUR_SPACE_CHANNELS, RGB, Channels, colour_space, spectral
from gonio.models.base import rgb


def test_rgb_is_the_declaration_every_layer_reads():
    assert CHANNELS == RGB.n == 3 and RGB.names == ("R", "G", "B") and RGB.variant_suffix == "rgb"
    assert COLOUR_SPACE_CHANNELS["xyz"] == ("X", "Y", "Z") and colour_space("srgb").names == RGB.names
    assert rgb(0.25) == {"type": "rgb", "value": [0.25, 0.25, 0.25]}
    with pytest.raises(ValueError, match="unknown colour space 'lab'"):
        colour_space("lab")
    with pytest.raises(ValueError, match="2 values for 3 channels"):
        RGB.mitsuba([1, 2])


@pytest.mark.parametrize("bad", [[], [550, 450], [550, 550], [100.0], [float("nan")]])
def test_spectral_channels_refuse_impossible_wavelengths(bad):
    with pytest.raises(ValueError):
        spectral(bad)
    with pytest.raises(ValueError, match="no wavelengths"):
        Channels(("R",), "camera", (550.0,))


def test_a_spectral_value_is_a_spectrum_mitsuba_renders_at_each_wavelength():
    mi = pytest.importorskip("mitsuba")
    if "scalar_spectral" not in mi.variants():
        pytest.skip("Mitsuba has no scalar_spectral variant here")
    c = spectral([450, 550, 650])
    assert c.n == 3 and c.names == ("450nm", "550nm", "650nm") and c.variant_suffix == "spectral"
    prev = mi.variant()          # scoped_set_variant cannot restore "no variant" (Mitsuba 3.9)
    mi.set_variant("scalar_spectral")
    try:
        bsdf = mi.load_dict({"type": "diffuse", "reflectance": c.mitsuba([0.2, 0.5, 0.8])})
        si = mi.SurfaceInteraction3f()
        si.sh_frame = mi.Frame3f(mi.Normal3f(0, 0, 1))
        si.wi = mi.Vector3f(0, 0, 1)
        si.wavelengths = mi.Spectrum([450, 550, 650, 500])
        v = [float(x) * math.pi for x in bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(0, 0, 1))]
    finally:
        if prev:
            mi.set_variant(prev)
    assert v == pytest.approx([0.2, 0.5, 0.8, 0.35], rel=1e-6)
