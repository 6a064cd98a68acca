"""Every model with a native Mitsuba twin: its XML export loads in a plain Mitsuba 3 (a fresh process that
never imports gonio): issue 36, probe 7. The two-lobe models (roughplastic2, roughconductor2:
a ``blendbsdf`` of two lobes) wrote their lobes as ``<texture>``, which Mitsuba refuses
("Type mismatch: the instantiated plugin "roughplastic" is of type "bsdf""); nested plugins are
now written with the tag Mitsuba gives their type. (``tabulated``, ``cooktorrance`` and
``orennayar`` export gonio's own Python plugins, which a plain Mitsuba cannot know: issue 34's
portable export.)"""

import subprocess
import sys

import numpy as np

import gonio.models as gm
from gonio.fitting.formats.mitsuba_xml import mitsuba_document

NATIVE = [n for n in gm.names()
          if not str(gm.get(n).to_mitsuba(gm.get(n).validate({}))["type"]).startswith("gonio_")]

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
