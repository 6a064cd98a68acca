"""Plans: presets, generators, files, validation, reachability, dry run."""

import math

import numpy as np
import pytest

from gonio.bench.plan import plans
from gonio.bench.settings import default_settings
from gonio.core.errors import GonioError, PlanError, UnreachableError

S = default_settings()


@pytest.mark.parametrize("name, lo, hi", [("quick", 25, 40), ("standard", 90, 120), ("dense", 900, 1200)])
def test_presets_size_and_reachable(name, lo, hi):
    p = plans.load_plan(name)
    assert lo <= len(p) <= hi
    assert plans.check_plan(p, S) == []
    assert np.all((p.angles[:, [0, 2]] >= 0) & (p.angles[:, [0, 2]] < 90))


def test_standard_has_in_plane_out_of_plane_and_reciprocal_pairs():
    p = plans.load_plan("standard")
    dphi = np.abs((p.angles[:, 3] - p.angles[:, 1] + 180) % 360 - 180)
    in_plane = np.isclose(dphi, 0) | np.isclose(dphi, 180) | (p.angles[:, 2] == 0)
    assert in_plane.sum() >= 40 and (~in_plane).sum() >= 30
    pairs = np.flatnonzero(p.partner >= 0)
    assert len(pairs) >= 10
    for i in pairs:
        j = p.partner[i]
        assert p.partner[j] == i
        np.testing.assert_allclose(p.angles[j], p.angles[i][[2, 3, 0, 1]])


def test_hemisphere_uniform_in_solid_angle():
    theta, phi = plans.hemisphere_directions(400, 80.0)
    assert 360 <= len(theta) <= 440
    # uniform in solid angle over the cap: cos(theta) is uniform on [cos(80 deg), 1]
    c, cm = np.cos(np.radians(theta)), math.cos(math.radians(80))
    assert np.mean(c) == pytest.approx((1 + cm) / 2, rel=0.01)
    assert np.mean(c ** 2) == pytest.approx((1 + cm + cm ** 2) / 3, rel=0.01)
    # and isotropic in azimuth
    assert abs(np.mean(np.cos(np.radians(phi)))) < 0.02 and abs(np.mean(np.sin(np.radians(phi)))) < 0.02


def test_generators():
    a = plans.in_plane([30], [-60, -30, 0, 30])
    assert a.tolist() == [[30, 0, 60, 0], [30, 0, 0, 180], [30, 0, 30, 180]]     # -30: backscatter, left out
    g = plans.isotropic_grid([20], [40], [90, 180])
    assert g.tolist() == [[20, 0, 40, 90], [20, 0, 40, 180]]
    r = plans.with_reciprocal(g)
    assert len(r) == 4 and r[2].tolist() == [40, 90, 20, 0]
    assert plans.Plan("x", r).partner.tolist() == [2, 3, 0, 1]


def test_toml_plan(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text('name = "mine"\npoints = [[30, 0, 40, 180], [10, 0, 20, 90]]\n'
                 '[[scan]]\nkind = "in_plane"\ntheta_i = [45]\ntheta_o = [20, 70]\nreciprocal = true\n')
    p = plans.load_plan(f)
    assert p.name == "mine" and len(p) == 6 and (p.partner >= 0).sum() == 4
    assert plans.plan_from_dict(p.to_dict()).angles.tolist() == p.angles.tolist()


def test_csv_plan(tmp_path):
    f = tmp_path / "p.csv"
    f.write_text("theta_i,phi_i,theta_o,phi_o\n30,0,40,180\n40,180,30,0\n")
    p = plans.load_plan(f)
    assert len(p) == 2 and p.partner.tolist() == [1, 0]


@pytest.mark.parametrize("text, match", [
    ("points = [[30, 0, 40", "not valid TOML"),
    ("points = [[30, 0, nan, 180]]", "non-finite"),
    ("points = [[30, 0, 90, 180]]", r"theta outside \[0, 90\)"),
    ("points = [[-1, 0, 30, 180]]", "theta outside"),
    ("points = [[30, 0, 40]]", "exactly 4 angles"),
    ("points = []", "no points"),
    ("name = 'x'", "no points"),
    ("pints = [[1, 2, 3, 4]]", "unknown keys"),
    ("[[scan]]\nkind = 'spiral'", "kind 'spiral'"),
    ("[[scan]]\nkind = 'in_plane'\ntheta_i = [30]", "lacks 'theta_o'"),
    ("[[scan]]\nkind = 'in_plane'\ntheta_i = ['a']\ntheta_o = [1]", "not a number"),
    ("[[scan]]\nkind = 'hemisphere'\ntheta_i = [30]\nn = 10\nmax_theta = 95", "max_theta"),
])
def test_bad_toml_plans_are_one_line(tmp_path, text, match):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(PlanError, match=match) as e:
        plans.load_plan(f)
    assert "\n" not in str(e.value) and isinstance(e.value, GonioError)


def test_bad_plan_specs(tmp_path):
    with pytest.raises(PlanError, match="unknown plan 'huge'.*quick"):
        plans.load_plan("huge")
    with pytest.raises(PlanError, match="cannot read plan file"):
        plans.load_plan(tmp_path / "missing.toml")
    (tmp_path / "h.csv").write_text("a,b,c,d\n1,2,3,4\n")
    with pytest.raises(PlanError, match="header"):
        plans.load_plan(tmp_path / "h.csv")
    (tmp_path / "v.csv").write_text("theta_i,phi_i,theta_o,phi_o\n1,2,x,4\n")
    with pytest.raises(PlanError, match="not a number"):
        plans.load_plan(tmp_path / "v.csv")


def test_unreachable_points_listed_before_anything_moves():
    p = plans.Plan("u", [[30, 0, 40, 180], [30, 0, 31, 0], [89, 0, 89, 90]])
    bad = plans.check_plan(p, S)
    assert [b[0] for b in bad] == [1, 2]
    with pytest.raises(UnreachableError) as e:
        plans.require_reachable(p, S)
    assert "2 unreachable" in str(e.value) and "\n" not in str(e.value)
    d = plans.dry_run(p, S)
    assert "2 unreachable point(s)" in d.summary() and "lamp in front of the camera" in d.summary()


def test_dry_run_summary():
    d = plans.dry_run(plans.load_plan("quick"), S)
    assert d.n_points == len(plans.load_plan("quick")) and d.unreachable == []
    assert d.bound_move_s <= d.ordered_move_s < d.naive_move_s
    assert d.estimated_s > d.ordered_move_s
    assert "points; estimated duration" in d.summary() and "lower bound" in d.summary()


def test_thin_keeps_every_kth_point_and_each_scans_share():
    """thin(dense, 14, 3): the listed points 3, 17, 31, ...; each of dense's three scans (120-point
    hemispheres at six incidences, the in-plane scans, the isotropic grid) keeps its share of the
    points within one point, so the thinned plan weighs the hemisphere as dense does."""
    dense = plans.load_plan("dense")
    t = plans.thin(dense, 14, 3)
    assert np.array_equal(t.angles, dense.angles[3::14]) and len(t) == 75
    hemi = 6 * 120
    n_hemi = np.sum(np.arange(3, len(dense), 14) < hemi)
    assert abs(n_hemi - hemi / 14) <= 1 and abs((len(t) - n_hemi) - (len(dense) - hemi) / 14) <= 1
    assert plans.thin(dense, 1).angles.shape == dense.angles.shape
    assert t.sides == dense.sides and "thinned 1/14" in t.source


@pytest.mark.parametrize("stride, offset, match", [(0, 0, "stride 0"), (2000, 0, "stride 2000"),
                                                   (14, 14, "offset 14"), (14, -1, "offset -1"),
                                                   (2.0, 0, "whole number"), (True, 0, "whole number"),
                                                   (14, "1", "whole number")])
def test_thin_refuses_what_is_not_a_stride(stride, offset, match):
    with pytest.raises(ValueError, match=match):
        plans.thin(plans.load_plan("dense"), stride, offset)


def test_thin_refuses_a_spectral_plan():
    with pytest.raises(ValueError, match="spectral"):
        plans.thin(plans.load_plan("spectral"), 2)
