"""Study (issue 35): how close can a reciprocal, non-negative BRDF render to an RGL file?

The file f(wi, wo) (gonio's convention: wi toward the light, wo toward the viewer) is tabulated
once on a (theta_i, theta_o, |phi_i - phi_o|) grid through Mitsuba's ``measured`` plugin and
rendered back through a trilinear Python BSDF in the preview scenes, beside the file itself
(``measured``, the same seeds), as :func:`gonio.fitting.render.preview.preview` compares a fit.
Variants: the file's own table (the path's floor: cosine sampling), its transpose, its symmetric
part, that part clamped at zero, the file clamped at zero; ``--fit``: gonio's ``--model auto`` fit
(or a pickled one) through its own plugin. Each at 256 spp (the issue's metric) and 4096 spp (the
noise nearly gone), with each channel's rendered total over the file's.
Run: ``python tests/bench/reciprocal_bound.py FILE.bsdf [--fit --cache FIT.pkl]``.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from gonio.core.geometry import directions
from gonio.fitting.formats import RGLBRDF
from gonio.fitting.render.preview import (LIGHTINGS, _render_seeds, delta_e_2000, matched_noise_floor,
                                          sphere_mask)
from gonio.models.mitsuba import select_variant
from gonio.models.mitsuba.plugins import bsdf_base

N_THETA, N_PHI = 90, 91          # 1-deg theta cells (centres), 2-deg phi nodes on [0, pi]
_TABLES: dict[str, np.ndarray] = {}
_PLUGIN = "gonio_study_table"


def theta_nodes(n=N_THETA):
    return (np.arange(n) + 0.5) * (0.5 * math.pi / n)


def file_table(path, variant=None) -> np.ndarray:
    """f (3, n_theta_i, n_theta_o, n_phi) of the file at the grid's nodes (light, viewer, phi)."""
    rgl = RGLBRDF(path, variant)
    t = theta_nodes()
    p = np.linspace(0.0, math.pi, N_PHI)
    TI, TO, P = np.meshgrid(t, t, p, indexing="ij")
    wi = directions(TI.ravel(), P.ravel())
    wo = directions(TO.ravel(), np.zeros(TO.size))
    f = rgl.eval(wi, wo)
    return np.ascontiguousarray(f.T.reshape(3, N_THETA, N_THETA, N_PHI))


def _register(mi, dr):
    base = bsdf_base(mi, dr)
    dt, dp = 0.5 * math.pi / N_THETA, math.pi / (N_PHI - 1)

    class TableBSDF(base):
        def __init__(self, props):
            super().__init__(props)
            table = _TABLES[props["table_key"]]
            self.c = [mi.Float(table[c].ravel().astype(np.float32)) for c in range(3)]

        def _f(self, si, wo):
            wi_g, wo_g = wo, si.wi          # gonio: wi toward the light, wo toward the viewer
            ti = dr.safe_acos(mi.Frame3f.cos_theta(wi_g)) / dt - 0.5
            to = dr.safe_acos(mi.Frame3f.cos_theta(wo_g)) / dt - 0.5
            dphi = dr.abs(dr.atan2(wi_g.y, wi_g.x) - dr.atan2(wo_g.y, wo_g.x))
            dphi = dr.select(dphi > dr.pi, 2.0 * dr.pi - dphi, dphi) / dp
            out = []
            idx, wts = [], []
            for s, n in ((ti, N_THETA), (to, N_THETA), (dphi, N_PHI)):
                s = dr.clip(s, 0.0, n - 1.0)
                i0 = dr.minimum(mi.UInt32(dr.floor(s)), n - 2)
                idx.append(i0)
                wts.append(s - mi.Float(i0))
            for c in range(3):
                acc = mi.Float(0.0)
                for a in (0, 1):
                    for b in (0, 1):
                        for e in (0, 1):
                            w = ((wts[0] if a else 1.0 - wts[0]) * (wts[1] if b else 1.0 - wts[1])
                                 * (wts[2] if e else 1.0 - wts[2]))
                            k = ((idx[0] + a) * N_THETA + idx[1] + b) * N_PHI + idx[2] + e
                            acc += w * dr.gather(mi.Float, self.c[c], k)
                out.append(acc)
            return mi.Color3f(*out)

        def to_string(self):
            return "StudyTableBSDF[]"

    mi.register_bsdf(_PLUGIN, lambda props: TableBSDF(props))


def table_dict(key, table, variant):
    import drjit as dr
    import mitsuba as mi

    with mi.scoped_set_variant(variant):
        if _PLUGIN not in _TABLES:
            _register(mi, dr)
            _TABLES[_PLUGIN] = np.zeros(1)
    _TABLES[key] = table
    return {"type": _PLUGIN, "table_key": key}


def compare(bsdf, meas, size, spp, seed, variant):
    """Per lighting: (mean dE00, matched-seed noise floor) of ``bsdf`` against the rendered file."""
    mask = sphere_mask(size)
    out = {}
    for lighting in LIGHTINGS:
        a0, a1 = _render_seeds(bsdf, lighting, size, spp, [seed, seed + 1], variant)
        m0, m1 = meas[(lighting, spp)]
        de = delta_e_2000(a0, m0)[mask]
        noise = matched_noise_floor(a0, m0, a1, m1)[mask]
        ratio = a0[mask].sum(axis=0) / m0[mask].sum(axis=0)
        out[lighting] = (float(de.mean()), float(noise.mean()), ratio.tolist())
    return out


def chosen_fit(path, seed=0, cache=None):
    """gonio's ``--model auto`` fit of the file (as ``gonio perf real`` makes it): (model, params),
    pickled to ``cache`` when given (a later run reads it back)."""
    import pickle
    from pathlib import Path

    if cache and Path(cache).is_file():
        with open(cache, "rb") as fh:
            model, params = pickle.load(fh)
        if isinstance(model, dict):     # (options, params) of a tabulated fit (the other studies' pickles)
            import gonio.models as gm

            model = gm.get("tabulated", **model)
        return model, params
    from gonio.fitting.likelihood.loss import REAL_DEFAULT_LOSS
    from gonio.fitting.realdata import rgl_samples
    from gonio.fitting.selection.auto import auto_fit

    best, _, note = auto_fit(rgl_samples(path), str(path), seed=seed, loss=REAL_DEFAULT_LOSS,
                             rng=np.random.default_rng(seed))
    print(note, flush=True)
    out = (best.model, best.params)
    if cache:
        with open(cache, "wb") as fh:
            pickle.dump(out, fh)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=int, nargs="+", default=[256, 4096])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fit", action="store_true", help="also render gonio's --model auto fit of the file")
    ap.add_argument("--cache", help="pickle of that fit (read when present, else written)")
    ap.add_argument("--only", nargs="*", help="variants to render (default all)")
    args = ap.parse_args(argv)
    variant = select_variant(None)
    f = file_table(args.file, variant)
    ft = np.swapaxes(f, 1, 2)
    sym = 0.5 * (f + ft)
    variants = {"file table": f, "transpose": ft, "symmetric": sym, "symmetric >= 0": np.maximum(sym, 0.0),
                "file >= 0": np.maximum(f, 0.0)}
    neg = {c: float(np.mean(sym[c] < 0)) for c in range(3)}
    print(f"{args.file}: share of grid cells with a negative symmetric part r/g/b: "
          + " / ".join(f"{neg[c]:.3f}" for c in range(3)), flush=True)
    meas_dict = {"type": "measured", "filename": str(args.file)}
    meas = {(lt, spp): _render_seeds(meas_dict, lt, args.size, spp, [args.seed, args.seed + 1], variant)
            for lt in LIGHTINGS for spp in args.spp}
    bsdfs = {name: table_dict(name, np.ascontiguousarray(t), variant) for name, t in variants.items()
             if not args.only or name in args.only}
    if args.fit:
        model, params = chosen_fit(args.file, args.seed, args.cache)
        bsdfs["gonio fit"] = model.to_mitsuba(params)
    rows = {}
    for name, bsdf in bsdfs.items():
        for spp in args.spp:
            r = compare(bsdf, meas, args.size, spp, args.seed, variant)
            rows[f"{name} @ {spp}"] = r
            print(f"{name:16s} spp {spp:5d}  env {r['env'][0]:.3f} (floor {r['env'][1]:.3f})  "
                  f"area {r['area'][0]:.3f} (floor {r['area'][1]:.3f})  mean {0.5 * (r['env'][0] + r['area'][0]):.3f}  "
                  f"rgb / file: env {' '.join(f'{v:.3f}' for v in r['env'][2])}, area {' '.join(f'{v:.3f}' for v in r['area'][2])}",
                  flush=True)
    return rows


if __name__ == "__main__":
    main()
