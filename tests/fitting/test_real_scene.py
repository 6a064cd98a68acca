"""Scene selection (issue 16): rank fitted candidates by their render in a scene against the
measured material's render with matched seeds; the simplest one within CIEDE2000 1 wins.

The "measured" material is a glossy GGX plastic (alpha 0.08, index 1.5) given as its exact
Mitsuba BSDF; the candidates are a Lambertian and a roughplastic. Renders 32 x 32 at 64 spp
(the matched-seed noise floor measured 0.17-0.35, asserted below half the threshold).
"""

import numpy as np
import pytest

import gonio.models as gm

pytest.importorskip("mitsuba")

TRUTH = {"diffuse_reflectance": [0.55, 0.35, 0.2], "alpha": 0.08, "int_ior": 1.5}


def _fits(meas, rng):
    from gonio.fitting import fit

    return [fit(meas, gm.get("diffuse"), rng=rng), fit(meas, gm.get("roughplastic", distribution="ggx"), rng=rng)]


@pytest.fixture(scope="module")
def truth():
    m = gm.get("roughplastic", distribution="ggx")
    return m, m.validate(TRUTH)


def test_sunlit_close_up_needs_the_lobe_and_reports_the_front(truth):
    """Under a sun in a close-up the highlight is in the frame: the Lambertian fit is > 1
    CIEDE2000 from the measured render (measured 3.6), the roughplastic fit is not (0.10),
    so the 5-parameter model is chosen; every row has its Mitsuba cost; the front holds the
    rows no other row beats on both cost and error."""
    from _simdata import simulate

    from gonio.fitting.scene import front, rank_in_scene

    model, p = truth
    rng = np.random.default_rng(16)
    fits = _fits(simulate(model, p, rng, n=400, rel=0.01), rng)
    sun = rank_in_scene(fits, model.to_mitsuba(p), "close-up-sun", size=32, spp=64)
    de = {row["model"]: row["delta_e"] for row in sun["rows"]}
    assert all(row["noise"] < 0.5 and row["cost_s"] > 0 for row in sun["rows"])
    assert de["diffuse"] > 1.0 > de["roughplastic"]
    assert sun["chosen"]["model"] == "roughplastic"
    rows = [{"cost_s": 1.0, "delta_e": 2.0}, {"cost_s": 2.0, "delta_e": 1.0}, {"cost_s": 3.0, "delta_e": 1.5}]
    assert front(rows) == rows[:2]


@pytest.mark.xfail(strict=True, reason=(
    "measured: fitted on the pairs the overcast scene asks (scene_samples, 1184 pairs weighted by the sky), "
    "the Lambertian is still 3.0 CIEDE2000 from the measured render (noise floor 0.35): a per-pair fit does "
    "not match the per-pixel integral of the sky, whose rim brightening (Fresnel) a Lambertian cannot show; "
    "the fit needs the pixel integrals as its data"))
def test_overcast_picks_a_simpler_model_than_a_sunlit_close_up(truth):
    from gonio.fitting.scene import rank_in_scene, scene_samples

    model, p = truth
    chosen = {}
    for preset in ("overcast", "close-up-sun"):
        rng = np.random.default_rng(16)
        fits = _fits(scene_samples(model.to_mitsuba(p), preset, size=16, rng=rng), rng)
        r = rank_in_scene(fits, model.to_mitsuba(p), preset, size=32, spp=64)
        chosen[preset] = r["chosen"]
    assert chosen["overcast"]["k"] < chosen["close-up-sun"]["k"]


def test_unknown_scene_is_refused(truth):
    from gonio.fitting.scene import rank_in_scene, scene_directions

    model, p = truth
    with pytest.raises(ValueError, match="overcast"):
        rank_in_scene([object()], model.to_mitsuba(p), "moonlight", size=8, spp=1)
    with pytest.raises(ValueError, match="overcast"):
        scene_directions("moonlight", 8, np.random.default_rng(0))
