"""``gonio perf real``'s warm-up (issue 35): it pays the process's one-time costs and changes no figure.

The rows are a batch's steady state only if running something first leaves every fit where
it was: auto's choice on cardboard, with and without a warm-up on another file first, gives
the same model and the same parameters (each fit draws from a Generator of its own seed, and
the choice sets its thread pool itself). Reads ../shared/data/rgl.
"""

from pathlib import Path

import numpy as np
import pytest

RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"

pytest.importorskip("colour")
pytest.importorskip("mitsuba")


@pytest.mark.long
@pytest.mark.skipif(not RGL.is_dir(), reason="../shared/data/rgl is not here")
def test_a_warm_up_on_another_file_changes_nothing_auto_chooses():
    from gonio.fitting.likelihood.loss import REAL_DEFAULT_LOSS
    from gonio.fitting.realdata import rgl_samples
    from gonio.fitting.selection.auto import auto_fit, subsample
    from gonio.perf.real import warm_up

    path = RGL / "cardboard_rgb.bsdf"
    meas = subsample(rgl_samples(path), 2500, np.random.default_rng(5))

    def choose():
        res, _, _ = auto_fit(meas, str(path), seed=3, loss=REAL_DEFAULT_LOSS, rng=np.random.default_rng(3))
        return res.model.name, dict(res.model.options), res.x.copy(), res.objective

    cold = choose()
    t_gonio, t_peer = warm_up(RGL / "paper_white_rgb.bsdf", seed=1, n=300)
    warm = choose()
    assert t_gonio > 0 and t_peer > 0
    assert warm[:2] == cold[:2]
    np.testing.assert_allclose(warm[2], cold[2], rtol=1e-9, atol=1e-12)
    assert warm[3] == pytest.approx(cold[3], rel=1e-12)
