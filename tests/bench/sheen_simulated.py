"""Study (issue 35): tabulated's sheen option on simulated truths it was not built on.

Each truth (principled with and without Burley's sheen, a felt-like white, a blue rough plastic)
is evaluated at an RGL file's own sample directions (cardboard's), with 1 % + 1e-4 Gaussian
noise (seeded Generator), and fitted by ``fit_tabulated`` (log loss) plain, then with
``sheen="ggx"`` from the plain fit, as ``gonio fit --model tabulated --option sheen=ggx`` would;
printed: Ngan and log error against the truth on perf real's dense grid, the product-shot
pixel CIEDE2000 against the truth (auto's check), the objective and the time. Needs
../shared/data/rgl. Run: ``python tests/bench/sheen_simulated.py``.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

import gonio.models as gm
from gonio.fitting.realdata import rgl_samples
from gonio.fitting.optimise.tabulated_start import fit_tabulated
from gonio.fitting.selection.by_pixels import PixelCheck
from gonio.perf.real import dense_grid, metrics

geo = rgl_samples("/work/shared/data/rgl/cardboard_rgb.bsdf")   # an RGL file's directions and weights
wi_d, wo_d = dense_grid()
truths = {
    "principled dark green, sheen 1": ("principled", dict(base_color=np.array([0.05, 0.15, 0.03]), roughness=0.5, sheen=1.0, specular=0.5)),
    "principled dark green, sheen 0": ("principled", dict(base_color=np.array([0.05, 0.15, 0.03]), roughness=0.5, sheen=0.0, specular=0.5)),
    "principled white felt, sheen 0.6 tint 0.5": ("principled", dict(base_color=np.array([0.7, 0.7, 0.65]), roughness=0.9, sheen=0.6, sheen_tint=0.5, specular=0.3)),
    "roughplastic ggx 0.2 blue": ("roughplastic", dict(alpha=0.2, diffuse_reflectance=np.array([0.05, 0.08, 0.3]))),
}
rng = np.random.default_rng(7)
for label, (name, kw) in truths.items():
    tm = gm.get(name)
    tp = tm.validate({**tm.defaults(), **kw})
    f = np.asarray(tm.eval(geo.wi, geo.wo, tp), float)
    sigma = 0.01 * np.abs(f) + 1e-4
    y = f + sigma * rng.standard_normal(f.shape)
    meas = dataclasses.replace(geo, brdf=y, brdf_std=sigma, use=np.ones_like(f, bool))
    f_d = np.asarray(tm.eval(wi_d, wo_d, tp), float)
    check = PixelCheck(tm.to_mitsuba(tp), seed=0)
    row = []
    plain = None
    for sheen in ("none", "ggx"):
        t0 = time.perf_counter()
        kw_fit = dict(loss="log", covariance=False)
        if sheen == "ggx":
            r = fit_tabulated(meas, rng=np.random.default_rng(0), sheen="ggx", start=plain.params, **kw_fit)
        else:
            r = fit_tabulated(meas, rng=np.random.default_rng(0), **kw_fit)
            plain = r
        dt = time.perf_counter() - t0
        g = metrics(r.model.eval(wi_d, wo_d, r.params), f_d, wi_d)
        de = check.delta_e(r.model, r.params)[0]
        extra = f" a_s {float(r.params['sheen_alpha']):.2f} A3 {np.round(r.params['sheen_3'], 3).tolist()}" if sheen == "ggx" else ""
        row.append(f"{sheen}: Ngan {g['ngan']:.4f} log {g['log']:.5f} pix {de:.3f} obj {r.objective:.4g} {dt:.1f}s{extra}")
    print(label, "|", " || ".join(row), flush=True)
