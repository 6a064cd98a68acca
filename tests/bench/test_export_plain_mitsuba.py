"""Every model with a native Mitsuba twin: its XML export loads in a plain Mitsuba 3 (a fresh process that
never imports gonio): issue 36, probe 7. The two-lobe models (roughplastic2, roughconductor2:
a ``blendbsdf`` of two lobes) wrote their lobes as ``<texture>``, which Mitsuba refuses
("Type mismatch: the instantiated plugin "roughplastic" is of type "bsdf""); nested plugins are
now written with the tag Mitsuba gives their type. ``tabulated``, ``cooktorrance`` and ``orennayar``
have no Mitsuba plugin: issue 34, their XML is the closest native BSDF fitted to them, with its
error stated (gonio's own plugins on request: ``--to mitsuba-xml-gonio``)."""

import subprocess
import sys

import numpy as np

import gonio.models as gm
from gonio.fitting.formats.mitsuba_xml import mitsuba_document

NATIVE = [n for n in gm.names() if getattr(type(gm.get(n)), "mitsuba_twin", True)
          and not str(gm.get(n).to_mitsuba(gm.get(n).validate({}))["type"]).startswith("gonio_")]

PLAIN = """
import sys
import mitsuba as mi
mi.set_variant("scalar_rgb")
assert not any(m.startswith("gonio") for m in sys.modules)
bad = []
for path in sys.argv[1:]:
    try:
        bsdf = mi.load_file(path)
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(0.3, 0.0, 0.954)
        v = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(-0.3, 0.1, 0.949))
        if not all(x == x and x >= 0 for x in v):
            bad.append(f"{path}: f_r cos = {v}")
    except Exception as exc:
        bad.append(f"{path}: {str(exc).splitlines()[0][:200]}")
print("\\n".join(bad))
sys.exit(1 if bad else 0)
"""


def test_every_native_models_xml_loads_in_plain_mitsuba(tmp_path):
    rng = np.random.default_rng(36)
    paths = []
    for name in NATIVE:
        model = gm.get(name)
        p = {}
        for par in model.parameters:     # inside the bounds, away from the defaults
            lo, hi = max(par.lower, -10.0), min(par.upper, 10.0)
            v = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), 3 if par.per_channel else None)
            p[par.name] = v
        path = tmp_path / f"{name}.xml"
        path.write_text(mitsuba_document(name, dict(model.options), model.validate(p)))
        paths.append(str(path))
    r = subprocess.run([sys.executable, "-c", PLAIN, *paths], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr[-2000:]
    assert set(NATIVE) >= {"roughplastic2", "roughconductor2"}


#: Paint-like values of the models without a Mitsuba plugin (random ones are no material; the tabulated
#: model's defaults are a glossy paint's peak)
PAINT = {"cooktorrance": {"diffuse_reflectance": [0.5, 0.3, 0.1], "specular_reflectance": 0.2, "roughness": 0.2,
                          "f0": 0.04},
         "orennayar": {"reflectance": [0.6, 0.5, 0.4], "sigma": 0.4}, "tabulated": {},
         # tests/fitting/test_spectral_fit.py's flake paint in three channels (issue 39)
         "flakepaint": {"diffuse_reflectance": [0.08, 0.05, 0.02], "specular_reflectance": 0.9, "alpha": 0.02,
                        "eta": 1.5, "haze_reflectance": 0.01, "haze_alpha": 0.05, "flake_reflectance": [0.3, 0.15, 0.05],
                        "flake_alpha": 0.3, "flake_exponent": 0.3, "flake_widen": 0.3}}
# the same paint with irid_flake_paint2's diffraction rings (issue 35)
PAINT["gratingpaint"] = {**PAINT["flakepaint"], "grating_reflectance": 0.1, "grating_period": 0.66, "grating_width": 0.1}

EVAL = """
import sys
import numpy as np
import mitsuba as mi
mi.set_variant("scalar_rgb")
assert not any(m.startswith("gonio") for m in sys.modules)
wi, wo = np.load(sys.argv[1])
for path in sys.argv[3:]:
    bsdf = mi.load_file(path)
    si = mi.SurfaceInteraction3f()
    ctx = mi.BSDFContext()
    out = []
    for a, b in zip(wi.tolist(), wo.tolist()):
        si.wi = mi.Vector3f(*b)                  # Mitsuba's si.wi points to the sensor: gonio's wo
        v = bsdf.eval(ctx, si, mi.Vector3f(*a))  # f_r cos(theta_i)
        out.append((v[0], v[1], v[2]))
    np.save(path + ".npy", np.array(out) / np.maximum(wi[:, 2:3], 1e-12))
"""


def test_every_registered_model_exports_xml_a_plain_mitsuba_loads_and_says_how_close(tmp_path, capsys):
    """Issue 34: ``gonio convert FIT --to mitsuba-xml`` of any model (those ``--model auto`` picks for real
    paints included) loads in a process without gonio; a model without a Mitsuba plugin is the closest
    native BSDF fitted to it, and the error printed and written in the XML is what a plain Mitsuba's
    values show (f_r cos_i cos_o, relative RMS; float32 evaluation adds < 1e-4)."""
    import re

    from gonio.cli import main as cli
    from gonio.fitting.formats.native import check_directions, relative_error
    from gonio.fitting.formats.mitsuba_xml import write_mitsuba_document

    rng = np.random.default_rng(34)
    wi, wo = check_directions()
    np.save(tmp_path / "dirs.npy", np.stack([wi, wo]))
    cases = {}
    for name in gm.names():
        if name in ("difftrans", "roughslab"):   # issue 37: transmitters no native Mitsuba 3.9 BSDF stands for
            continue
        model = gm.get(name)
        p = {}
        if name != "gratingpaint":       # added later: drawing nothing keeps every other model's draws
            for par in model.parameters:     # inside the bounds, away from the defaults
                lo, hi = max(par.lower, -10.0), min(par.upper, 10.0)
                p[par.name] = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), 3 if par.per_channel else None)
        if name in PAINT:                # the models --model auto picks for paints: a paint's values
            p = dict(PAINT[name])
        p = model.validate(p)
        path = tmp_path / f"{name}.xml"
        note = write_mitsuba_document(path, name, dict(model.options), p)
        cases[name] = (model, p, path, note)
    assert {n for n, c in cases.items() if c[3]} == {"cooktorrance", "orennayar", "tabulated", "flakepaint",
                                                    "gratingpaint"}
    r = subprocess.run([sys.executable, "-c", EVAL, str(tmp_path / "dirs.npy"), "--", *(str(c[2]) for c in cases.values())],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    for name, (model, p, path, note) in cases.items():
        got = np.load(str(path) + ".npy")
        err = relative_error(model.eval(wi, wo, p), got, wi, wo)
        text = path.read_text()
        assert not re.search(r"type=\"gonio_", text)
        if note is None:                 # the model's own plugin
            assert err.max() < 1e-4, (name, err)
            continue
        stated = np.array(re.search(r"cos_i cos_o ([\d.]+)/([\d.]+)/([\d.]+) %", note).groups(), float) / 100
        assert note in text.replace("\n", " ")
        assert np.all(err <= stated + 5e-4 + 1e-4), (name, err, stated)     # stated to 0.1 %: half of it, + float32
        assert np.all(err >= stated - 5e-4 - 1e-4), (name, err, stated)
        # flakepaint's flake lobe (D / (cos_i cos_o)^p) is no microfacet lobe: its closest native family,
        # roughplastic, is 17.3 % off in red (measured 2026-12-04), gratingpaint (its rings on top) 16.4 %;
        # the others are paints' single lobes
        assert stated.max() < (0.25 if name in ("flakepaint", "gratingpaint") else 0.15), (name, note)


def test_convert_prints_the_approximation_and_keeps_gonios_plugin_on_request(tmp_path, capsys):
    from gonio.cli import main as cli
    from gonio.fitting import fit, fit_document, write_json_atomic
    from gonio.perf.fit import simulate_capture

    model = gm.get("orennayar")
    meas, _ = simulate_capture(model, {"reflectance": np.array([0.6, 0.4, 0.2]), "sigma": 0.4}, 60,
                               np.random.default_rng(4))
    path = write_json_atomic(tmp_path / "fit.json", fit_document(fit(meas, model, rng=np.random.default_rng(0)),
                                                                 meas, seed=0))
    out = tmp_path / "on.xml"
    assert cli.main(["convert", str(path), "--to", "mitsuba-xml", "--out", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].startswith("model orennayar has no Mitsuba 3 plugin: written as ") and printed[1] == f"wrote {out}"
    assert 'type="gonio_orennayar"' not in out.read_text()
    assert cli.main(["convert", str(path), "--to", "mitsuba-xml-gonio", "--out", str(tmp_path / "g.xml")]) == 0
    assert 'type="gonio_orennayar"' in (tmp_path / "g.xml").read_text()
    assert "the loading process must import gonio" in capsys.readouterr().out


def test_a_transmitter_without_a_native_twin_is_refused_not_fitted_by_a_reflector():
    """difftrans (gonio's plugin; Mitsuba 3 has no diffuse transmitter): every native family
    reflects only, so on the upper hemisphere a black reflector would "fit" it with a zero
    stated error. The native export refuses, in one line naming the plugin export instead."""
    import pytest

    from gonio.fitting.formats.native import native_bsdf
    from gonio.fitting.formats.readback import ExportError

    with pytest.raises(ExportError, match="transmits.*mitsuba-xml-gonio") as info:
        native_bsdf("difftrans", {}, {"transmittance": [0.5, 0.4, 0.3]})
    assert "\n" not in str(info.value)
