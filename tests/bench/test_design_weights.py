"""Design weights (gonio.bench.plan.design_weights, issue 38): each point's share of the
evaluation measure, so that a misspecified model fitted to a sequential design targets the
measure's minimiser (Shimodaira 2000), and dataset.nc carrying them to the fit."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

import gonio.models as gm
from gonio.bench.plan.design_weights import (REFERENCE_SR2, VARIABLE, design_weights, reference_pairs,
                                             wanted)
from gonio.bench.plan.plans import load_plan
from gonio.core.errors import GonioError
from gonio.core.geometry import directions_deg
from gonio.fitting import Measurements, fit


def _dirs(a):
    return directions_deg(a[:, 0], a[:, 1]), directions_deg(a[:, 2], a[:, 3])


def test_the_weights_sum_to_the_measure_and_are_deterministic():
    """(2 pi (1 - cos 80 deg))^2 = 26.958 sr^2 for the pairs with both elevations <= 80 deg;
    every weight > 0; the same design gives the same weights."""
    wi, wo = _dirs(load_plan("quick").angles)
    w = design_weights(wi, wo)
    assert REFERENCE_SR2 == pytest.approx(26.958127, rel=1e-6)
    assert w.sum() == pytest.approx(REFERENCE_SR2, rel=1e-12) and np.all(w > 0)
    assert np.array_equal(w, design_weights(wi, wo))


def test_points_of_one_brdf_value_share_their_cell():
    """A turn about the normal, a mirrored azimuth and a swapped pair are the same value of an
    isotropic, reciprocal BRDF: such points split one cell equally."""
    a = np.array([[30.0, 0.0, 50.0, 150.0], [30.0, 90.0, 50.0, 240.0], [30.0, 0.0, 50.0, 210.0],
                  [50.0, 0.0, 30.0, 150.0], [10.0, 0.0, 70.0, 30.0]])
    w = design_weights(*_dirs(a))
    assert w[:4] == pytest.approx(np.full(4, w[0]), rel=1e-12)
    single = design_weights(*_dirs(a[[0, 4]]))
    assert 4 * w[0] == pytest.approx(single[0], rel=1e-12)


def test_bad_directions_are_refused():
    wi, wo = _dirs(load_plan("quick").angles)
    bad = wi.copy()
    bad[3, 0] = np.nan
    for args in ((bad, wo), (wi[:0], wo[:0]), (wi, wo[:-1])):
        with pytest.raises(ValueError):
            design_weights(*args)


def _lobed(wi, wo):
    """A Lambertian (albedo 0.5) plus a broad lobe about the mirror direction: no Lambertian
    fits it, so the fitted albedo depends on where the points are."""
    wr = wi * np.array([-1.0, -1.0, 1.0])
    return (0.5 / np.pi + 0.2 * np.clip(np.sum(wr * wo, 1), 0.0, 1.0) ** 8)[:, None] * np.ones(3)


def test_a_weighted_fit_of_a_concentrated_design_recovers_the_measure_minimiser():
    """Diffuse fitted by chi2 (constant sigma) to the Lambertian + lobe: the minimiser over the
    evaluation measure is pi times the mean f_r over the reference pairs, 0.5715. A design of
    60 points, 40 of them within about 15 deg of the mirror direction: unweighted the fit is
    the design's mean, 0.930 (off by 0.36); weighted, 0.605 (off by 0.033, the Voronoi
    estimate's own error at 60 points). Deterministic: the design is drawn from a seeded
    Generator; the fits are linear least squares."""
    rng = np.random.default_rng(1)
    ti, pi = rng.uniform(10, 70, 60), rng.uniform(0, 360, 60)
    to = np.concatenate([ti[:40] + rng.uniform(-10, 10, 40), rng.uniform(0, 80, 20)]).clip(0, 80)
    po = np.concatenate([pi[:40] + 180 + rng.uniform(-15, 15, 40), rng.uniform(0, 360, 20)])
    wi, wo = directions_deg(ti, pi), directions_deg(to, po)
    f = _lobed(wi, wo)
    target = np.pi * _lobed(*reference_pairs()).mean(0)[0]
    got = {}
    for name, w in (("unweighted", None), ("weighted", design_weights(wi, wo))):
        meas = Measurements(wi, wo, f, np.full_like(f, 1e-3), True, weight=w)
        got[name] = fit(meas, gm.get("diffuse"), rng=np.random.default_rng(0)).params["reflectance"][0]
    assert target == pytest.approx(0.5715, abs=1e-3)
    assert abs(got["unweighted"] - target) > 0.3
    assert abs(got["weighted"] - target) < 0.05


def test_only_a_sequential_plan_asks_for_them():
    assert not wanted(None) and not wanted({"name": "fixed"})
    assert wanted({"name": "adaptive"}) and wanted({"name": "ndf", "design_weights": True})
    assert not wanted({"name": "adaptive", "design_weights": False})


def _dataset(path, weight):
    n = len(weight)
    xr.Dataset({"brdf": (("point", "channel"), np.full((n, 3), 0.2)),
                "brdf_std": (("point", "channel"), np.full((n, 3), 0.002)),
                "saturated": ("point", np.zeros(n, bool)), VARIABLE: ("point", np.asarray(weight, float))},
               coords={"point": np.arange(n), "channel": ["R", "G", "B"], "theta_i": ("point", np.full(n, 30.0)),
                       "phi_i": ("point", np.zeros(n)), "theta_o": ("point", np.linspace(0, 60, n)),
                       "phi_o": ("point", np.full(n, 180.0))}).to_netcdf(path, engine="h5netcdf")
    return path


def test_the_reader_hands_the_design_weight_to_the_fit(tmp_path):
    from gonio.bench.dataset.reader import open_dataset

    meas = open_dataset(_dataset(tmp_path / "a.nc", [1.0, 2.0, 3.0, 4.0, 5.0]))
    assert np.array_equal(meas.weight, [1.0, 2.0, 3.0, 4.0, 5.0])


def test_a_design_weight_that_is_no_weight_is_refused(tmp_path):
    """Zero, NaN, negative: ValueError naming the variable (the reader's own check, which
    open_dataset turns into one line: the long test below)."""
    from gonio.bench.dataset.reader import _with_design_weight

    meas = Measurements(*_dirs(load_plan("quick").angles[:5]), np.full((5, 3), 0.2), 0.002, True)
    for k, bad in enumerate(([1.0, 0.0, 3.0, 4.0, 5.0], [1.0, np.nan, 3.0, 4.0, 5.0], [1.0, -2.0, 3.0, 4.0, 5.0],
                             [1.0, 2.0])):
        with pytest.raises(ValueError, match=VARIABLE):
            _with_design_weight(_dataset(tmp_path / f"bad{k}.nc", bad), meas)
    assert meas.weight is None


@pytest.mark.long       # each open walks the file in a child process first (check_hdf5): ~2 s
def test_open_dataset_says_the_bad_design_weight_in_one_line(tmp_path):
    from gonio.bench.dataset.reader import open_dataset

    with pytest.raises(GonioError, match=VARIABLE) as err:
        open_dataset(_dataset(tmp_path / "bad.nc", [1.0, np.nan, 3.0]))
    assert len(str(err.value).splitlines()) == 1


@pytest.mark.long       # a 12-point adaptive capture on the simulator and its export: about 10 s
def test_an_adaptive_capture_exports_its_design_weights(tmp_path):
    """The adaptive plan's dataset.nc carries design_weight (sr^2, summing to the measure, the
    same for the same seed, equal to the weights of its points); design_weights = false leaves
    it out."""
    sim = pytest.importorskip("gonio.sim")
    from gonio.bench.dataset.export import export
    from gonio.bench.session.capture import capture
    from gonio.bench.settings import default_settings

    settings = default_settings()
    sample = {"model": "roughplastic", "options": {"distribution": "ggx"},
              "params": {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": 0.15}}
    got = []
    for k, table in enumerate(({"name": "adaptive", "points": 12, "seed": 4},
                               {"name": "adaptive", "points": 12, "seed": 4},
                               {"name": "adaptive", "points": 12, "seed": 4, "design_weights": False})):
        inst = sim.Instrument(settings, sample=sample, seed=4).register(f"weights-{k}")
        try:
            capture(tmp_path / f"s{k}", load_plan("quick"), settings, inst.url("zaber"), inst.url("meter"),
                    inst.url("camera"), seed=4, progress=False, sleep=inst.clock.advance,
                    sample_truth=inst.sample_spec, strategy=table)
        finally:
            inst.unregister()
        with xr.open_dataset(export(tmp_path / f"s{k}")) as ds:
            got.append(None if VARIABLE not in ds else (ds[VARIABLE].values.copy(), ds[VARIABLE].attrs["units"],
                                                        np.stack([ds[a].values for a in ("theta_i", "phi_i",
                                                                  "theta_o", "phi_o")], 1)))
    w, units, angles = got[0]
    assert units == "sr^2" and len(w) == 12 and w.sum() == pytest.approx(REFERENCE_SR2, rel=1e-12)
    assert np.array_equal(w, got[1][0]) and np.array_equal(w, design_weights(*_dirs(angles)))
    assert got[2] is None
