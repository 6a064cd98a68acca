"""Real materials (issue 16): an RGL file fitted on its own measured layout with solid-angle
weights, and the preview's noise floor from matched seeds. The RGL tests use the three
RGL-EPFL materials in ../shared/data/rgl when they are there."""

from pathlib import Path

import numpy as np
import pytest

import gonio.models as gm

RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"
needs_rgl = pytest.mark.skipif(not (RGL / "vch_golden_yellow_rgb.bsdf").exists(), reason="no RGL data here")


def test_noise_floor_uses_matched_seeds(tmp_path):
    """The same BSDF as 'model' and 'measured': with matched seeds the renders are identical,
    so the noise floor (and the difference) is exactly 0. The old floor (the model against
    itself at seed + 1: two independent renders) reported > 0 here, so any difference "below
    the floor" proved nothing."""
    from gonio.fitting.render.preview import matched_noise_floor, preview

    model = gm.get("roughplastic", distribution="ggx")
    params = {"diffuse_reflectance": [0.4, 0.3, 0.2], "alpha": 0.15, "int_ior": 1.5}
    out = preview(model, params, tmp_path, measured=model.to_mitsuba(params), size=24, spp=8, lightings=("env",))
    st = out["delta_e"]["env"]
    assert st["mean"] == 0.0 and st["noise_mean"] == 0.0
    # a real difference: the matched floor stays far below the difference itself
    other = dict(params, alpha=0.4)
    out2 = preview(model, params, tmp_path / "b", measured=model.to_mitsuba(other), size=24, spp=8, lightings=("env",))
    assert out2["delta_e"]["env"]["noise_mean"] < 0.5 * out2["delta_e"]["env"]["mean"]
    a = np.full((2, 2, 3), 0.5)
    assert np.all(matched_noise_floor(a, a * 0.9, a, a * 0.9) == 0.0)   # the true difference cancels


@needs_rgl
def test_rgl_own_layout_weights_and_peak():
    """Every measured theta_i <= 80 deg, 1152 outgoing directions each; the weights integrate
    the direction-pair space within theta <= 80 deg ((2 pi (1 - cos 80 deg))^2 = 26.9 sr^2)
    and the specular peak of vch_golden_yellow is resolved (>= 25 % of the pairs within
    10 deg of the mirror direction, against 6 % of the standard plan's 100)."""
    from gonio.fitting import rgl_samples

    meas = rgl_samples(RGL / "vch_golden_yellow_rgb.bsdf")
    assert meas.n_points >= 6000 and meas.attrs["nominal_sigma"] is True and meas.attrs["isotropic"] is True
    full = (2 * np.pi * (1 - np.cos(np.radians(80.0)))) ** 2
    assert meas.weight.sum() == pytest.approx(full, rel=0.05)
    mirror = meas.wo * np.array([-1.0, -1.0, 1.0])
    near = np.degrees(np.arccos(np.clip(np.sum(meas.wi * mirror, axis=1), -1, 1))) < 10.0
    assert near.mean() >= 0.25
    assert np.all(np.isfinite(meas.brdf))


@needs_rgl
def test_cli_fits_rgl_on_its_own_samples():
    from gonio.cli.fit import _open_dataset

    meas = _open_dataset(RGL / "paper_white_rgb.bsdf")
    assert meas.n_points > 5000 and meas.weight is not None and "own layout" in meas.attrs["sampling"]
