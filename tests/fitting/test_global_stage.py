"""The fit's global stage on sparse data of a material its family cannot follow (issue 38):
the lowest basin is found and kept across the affine stage's hand-over to the general path."""

from pathlib import Path

import numpy as np
import pytest

RGL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "rgl"
FELT = RGL / "acrylic_felt_white_rgb.bsdf"


def test_the_affine_stage_scores_many_starts_in_one_call():
    """At least SCORED starts (and the defaults) whatever n_starts asks, except 0: the defaults alone."""
    import gonio.models as gm
    from _simdata import simulate
    from gonio.fitting.optimise.affine import SCORED, AffineFit
    from gonio.fitting.optimise.space import ParameterSpace

    model = gm.get("roughplastic", distribution="ggx")
    meas = simulate(model, {"diffuse_reflectance": np.array([0.5, 0.35, 0.2]), "alpha": 0.2, "int_ior": 1.5},
                    np.random.default_rng(8), n=60, rel=0.03)
    fit = AffineFit(meas, model, ParameterSpace(model, 3, None), "chi2")
    assert len(fit.starts(12, np.random.default_rng(0))[0]) == SCORED + 1
    assert len(fit.starts(None, np.random.default_rng(0))[0]) == SCORED + 1
    assert len(fit.starts(0, np.random.default_rng(0))[0]) == 1


def test_the_general_path_starts_where_the_affine_stage_ended(monkeypatch):
    """Where the affine stage hands over (here forced: every point 'on an approximate bound'),
    the general path's first start is the affine stage's best point, and the fit ends there."""
    import gonio.fitting.optimise.mle as mle
    import gonio.models as gm
    from _simdata import simulate
    from gonio.fitting.optimise.affine import AffineFit

    model = gm.get("roughplastic", distribution="ggx")
    meas = simulate(model, {"diffuse_reflectance": np.array([0.5, 0.35, 0.2]), "alpha": 0.2, "int_ior": 1.5},
                    np.random.default_rng(8), n=150, rel=0.03)
    plain = mle.fit(meas, model, rng=np.random.default_rng(0))
    exact = AffineFit._parameters
    monkeypatch.setattr(AffineFit, "_parameters", lambda self, theta: (exact(self, theta)[0], False))
    given = []
    real = mle.GeneralFit.__init__

    def spy(self, meas, model, space, loss, use_fast, enforce_energy, maxeval, start=None):
        given.append(start)
        real(self, meas, model, space, loss, use_fast, enforce_energy, maxeval, start)

    monkeypatch.setattr(mle.GeneralFit, "__init__", spy)
    handed = mle.fit(meas, model, rng=np.random.default_rng(0))
    assert given and given[0] is not None
    assert given[0]["alpha"] == pytest.approx(plain.params["alpha"], rel=1e-3)
    assert handed.chi2 <= plain.chi2 + 1e-3


@pytest.mark.skipif(not FELT.is_file(), reason="needs ../shared/data/rgl")
def test_sparse_felt_finds_its_lowest_basin(tmp_path):
    """acrylic_felt_white as the simulated truth, seed 18, typical errors, every 19th point of the
    dense plan from point 18 (55 points): the plastic's lowest chi2 lies at alpha about 0.24, eta
    1.3 (1.40e6), beside a plateau of invisible coats (eta -> 1, 2.19e6) where 12 scored starts
    and a fresh general search ended 7 times in 10. The fit with the default starts must end in
    the lower basin for every rng seed tried: within 0.1 % of the objective a start there
    reaches (the plateau lies 57 % above; the local runs' own stopping leaves up to 5e-5) and
    at its alpha (measured: 5 of 5)."""
    from gonio.bench.calibrate import with_errors_and_calibration
    from gonio.bench.dataset.export import export
    from gonio.bench.dataset.reader import open_dataset
    from gonio.bench.plan.plans import load_plan, thin
    from gonio.bench.samples import load_sample
    from gonio.bench.session.simulated import capture_sim
    from gonio.bench.settings import load_settings
    import gonio.models as gm
    from gonio.fitting.optimise.mle import fit

    settings = with_errors_and_calibration(load_settings(None), sim=True, seed=18, errors="typical", calibration=None)
    capture_sim(tmp_path / "s", sample=load_sample(str(FELT)), plan=thin(load_plan("dense"), 19, 18), seed=18,
                progress=False, settings=settings)
    meas = open_dataset(export(tmp_path / "s"), seed=18)
    model = gm.get("roughplastic", distribution="ggx")
    low = fit(meas, model, rng=np.random.default_rng(0),
              start={"diffuse_reflectance": [0.78, 0.83, 1.0], "alpha": 0.24, "int_ior": 1.31})
    assert low.params["alpha"] == pytest.approx(0.24, abs=0.03)
    for s in range(5):
        r = fit(meas, model, rng=np.random.default_rng(s))
        assert r.objective <= low.objective * (1 + 1e-3), (s, r.objective, low.objective, r.params)
        assert r.params["alpha"] == pytest.approx(low.params["alpha"], abs=0.01), (s, r.params)
