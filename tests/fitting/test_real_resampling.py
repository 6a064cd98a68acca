"""Intervals on real data are honest (issue 16): refits of one RGL-EPFL material on random
geometries of its own layout spread within the reported uncertainty at the stated rate.

Design: colodur_napoli_4f fitted with roughplastic-GGX and the real-data default loss
(log, sandwich covariance). The reference is the fit on the full stratified layout
(7700 pairs); each of K = 10 refits uses an independent random geometry of the same layout
(``rgl_samples(n_side=10, rng=Generator)``: ~1330 pairs, every measured theta_i <= 80 deg,
half of the outgoing directions importance-sampled through the peak, MIS weights). With
honest 1-sigma values, z = (alpha_k - alpha_ref) / sqrt(sigma_k^2 + sigma_ref^2) is
standard normal, so:

* the 90 % interval covers z in at least 7 of the 10 refits: false alarm
  P(Binomial(10, 0.9) <= 6) = 1.3 %;
* sum z^2 lies between 1.5 and 29.6, the 0.1 % and 99.9 % points of chi2 with 10 degrees of
  freedom (intervals neither far too wide nor far too narrow): false alarm 0.2 %.

Measured (this commit): alpha is covered in 7 of 10 refits, but sum z^2 is far above 29.6:
the spread across geometries is ~1.7x the sandwich sigma on most refits, and one geometry
moves alpha by 80 sigma (int_ior at its bound). 95 % of alpha's sandwich variance comes
from 1 % of the pairs, all at the grazing measured elevation (78 deg): the estimate rests on
a few grazing samples whose model discrepancy is large, and the sandwich estimated from a
subset misses most of them. Hence the strict xfail until the likelihood models that
discrepancy (see issue 16); it turns into a failure the day the intervals are honest.
"""

from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binom, chi2

import gonio.models as gm

RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"
MATERIAL = RGL / "colodur_napoli_4f_rgb.bsdf"
K, N_SIDE, MIN_COVERED = 10, 10, 7


@pytest.mark.skipif(not MATERIAL.exists(), reason="no RGL data here")
@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="sandwich intervals under-cover on real geometry resampling (grazing "
                                        "discrepancy dominates the influence); issue 16")
def test_refits_on_random_geometries_spread_within_the_reported_sigma():
    from gonio.fitting import fit, rgl_samples

    assert binom.cdf(MIN_COVERED - 1, K, 0.9) < 0.015          # the stated false-alarm rates
    lo, hi = chi2.ppf([0.001, 0.999], K)
    model = gm.get("roughplastic", distribution="ggx")
    ref = fit(rgl_samples(MATERIAL), model, rng=np.random.default_rng(0), loss="log")
    i = ref.space.names.index("alpha")
    z = []
    for k in range(K):
        meas = rgl_samples(MATERIAL, n_side=N_SIDE, rng=np.random.default_rng([16, k]))
        r = fit(meas, model, rng=np.random.default_rng(k), loss="log")
        z.append((r.x[i] - ref.x[i]) / np.hypot(r.std[i], ref.std[i]))
    z = np.array(z)
    print(f"alpha z over {K} geometries: {np.round(z, 2)}; covered {np.sum(np.abs(z) <= 1.645)}; "
          f"sum z^2 {np.sum(z * z):.3g} (range {lo:.3g}-{hi:.3g})")
    assert np.all(np.isfinite(z))
    assert np.sum(np.abs(z) <= 1.645) >= MIN_COVERED
    assert lo <= np.sum(z * z) <= hi


@pytest.mark.skipif(not MATERIAL.exists(), reason="no RGL data here")
def test_log_fit_leaves_the_lobe_free_plateau():
    """Geometry 9 of the refits above: the global stage's three best-scored starts all had
    alpha < 1e-3 (a specular lobe too narrow to meet any sample: the diffuse term alone,
    which scores better than any start whose lobe is in the wrong place), and Levenberg-
    Marquardt cannot leave that plateau (d f / d alpha = 0 there). The fit ended at alpha
    6e-4, int_ior at its bound 4, log objective 0.690; from the declared defaults it reaches
    alpha 0.394, int_ior 1.38, objective 0.108 (measured). The defaults are now always refined
    where starts are scored without variable projection."""
    from gonio.fitting import fit, rgl_samples

    meas = rgl_samples(MATERIAL, n_side=N_SIDE, rng=np.random.default_rng([16, 9]))
    r = fit(meas, gm.get("roughplastic", distribution="ggx"), rng=np.random.default_rng(9), loss="log")
    p = r.params
    assert r.at_bound == [], r.at_bound
    assert 0.3 < p["alpha"] < 0.6 and 1.2 < p["int_ior"] < 1.7, p
    assert r.objective < 0.12          # the plateau: 0.690


@pytest.mark.skipif(not MATERIAL.exists(), reason="no RGL data here")
def test_rgl_geometry_clusters_are_its_draws():
    """Each outgoing direction of rgl_samples comes from one (U, V) draw, shared by every
    measured theta_i and by both sample sets: ``meas.cluster`` names that draw (n_side^2 of
    them), so the sandwich treats the pairs of one draw as one unit of the geometry."""
    from gonio.fitting import rgl_samples

    meas = rgl_samples(MATERIAL, n_side=4, rng=np.random.default_rng(1))
    assert meas.cluster.shape == (meas.n_points,) and set(np.unique(meas.cluster)) <= set(range(16))
    theta_i = np.round(np.degrees(np.arccos(meas.wo[:, 2])), 1)
    # a draw recurs at (almost) every measured elevation, twice (importance and cosine sets)
    assert np.median(np.bincount(meas.cluster)) >= 2 * np.unique(theta_i).size - 2
    sub = meas.subset(slice(0, 10))
    assert np.array_equal(sub.cluster, meas.cluster[:10])


def test_cluster_must_be_one_integer_per_point():
    from gonio.fitting import DataError, Measurements

    wi = np.tile([0.0, 0.0, 1.0], (3, 1))
    for bad in (np.zeros(2, int), np.array([0.0, 1.0, 2.0])):
        with pytest.raises(DataError, match="cluster"):
            Measurements(wi, wi, np.ones((3, 3)), 0.1, True, cluster=bad)
