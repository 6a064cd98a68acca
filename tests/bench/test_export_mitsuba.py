"""``gonio convert FIT --to mitsuba-xml`` writes a file Mitsuba 3 loads by itself
(``mitsuba.load_file``) and through ``<include>`` in a scene, and renders what the fit says.

Reference: a Lambertian surface of albedo rho lit at normal incidence by a directional
emitter of irradiance E has radiance L = rho E / pi in every direction (Lambert's law; e.g.
Pharr, Jakob & Humphreys, PBRT 4th ed., sec. 4.3 and 9.2), so an orthographic camera looking
straight down on it sees rho / pi per channel with E = 1; the direct integrator has no noise
for a delta light, so the image equals it to float32 rounding.
"""

import numpy as np
import pytest

import gonio.models as gm
from gonio.cli import main as cli
from gonio.fitting import fit, fit_document, write_json_atomic
from gonio.fitting.formats import MITSUBA_XML_VERSION, mitsuba_document, mitsuba_snippet
from gonio.perf.fit import simulate_capture

mi = pytest.importorskip("mitsuba")


def scalar_rgb():
    """``scalar_rgb`` for a block (Mitsuba's scoped_set_variant needs some variant set first)."""
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    return mi.scoped_set_variant("scalar_rgb")

SCENE = """<scene version="3.0.0">
    <include filename="{include}"/>
    <integrator type="direct"/>
    <sensor type="orthographic">
        <transform name="to_world"><lookat origin="0, 0, 2" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="6"/><integer name="height" value="6"/>
            <rfilter type="box"/></film>
    </sensor>
    <emitter type="directional"><vector name="direction" value="0, 0, -1"/>
        <rgb name="irradiance" value="1, 1, 1"/></emitter>
    <shape type="rectangle"><ref id="gonio_fit"/>
        <transform name="to_world"><scale value="4"/></transform></shape>
</scene>
"""


@pytest.fixture(scope="module")
def fit_file(tmp_path_factory):
    """A diffuse fit of a simulated capture, as a fit file."""
    model = gm.get("diffuse")
    meas, _ = simulate_capture(model, {"reflectance": np.array([0.6, 0.4, 0.2])}, 60, np.random.default_rng(4))
    result = fit(meas, model, rng=np.random.default_rng(0))
    path = tmp_path_factory.mktemp("fit") / "fit.json"
    write_json_atomic(path, fit_document(result, meas, seed=0))
    return path, result


def test_convert_writes_a_file_mitsuba_loads_and_includes(fit_file, tmp_path, capsys):
    path, result = fit_file
    out = tmp_path / "exports" / "mitsuba" / "fit.xml"          # folders that do not exist yet
    assert cli.main(["convert", str(path), "--to", "mitsuba-xml", "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == f"wrote {out}"
    text = out.read_text(encoding="utf-8")
    assert f'version="{MITSUBA_XML_VERSION}"' in text and text.startswith("<?xml")
    with scalar_rgb():
        bsdf = mi.load_file(str(out))
        assert isinstance(bsdf, mi.BSDF)
        (tmp_path / "exports" / "mitsuba" / "scene.xml").write_text(SCENE.format(include="fit.xml"))
        scene = mi.load_file(str(tmp_path / "exports" / "mitsuba" / "scene.xml"))
        img = np.array(mi.render(scene, spp=1))
    assert img.shape == (6, 6, 3)
    np.testing.assert_allclose(img.reshape(-1, 3), np.tile(result.x / np.pi, (36, 1)), rtol=2e-6)


@pytest.mark.parametrize("name,options,params", [
    ("roughplastic", {"distribution": "ggx"}, {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": 0.15}),
    ("cooktorrance", {}, {"diffuse_reflectance": 0.3, "specular_reflectance": 0.2, "roughness": 0.3, "f0": 0.04}),
])
def test_document_loads_as_the_dict_does(tmp_path, name, options, params):
    """The file's BSDF evaluates exactly as ``model.to_mitsuba(params)`` (a native and a Python plugin)."""
    from gonio.models.mitsuba import ensure_registered, eval_cos

    path = tmp_path / "b.xml"
    path.write_text(mitsuba_document(name, options, params), encoding="utf-8")
    _, d = mitsuba_snippet(name, options, params)
    rng = np.random.default_rng(1)
    wi = gm.geometry.directions(np.radians(rng.uniform(0, 80, 50)), rng.uniform(-np.pi, np.pi, 50))
    wo = gm.geometry.directions(np.radians(rng.uniform(0, 80, 50)), rng.uniform(-np.pi, np.pi, 50))
    with scalar_rgb():
        if d["type"].startswith("gonio_"):   # a Python plugin: as in any scene, registered before the file loads
            ensure_registered(name)
        a = eval_cos(mi.load_file(str(path)), wi, wo, "scalar_rgb")
        b = eval_cos(d, wi, wo, "scalar_rgb")
    np.testing.assert_array_equal(a, b)
    assert np.all(a > 0)


def test_snippet_has_no_version_and_attributes_are_escaped():
    """Mitsuba refuses ``version`` below a file's root; a string value never breaks the XML."""
    import xml.etree.ElementTree as ET

    xml, _ = mitsuba_snippet("diffuse", {}, {"reflectance": [0.5, 0.5, 0.5]})
    assert "version=" not in xml
    from gonio.fitting.formats.mitsuba_xml import _xml_lines

    line = _xml_lines({"type": "x", "s": 'a"<b>&--'}, "")[0]
    assert ET.fromstring(line).get("value") == 'a"<b>&--'


def test_convert_refuses_before_making_folders(fit_file, tmp_path, capsys):
    bad = tmp_path / "notafit.json"
    bad.write_text("{}")
    out = tmp_path / "new" / "deeper" / "x.xml"
    assert cli.main(["convert", str(bad), "--to", "mitsuba-xml", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a gonio fit file" in err[0]
    assert not (tmp_path / "new").exists()
