"""``--model auto``'s sheen refinement on leaf_maple (RGL-EPFL, ../shared/data/rgl when it is
there), the material it was built for: the chosen plain ``tabulated`` fit renders the leaf's
grazing, blue-free sheen as a too-wide main lobe (preview CIEDE2000 1.21 at 256 spp); the
refinement, the same model with a GGX sheen lobe fitted with the luminance loss from a start
whose main-lobe tail is handed to the sheen, renders it at 1.04 (docs/performance.md)."""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba")

RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"
LEAF = RGL / "leaf_maple_rgb.bsdf"


@pytest.mark.slow
@pytest.mark.skipif(not LEAF.exists(), reason="no RGL data here")
def test_leaf_is_refined_with_the_sheen_and_renders_closer_in_a_scene_it_was_not_chosen_in():
    from gonio.fitting.realdata import rgl_samples
    from gonio.fitting.selection.auto import auto_fit
    from gonio.perf.real import rendered_delta_e

    meas = rgl_samples(LEAF)
    said = []
    result, ranking, note = auto_fit(meas, str(LEAF), loss="log", seed=0, progress=lambda *a: said.append(a[-1]))
    assert result.model.name == "tabulated" and result.model.options["sheen"] == "ggx", note
    assert any(s.startswith("refining tabulated") for s in said), said       # the terminal says what runs
    assert result.loss == "luminance" and result.converged, note
    body = result.model.options["body"]
    rows = {r.options.get("sheen"): r for r in ranking if r.name == "tabulated" and r.options.get("body") == body}
    plain, sheen = rows["none"], rows["ggx"]          # the refinement and the fit it started from
    assert sheen.chosen and not plain.chosen and sum(r.chosen for r in ranking) == 1
    # its BIC is under the ranking's loss (log), as every row's: a log-loss BIC near the plain fit's,
    # not the luminance loss's profiled scale (thousands apart on the same values)
    assert sheen.loss == plain.loss == "log"
    assert abs(sheen.bic - plain.bic) < 0.1 * abs(plain.bic)
    # the product-shot pixels (auto's own check): closer by far more than both rows' noise
    assert sheen.delta_e < plain.delta_e - 10 * (plain.noise + sheen.noise), (plain.delta_e, sheen.delta_e)
    # the preview (another scene, both lightings; matched seeds): 1.21 -> 1.04 at seed 0
    de_plain, floor = rendered_delta_e(plain.result.model, plain.result.params, LEAF, 0)
    de_sheen, _ = rendered_delta_e(result.model, result.params, LEAF, 0)
    assert de_sheen < de_plain - 0.1, (de_plain, de_sheen, floor)
    # no energy made: the refit's polish holds albedo <= 1 (it is 0.28 here)
    assert result.energy["holds"] and result.energy["max_albedo"] <= 1.0
    # not a flat, bright sheen: its grazing amplitude is the one the data see, below 1
    assert np.all(np.asarray(result.params["sheen_3"]) < 1.0)


def test_no_refinement_is_tried_where_the_choice_renders_within_the_threshold():
    """As the fallback: where the chosen fit's pixels are within CIEDE2000 1 already, the scene
    needs no more, and the refinement's fit (about 1 s) is not run."""
    from types import SimpleNamespace

    from gonio.fitting.selection.auto import _refined

    asked = []

    class Model:
        def refinement(self, params):
            asked.append(params)
            return None

    class Check:
        def __init__(self, de):
            self.de = de

        def delta_e(self, model, params):
            return self.de, 0.01

    chosen = SimpleNamespace(model=Model(), params={"x": 1.0})
    assert _refined(chosen, None, Check(0.99), "n", seed=0, loss="log") == (chosen, "n", None)
    assert asked == []
    assert _refined(chosen, None, Check(1.01), "n", seed=0, loss="log") == (chosen, "n", None)
    assert asked == [{"x": 1.0}]
