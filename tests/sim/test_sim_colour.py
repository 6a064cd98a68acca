"""The simulated camera's colour (gonio/sim/physics/colour.py): sensitivities -> matrices -> DNG tags LibRaw reads."""

import io

import colour
import numpy as np
import pytest
import rawpy

from gonio.sim import SensorModel
from gonio.sim.physics.colour import TABLES, camera_colour, computed_tables, luther_error, mallett_fidelity, srgb_matrices
from gonio.sim.physics.sensor import encode_dng

NIKON = camera_colour("Nikon 5100 (NPL)")


def test_the_camera_matrix_is_a_real_cameras_not_the_identity():
    a = NIKON.balanced
    np.testing.assert_allclose(a.sum(1), 1.0, atol=1e-12)           # a neutral stays neutral
    assert np.abs(a - np.eye(3)).max() > 0.2                          # the D5100 mixes channels strongly
    assert NIKON.neutral.max() == 1.0 and NIKON.neutral.min() < 0.7  # red is ~0.58 of green under D65
    assert camera_colour("identity").balanced.tolist() == np.eye(3).tolist()


#: how far a recomputed entry may sit from the tabulated one, in units of eps times the
#: largest entry of its matrix. The same formulas summed in another order (another BLAS
#: kernel: OpenBLAS picks its own for AVX2 and for AVX-512) round differently, by units in
#: the last place of the largest terms summed, and these land on the small entries too.
#: A priori (Higham, Accuracy and Stability of Numerical Algorithms, 2nd ed., 2002: |dC| <=
#: gamma_n |A||B| for a product, sec. 3.5; an LU-based inverse within ~n gamma_n
#: |X||L||U||X|, ch. 14), the Bradford matrix M^-1 diag(r) M lies within 10.5 eps x max|C|
#: of its exact value, so two evaluations within 21. Measured: tabulated on an AVX2 machine
#: and recomputed on an AVX-512 one (2026-12-03), 0.95 eps x max|C| apart (its 0.0229 entry
#: by 2.4e-15 relative), and equal with OPENBLAS_CORETYPE=Haswell. A change of a constant in
#: colour-science moves these numbers by orders of magnitude more than 24 eps (5.6e-15).
ROUNDING_EPS = 24


def _same_up_to_rounding(stored, fresh, what):
    stored, fresh = np.asarray(stored, float), np.asarray(fresh, float)
    assert stored.shape == fresh.shape, what
    bound = ROUNDING_EPS * np.finfo(float).eps * np.abs(fresh).max()
    np.testing.assert_allclose(stored, fresh, rtol=0, atol=bound, err_msg=what)


def test_the_tabulated_colour_numbers_are_colour_sciences():
    """sim/data/colour_tables.json (read by every simulated capture instead of importing
    colour-science) holds what the installed colour-science computes, up to the rounding of
    another summation order (:data:`ROUNDING_EPS`); a new release that changes a number
    fails here: rewrite it with ``python -m gonio.sim.physics.colour --tabulate``."""
    import json
    import subprocess
    import sys

    stored, fresh = json.loads(TABLES.read_text()), computed_tables()
    assert stored.keys() == fresh.keys() and stored["cameras"].keys() == fresh["cameras"].keys()
    for key in ("srgb_to_xyz", "bradford_d65_to_d50"):
        _same_up_to_rounding(stored[key], fresh[key], key)
    for name, cam in fresh["cameras"].items():
        for key, value in cam.items():
            _same_up_to_rounding(stored["cameras"][name][key], value, f"{name}: {key}")
    # the simulator's start really does without colour-science (and so without matplotlib)
    probe = ("import sys\nfrom gonio.sim.physics.colour import camera_colour\nc = camera_colour()\n"
             "c.color_matrix, c.forward_matrix\nprint('colour' in sys.modules, 'matplotlib' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.stdout.split() == ["False", "False"], out.stderr[-2000:]


def test_spectral_integration_of_a_mallett_spectrum_equals_the_matrix():
    """The 3x3 is exact for the simulated surfaces: their spectra are linear in rho (Mallett 2019)."""
    basis = colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019
    rho = np.array([0.6, 0.1, 0.05])
    sd = colour.SpectralDistribution(basis.values @ rho, basis.wavelengths)
    np.testing.assert_allclose(NIKON.white_balanced(sd)[0], NIKON.balanced @ rho, rtol=1e-8)
    # and the spectrum's own sRGB is rho to well under a just-noticeable difference (Mallett 2019)
    assert mallett_fidelity(rho) < 0.05


def test_luther_error_is_zero_only_for_the_identity():
    """A 3x3 cannot map a real camera's response to a metamer-free colorimeter: the 24 Ohta
    ColorChecker spectra are off by a few CIEDE2000 through the D5100's matrix."""
    assert luther_error(camera_colour("identity")).max() == 0.0
    err = luther_error(NIKON)
    assert err.shape == (24,) and 0.2 < err.mean() < 5.0


def test_dng_declares_the_matrices_libraw_reads():
    s = SensorModel(seed=3)
    raw = s.expose(np.full((s.height, s.width, 3), 0.2), 0.01, 0.01, np.random.default_rng(0))
    data = encode_dng(raw, black=s.black, white=s.white, exposure=0.01, colour=s.colour)
    with rawpy.imread(io.BytesIO(data)) as r:
        # LibRaw's camera -> sRGB (its own 6-digit sRGB constants and float32: agreement to ~2e-4)
        np.testing.assert_allclose(np.asarray(r.color_matrix)[:3, :3], NIKON.srgb_from_cam, atol=5e-4)
        wb = np.asarray(r.camera_whitebalance[:3])
        np.testing.assert_allclose(wb / wb[1], NIKON.neutral[1] / NIKON.neutral, rtol=1e-5)   # 1 / AsShotNeutral
    # ColorMatrix1 maps the D65 white (Y = 1) onto AsShotNeutral; ForwardMatrix1 maps neutral to D50
    d65 = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])
    d50 = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D50"])
    np.testing.assert_allclose(NIKON.color_matrix @ d65, NIKON.neutral, rtol=1e-4)
    np.testing.assert_allclose(NIKON.forward_matrix @ np.ones(3), d50, rtol=1e-4)
    to_xyz, to_rgb = srgb_matrices()
    np.testing.assert_allclose(to_xyz @ to_rgb, np.eye(3), atol=1e-14)


def test_sensor_records_the_sRGB_radiance_through_the_camera():
    """Mean raw per channel of a uniform sRGB patch = N A rho x the sensitivity scale."""
    s = SensorModel(width=64, height=48, seed=0, prnu=0.0, dsnu=0.0, dark_current=0.0)
    rho = np.array([0.6, 0.1, 0.05])
    mu = s.mean_electrons(np.broadcast_to(rho, (s.height, s.width, 3)), 0.01, 0.01)
    got = [mu[s.channel_map == k].mean() for k in range(3)]
    np.testing.assert_allclose(got, NIKON.cam_from_srgb @ rho * 0.01 * 0.01 * s.sensitivity, rtol=1e-12)


def test_unknown_camera_is_refused():
    with pytest.raises(ValueError, match="unknown camera"):
        SensorModel(camera="Brownie")
