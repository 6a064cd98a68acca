"""``--model auto`` on measured files (issue 35): screened on a subsample, chosen by the default
scene's own pixels and the data's BIC, degenerate fits never chosen, the chosen one refitted.

The "measured" material is a glossy GGX plastic (alpha 0.08, index 1.5) given as its exact
Mitsuba BSDF, as in test_real_scene; the scene's pixels are 24 x 24 with 8 light samples.
"""

import types

import numpy as np
import pytest

import gonio.models as gm

pytest.importorskip("mitsuba")

TRUTH = {"diffuse_reflectance": [0.55, 0.35, 0.2], "alpha": 0.08, "int_ior": 1.5}
KW = dict(size=24, k=8, seed=0)


@pytest.fixture(scope="module")
def truth():
    m = gm.get("roughplastic", distribution="ggx")
    return m, m.validate(TRUTH)


def _result(name, params, **options):
    from gonio.fitting.optimise.space import ParameterSpace

    model = gm.get(name, **options)
    params = model.validate(params)
    space = ParameterSpace(model)
    return types.SimpleNamespace(model=model, params=params, space=space, x=space.from_params(params),
                                 chi2=0.0, bic=0.0, loss="log", neg2_loglik=0.0)


def _row(label, result, bic):
    from gonio.fitting.selection.by_data import Ranked

    result.bic = bic
    return Ranked(label, dict(result.model.options), result.space.size, 0.0, bic, 0.0, False, result, "log", 0.0)


def test_degenerate_is_an_edge_of_the_box_not_a_material():
    """A conductor's k at its bound, a roughness below the data's resolution or at its floor,
    a second lobe's weight at 0 are degenerate; principled's metallic and sheen at 0 are a
    material (a dielectric without sheen), and a proper conductor is proper."""
    from gonio.fitting.selection.by_pixels import degenerate

    silver = {"eta": [0.16, 0.14, 0.13], "k": [3.9, 3.2, 2.5], "alpha": 0.1}
    assert degenerate(_result("roughconductor", silver, distribution="ggx")) == []
    bad = degenerate(_result("roughconductor", {**silver, "k": [3.9, 3.2, 10.0]}, distribution="ggx"))
    assert len(bad) == 1 and bad[0].startswith("k[B]")
    assert degenerate(_result("roughconductor", {**silver, "alpha": 0.004}, distribution="ggx"))[0].startswith("alpha")
    two = {**silver, "alpha2": 0.3, "weight": 0.0}
    assert [d.split(" ")[0] for d in degenerate(_result("roughconductor2", two, distribution="ggx"))] == ["weight"]
    p = gm.get("principled", distribution="ggx").defaults()
    assert degenerate(_result("principled", {**p, "metallic": 0.0, "sheen": 0.0, "clearcoat": 0.0},
                              distribution="ggx")) == []
    assert degenerate(_result("principled", {**p, "roughness": 0.0317}, distribution="ggx"))[0].startswith("roughness")


def test_the_scene_keeps_what_renders_alike_and_the_data_chooses_among_them(truth):
    """pixel_choice: the degenerate conductor (lowest BIC of all) is never chosen; the
    Lambertian, whose highlight is missing, renders visibly worse than the plastics and is
    rejected although its BIC is below theirs; between two plastics that render alike (alpha
    0.08 and 0.09), the data's choice (lower BIC) wins although it renders a little worse.
    No rejected proper row renders more than the tolerance (+ floor) better than the chosen."""
    from gonio.fitting.selection.by_pixels import TOLERANCE, pixel_choice

    model, p = truth
    rows = [_row("roughplastic", _result("roughplastic", TRUTH, distribution="ggx"), -900.0),
            _row("roughplastic", _result("roughplastic", {**TRUTH, "alpha": 0.09}, distribution="ggx"), -1000.0),
            _row("diffuse", _result("diffuse", {"reflectance": TRUTH["diffuse_reflectance"]}), -1100.0),
            _row("roughconductor", _result("roughconductor", {"eta": [0.2, 0.2, 0.2], "k": [10.0, 3.0, 3.0],
                                                              "alpha": 0.08}, distribution="ggx"), -5000.0)]
    calls = []
    result, ranking, note = pixel_choice(rows, model.to_mitsuba(p), fallback=lambda: calls.append(1) or [], **KW)
    print(note, [(r.name, r.bic, round(r.delta_e, 3), round(r.noise, 3)) for r in ranking])
    chosen = next(r for r in ranking if r.chosen)
    assert chosen.bic == -1000.0 and result is chosen.result and calls == []
    exact = next(r for r in ranking if r.bic == -900.0)
    diffuse = next(r for r in ranking if r.name == "diffuse")
    assert exact.delta_e < chosen.delta_e < exact.delta_e + TOLERANCE
    assert diffuse.delta_e > chosen.delta_e + TOLERANCE + chosen.noise
    assert "degenerate, not chosen: roughconductor" in note
    assert all(r.delta_e <= chosen.delta_e + TOLERANCE + chosen.noise or r.name == "roughconductor"
               or r.delta_e > chosen.delta_e for r in ranking)


def test_the_fallback_is_fitted_only_when_nothing_renders_within_the_threshold(truth):
    """Only a Lambertian (CIEDE2000 above 1 from the glossy plastic): the fallback is called,
    its fit added to the ranking and chosen; with the plastic among the rows it is not called."""
    from gonio.fitting.selection.by_pixels import pixel_choice

    model, p = truth
    calls = []

    def fallback():
        calls.append(1)
        return [_result("roughplastic", TRUTH, distribution="ggx")]

    rows = [_row("diffuse", _result("diffuse", {"reflectance": TRUTH["diffuse_reflectance"]}), 0.0)]
    result, ranking, note = pixel_choice(rows, model.to_mitsuba(p), fallback=fallback, **KW)
    assert calls == [1] and result.model.name == "roughplastic" and len(ranking) == 2 and "fitted too" in note
    rows = [_row("roughplastic", _result("roughplastic", TRUTH, distribution="ggx"), 0.0)]
    pixel_choice(rows, model.to_mitsuba(p), fallback=fallback, **KW)
    assert calls == [1]


def test_auto_fit_screens_on_a_subsample_and_refits_the_chosen_one_to_all(truth):
    """auto_fit on 4500 simulated samples of the glossy plastic: the ranking's fits saw 2000,
    the chosen family is the true one, refitted to all 4500 (its fit's n_used), its
    parameters within 5 sigma of the truth and its pixels within CIEDE2000 0.5."""
    from _simdata import simulate

    from gonio.fitting.selection.auto import auto_fit

    model, p = truth
    meas = simulate(model, p, np.random.default_rng(35), n=4500, rel=0.02)
    cands = [("diffuse", {}), ("roughplastic", {"distribution": "ggx"}), ("roughconductor", {"distribution": "ggx"})]
    result, ranking, note = auto_fit(meas, model.to_mitsuba(p), loss="log", candidates=cands, **KW)
    print(note)
    assert note.startswith("ranked on 2000 of 4500 samples")
    assert result.model.name == "roughplastic" and result.n_used == 4500 * 3
    assert all(r.result.n_used == 2000 * 3 for r in ranking if not r.chosen)
    z = (result.space.from_params(result.params) - result.space.from_params(p)) / result.std
    assert np.all(np.abs(z) < 5), z
    assert next(r for r in ranking if r.chosen).delta_e < 0.5


def test_negative_measured_values_are_noise_not_a_target():
    """A dark Lambertian (rho / pi = 0.005 sr^-1) under additive noise sigma 0.01: 31 % of the
    values are below zero. The log loss keeps them as they are (its ln(1 + f cos) is linear
    near 0, a Gaussian likelihood that allows them), so the fit is unbiased: within 3 of its
    standard errors of the truth. Clipping them at zero (what a log of the values would need)
    moves the mean to mu Phi(mu / s) + s phi(mu / s) = 0.00698 (a normal's censored mean), a
    bias of 0.00198 or about 10 standard errors; asserted above 5: the test can fail."""
    from gonio.fitting import Measurements, fit

    rng = np.random.default_rng(351)
    n = 4000
    mu = rng.uniform(0.2, 1.0, (2, n))
    ph = rng.uniform(0, 2 * np.pi, (2, n))
    s = np.sqrt(1 - mu ** 2)
    wi = np.stack([s[0] * np.cos(ph[0]), s[0] * np.sin(ph[0]), mu[0]], axis=1)
    wo = np.stack([s[1] * np.cos(ph[1]), s[1] * np.sin(ph[1]), mu[1]], axis=1)
    y = 0.005 + 0.01 * rng.standard_normal((n, 3))
    assert 0.25 < np.mean(y < 0) < 0.35
    std = np.full_like(y, 0.01)
    model = gm.get("diffuse")
    fr = {}
    for label, data in (("as measured", y), ("clipped", np.maximum(y, 0.0))):
        meas = Measurements(wi, wo, data, std, np.ones(y.shape, bool), {"nominal_sigma": True})
        res = fit(meas, model, rng=np.random.default_rng(0), loss="log")
        fr[label] = (res.params["reflectance"] / np.pi, res.std[:3] / np.pi)
    est, se = fr["as measured"]
    assert np.all(np.abs(est - 0.005) < 3 * se), (est, se)
    clipped, _ = fr["clipped"]
    assert np.all(clipped - 0.005 > 5 * se), (clipped, se)


SIMULATED = [  # (label, family, options, truth): one of every kind --model auto chooses among
    ("matte", "diffuse", {}, {"reflectance": [0.7, 0.5, 0.3]}),
    ("glossy plastic", "roughplastic", {"distribution": "ggx"}, TRUTH),
    ("rough plastic", "roughplastic", {"distribution": "beckmann"},
     {"diffuse_reflectance": [0.2, 0.4, 0.6], "alpha": 0.3, "int_ior": 1.6}),
    ("rough gold", "roughconductor", {"distribution": "ggx"},
     {"eta": [0.143, 0.374, 1.442], "k": [3.983, 2.385, 1.603], "alpha": 0.25}),
]


@pytest.mark.long       # about a minute: every candidate screened on four materials
@pytest.mark.parametrize("label, family, options, params", SIMULATED, ids=[s[0] for s in SIMULATED])
def test_auto_fit_on_simulated_materials_of_every_kind(label, family, options, params):
    """Simulated materials none of the choice's constants were set on: 4000 samples at 2 %
    noise, every candidate. The chosen fit is proper, renders within the tolerance of the true
    family's own fit (which is among the candidates), and is within 10 % of its Ngan error
    against the truth on the dense grid."""
    from _simdata import simulate

    from gonio.fitting import fit
    from gonio.fitting.selection.auto import auto_fit
    from gonio.fitting.selection.by_pixels import TOLERANCE, PixelCheck, degenerate
    from gonio.perf.real import dense_grid, metrics

    model = gm.get(family, **options)
    p = model.validate(params)
    meas = simulate(model, p, np.random.default_rng(350), n=4000, rel=0.02)
    result, ranking, note = auto_fit(meas, model.to_mitsuba(p), loss="log", seed=0)
    own = fit(meas, model, rng=np.random.default_rng(1), loss="log")
    check = PixelCheck(model.to_mitsuba(p), seed=0)
    de, noise = check.delta_e(result.model, result.params)
    de_own, _ = check.delta_e(own.model, own.params)
    wi, wo = dense_grid()
    truth = model.eval(wi, wo, p)
    ngan = metrics(result.model.eval(wi, wo, result.params), truth, wi)["ngan"]
    ngan_own = metrics(own.model.eval(wi, wo, own.params), truth, wi)["ngan"]
    print(label, result.model.name, de, de_own, ngan, ngan_own, note)
    assert degenerate(result) == []
    assert de <= de_own + TOLERANCE + noise
    assert ngan <= 1.1 * ngan_own + 1e-3


def test_a_format_that_holds_an_isotropic_brdf_gets_no_anisotropic_candidate():
    """RGL and MERL files hold isotropic BRDFs (f at phi_i = 0): a mirror pair differing there is
    the file's noise (a flake paint's sparkle), not azimuthal structure. Data built to show
    azimuthal structure gets the anisotropic candidates, the same data marked isotropic (as
    rgl_samples and merl_samples mark theirs) does not."""
    from gonio.fitting import Measurements
    from gonio.fitting.selection.by_data import ANISOTROPIC, CANDIDATES, candidates_for

    t = np.radians([30.0, 45.0])
    rows = []
    for ti in t:
        for phi_i in np.radians([0.0, 60.0, 120.0]):
            for dphi in np.radians([150.0, 180.0]):
                wi = [np.sin(ti) * np.cos(phi_i), np.sin(ti) * np.sin(phi_i), np.cos(ti)]
                wo = [np.sin(ti) * np.cos(phi_i + dphi), np.sin(ti) * np.sin(phi_i + dphi), np.cos(ti)]
                rows.append((wi, wo, 1.0 + np.cos(2 * phi_i)))     # a value that turns with the azimuth
    wi, wo, v = (np.array(x) for x in zip(*rows))
    f = np.repeat(v[:, None], 3, axis=1)
    meas = Measurements(wi, wo, f, 0.01 * f, np.ones(f.shape, bool), {})
    assert ANISOTROPIC and candidates_for(meas) == CANDIDATES + ANISOTROPIC
    iso = Measurements(wi, wo, f, 0.01 * f, np.ones(f.shape, bool), {"isotropic": True})
    assert candidates_for(iso) == CANDIDATES


def test_a_zemax_table_is_not_taken_for_a_measured_file_mitsuba_renders(tmp_path):
    """A Zemax/LightTools table shares the RGL files' .bsdf suffix: --model auto must not hand it
    to Mitsuba's ``measured`` plugin (that failed the whole fit: 'not an RGL-EPFL tensor .bsdf
    file'); told by content. An RGL-like name that is not a Zemax table still counts."""
    from gonio.fitting.formats.zemax import export_zemax
    from gonio.fitting.pipeline import renders_measured

    model = gm.get("difftrans")
    paths = export_zemax(tmp_path / "diffuser", model, {"transmittance": [0.5, 0.4, 0.3]}, aoi=[0.0, 30.0])
    assert paths and all(str(p).endswith(".bsdf") for p in paths)
    assert not any(renders_measured(p) for p in paths)
    fake = tmp_path / "paint_rgb.bsdf"
    fake.write_bytes(b"tensor_file\x00" + bytes(64))
    assert renders_measured(fake)
    assert not renders_measured(tmp_path / "x.nc") and not renders_measured(None)
