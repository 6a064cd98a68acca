"""Sensor model: photon transfer curve, dark statistics, DNG round trip through rawpy."""

import hashlib

import numpy as np
import pytest
import rawpy

from gonio.sim import SensorModel
from gonio.sim.physics.sensor import encode_dng, write_dng


def test_photon_transfer_curve_slope_is_inverse_gain():
    s = SensorModel(width=128, height=96, seed=2)
    flat = np.full((s.height, s.width, 3), 1.0 / np.pi)
    means, variances = [], []
    for k, t in enumerate(np.geomspace(2e-4, 1.8e-2, 8)):
        a = s.expose(flat, 0.01, t, np.random.default_rng([k, 0])).astype(float)
        b = s.expose(flat, 0.01, t, np.random.default_rng([k, 1])).astype(float)
        g = s.channel_map == 1
        means.append((0.5 * (a + b))[g].mean() - s.black)
        variances.append(0.5 * (a - b)[g].var())       # the difference cancels PRNU and DSNU
    slope, _ = np.polyfit(means, variances, 1)
    assert slope == pytest.approx(1 / s.gain, rel=0.05)
    assert max(means) < 0.95 * (s.white - s.black)            # stayed below saturation


def test_half_well_at_10ms_for_white_lambertian():
    """Green (the most sensitive channel) fills half the well; with the identity camera every
    channel does; with the default (Nikon D5100) red and blue reach AsShotNeutral times that."""
    for camera in ("identity", "Nikon 5100 (NPL)"):
        s = SensorModel(seed=0, camera=camera)
        flat = np.full((s.height, s.width, 3), 1.0 / np.pi)
        raw = s.expose(flat, 0.01, 0.01, np.random.default_rng(0)).astype(float)
        fill = [(raw[s.channel_map == k].mean() - s.black) * s.gain / s.full_well for k in range(3)]
        np.testing.assert_allclose(fill, 0.5 * s.colour.neutral, rtol=0.01)
        assert s.colour.neutral[1] == 1.0


def test_dark_frames():
    s = SensorModel(width=128, height=96, seed=4)
    zero = np.zeros((s.height, s.width, 3))
    t = 2.0
    frames = np.array([s.expose(zero, 0.0, t, np.random.default_rng([9, i])) for i in range(40)], float)
    mean_img = frames.mean(0)
    expected = s.black + (s.dark_current * t + s.dsnu_map) / s.gain
    assert (mean_img - expected).mean() == pytest.approx(0.0, abs=0.05)
    # fixed pattern: the per-pixel mean follows the DSNU map
    assert np.corrcoef(mean_img.ravel(), s.dsnu_map.ravel())[0, 1] > 0.4
    temporal = frames.var(0, ddof=1).mean()
    assert temporal == pytest.approx((s.dark_current * t + s.read_noise ** 2) / s.gain ** 2 + 1 / 12, rel=0.1)


def test_saturation_clips_at_white_level():
    s = SensorModel(seed=0)
    flat = np.full((s.height, s.width, 3), 1.0)
    raw = s.expose(flat, 0.01, 1.0, np.random.default_rng(0))
    assert raw.dtype == np.uint16 and (raw == s.white).all()


@pytest.mark.parametrize("bits", [12, 14])
def test_dng_round_trip_through_rawpy(tmp_path, bits):
    s = SensorModel(bits=bits, black=256, seed=1)
    flat = np.random.default_rng(0).uniform(0, 0.5, (s.height, s.width, 3))
    raw = s.expose(flat, 0.01, 0.01, np.random.default_rng(1))
    data = encode_dng(raw, black=s.black, white=s.white, exposure=0.01)
    path = tmp_path / "frame.dng"
    digest = write_dng(path, data)
    assert digest == hashlib.sha256(path.read_bytes()).hexdigest()
    assert not (tmp_path / "frame.dng.part").exists()
    with rawpy.imread(str(path)) as r:
        np.testing.assert_array_equal(r.raw_image_visible, raw)
        assert list(r.black_level_per_channel) == [s.black] * 4
        assert r.white_level == s.white
        assert r.color_desc.decode()[:3] == "RGB"
        pattern = "".join(r.color_desc.decode()[i] for i in r.raw_pattern.ravel())
        assert pattern[:4] == "RGBG"[0] + "G" + "G" + "B" or pattern == "RGGB"
    assert encode_dng(raw, black=s.black, white=s.white, exposure=0.01) == data   # deterministic
