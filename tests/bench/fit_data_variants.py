"""Study (issue 35): ``tabulated`` fitted to variants of an RGL file's data, scored by its preview pixels.

Data: ``file``, ``clamped`` (at zero), ``symmetric>=0`` (the file's symmetric part clamped at
zero); ``-body`` fits option body="table". Loss (prefix): none, the default log loss;
``equal:`` each channel divided by its mean over green's; ``levelK:`` divided by K times its own
mean f cos_i (the log loss then reads ln(1 + f cos / a_c); rho and F unbounded above, data_start
still clips rho at 1); ``lumK:`` chi2 with sigma = (a + Y cos_i) / cos_i, Y the pair's measured
luminance, a = K times its mean. The fit is ``fit_tabulated`` on the file's own samples; the
score, the CIEDE2000 of the preview scenes' pixels against the file's (common random numbers:
``scene_pairs_excess.preview_pairs``) per lighting, with each channel's total over the file's.
Run: ``python tests/bench/fit_data_variants.py FILE.bsdf [VARIANT...] [--tilt-knots K...]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from scene_pairs_excess import preview_pairs  # noqa: E402

from gonio.fitting.formats import RGLBRDF  # noqa: E402
from gonio.fitting.optimise.tabulated_start import fit_tabulated  # noqa: E402
from gonio.fitting.realdata import rgl_samples  # noqa: E402
from gonio.fitting.render.preview import LIGHTINGS, delta_e_2000  # noqa: E402
from gonio.fitting.selection.scene_fit import pixel_values  # noqa: E402
from gonio.models.mitsuba import select_variant  # noqa: E402


def variant_data(meas, rgl, name):
    f = meas.brdf
    if name in ("file", "file-body"):
        return meas
    if name == "clamped":
        return dataclasses.replace(meas, brdf=np.maximum(f, 0.0))
    if name == "symmetric>=0":
        ft = rgl.eval(meas.wo, meas.wi)
        return dataclasses.replace(meas, brdf=np.maximum(0.5 * (f + ft), 0.0))
    raise ValueError(f"unknown variant {name!r}")


def channel_scale(meas, level=None):
    """Each channel's solid-angle- and cosine-weighted mean of f cos_i over green's: (3,); with
    ``level``, the channel's own mean times ``level`` (the log loss then reads ln(1 + f cos / a_c))."""
    w = meas.weight[:, None]
    m = np.sum(w * np.maximum(meas.brdf, 0.0) * meas.wi[:, 2:3], axis=0) / np.sum(w)
    return m / m[1] if level is None else m * level


def luminance_sigma(meas, kappa):
    """``meas`` with sigma = (a + Y cos_i) / cos_i for every channel of a pair: Y the measured
    luminance there (Rec. 709 weights, at least 0), a = kappa times Y cos_i's solid-angle mean,
    so the chi2 residual is (f_model - f) cos_i / (a + Y cos_i): a colour error relative to
    the pair's luminance (above a), absolute below it."""
    ci = np.clip(meas.wi[:, 2:3], 1e-3, 1.0)
    y = np.maximum(meas.brdf @ np.array([0.2126, 0.7152, 0.0722]), 0.0)[:, None]
    a = kappa * np.sum(meas.weight[:, None] * y * ci) / np.sum(meas.weight)
    std = np.broadcast_to((a + y * ci) / ci, meas.brdf.shape).copy()
    return dataclasses.replace(meas, brdf_std=std)


def _wide_tabulated():
    """tabulated with rho and F unbounded above (data divided by a channel level need them > 1)."""
    import gonio.models.catalogue.tabulated as tab
    from gonio.models.base import Parameter

    class Wide(tab.Tabulated):
        def _parameters(self):
            out = []
            for p in super()._parameters():
                if p.name == "diffuse_reflectance" or p.name.startswith("fresnel_"):
                    p = Parameter(p.name, p.default, p.lower, 1e4, p.unit, p.description, p.per_channel)
                out.append(p)
            return tuple(out)

    Wide.__module__ = tab.__name__
    tab.Tabulated = Wide


def rescaled(params, s):
    """Parameters fitted to data divided by ``s`` per channel, back on the data's scale
    (tabulated is linear in (rho_c, F_c) per channel)."""
    out = dict(params)
    for k, v in params.items():
        if k == "diffuse_reflectance" or k.startswith("fresnel_"):
            out[k] = np.asarray(v) * s
    return out


def score(model, params, pairs, file_pix):
    out = {}
    for lighting, sp in pairs.items():
        pix = pixel_values(model.eval(sp.wi, sp.wo, params) * sp.wi[:, 2:3], sp)
        out[lighting] = (float(delta_e_2000(pix, file_pix[lighting]).mean()),
                         pix.sum(axis=0) / file_pix[lighting].sum(axis=0))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("variants", nargs="*", default=["file", "clamped", "symmetric>=0"])
    ap.add_argument("--loss", default="log")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save", help="folder for a pickle (model, params) of each fit")
    ap.add_argument("--tilt-knots", type=int, nargs="+", help="tabulated's colour-tilt knots (default its own)")
    args = ap.parse_args(argv)
    if args.tilt_knots:
        import gonio.models.catalogue.tabulated as tab

        tab.TILT_KNOTS = tuple(args.tilt_knots)
        tab.TILT_BASIS = tab._tilt_basis()
    variant = select_variant(None)
    rgl = RGLBRDF(args.file, variant)
    meas = rgl_samples(args.file)
    pairs = {lt: preview_pairs(args.file, lt, 64, 64, args.seed, variant) for lt in LIGHTINGS}
    file_pix = {lt: pixel_values(rgl.eval(sp.wi, sp.wo) * sp.wi[:, 2:3], sp) for lt, sp in pairs.items()}
    for name in args.variants:
        lum = float(name.split(":")[0][3:]) if name.startswith("lum") else None
        equal = name.startswith(("equal:", "level"))
        data = variant_data(meas, rgl, name.split(":")[-1])
        level = float(name.split(":")[0][5:]) if name.startswith("level") else None
        scale = channel_scale(data, level) if equal else np.ones(3)
        if level is not None:
            _wide_tabulated()
        if equal:
            data = dataclasses.replace(data, brdf=data.brdf / scale, brdf_std=data.brdf_std / scale)
        loss = args.loss
        if lum is not None:
            data, loss = luminance_sigma(data, lum), "chi2"
        t0 = time.perf_counter()
        res = fit_tabulated(data, rng=np.random.default_rng(args.seed), loss=loss,
                            body="table" if name.endswith("-body") else "lambert", covariance=False,
                            enforce_energy=level is None)
        params = rescaled(res.params, scale)
        s = score(res.model, params, pairs, file_pix)
        rho = np.round(np.asarray(params["diffuse_reflectance"]), 4).tolist()
        print(f"{name:20s} scale {np.round(scale, 3).tolist()} {loss:8s} fit {time.perf_counter() - t0:5.1f} s  objective {res.objective:.5g}  rho {rho}  "
              + "  ".join(f"{lt} dE {v[0]:.3f} rgb/file {' '.join(f'{x:.3f}' for x in v[1])}" for lt, v in s.items())
              + f"  mean {np.mean([v[0] for v in s.values()]):.3f}", flush=True)
        if args.save:
            Path(args.save).mkdir(parents=True, exist_ok=True)
            with open(Path(args.save) / f"{name.replace(':', '-')}-{args.loss}.pkl", "wb") as fh:
                pickle.dump((dict(res.model.options), {k: np.asarray(v) for k, v in params.items()}), fh)


if __name__ == "__main__":
    main()
