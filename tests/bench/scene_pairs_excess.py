"""Study (issue 35): where in (theta_light, theta_view) a fit's rendered colour departs from the file's.

The preview scenes' pixels (:func:`gonio.fitting.render.preview`'s two lightings) as
:func:`gonio.fitting.selection.scene_fit.scene_pixels` takes them: per pixel, k light samples,
the same pairs for every BSDF (common random numbers, no Monte Carlo noise between them). For the
file, its symmetric part clamped at zero and a fit, this prints the pixel CIEDE2000 against the
file and each channel's share of the rendered light by theta_light and theta_view band, so the
excess of a channel can be traced to the pairs that carry it. Run:
``python tests/bench/scene_pairs_excess.py FILE.bsdf --cache FIT.pkl`` (the pickle of
``reciprocal_bound.py --cache``).
"""

from __future__ import annotations

import argparse
import pickle

import numpy as np

from gonio.fitting.formats import RGLBRDF
from gonio.fitting.render.preview import LIGHTINGS, _scene_dict, delta_e_2000
from gonio.fitting.selection.scene_fit import pixel_values, scene_pixels
from gonio.models.mitsuba import select_variant

BANDS = np.radians([0, 30, 50, 60, 70, 80, 90.01])


def preview_pairs(path, lighting, size, k, seed, variant):
    import mitsuba as mi

    with mi.scoped_set_variant(variant):
        bsdf = {"type": "measured", "filename": str(path), "id": "sample"}
        scene = mi.load_dict(_scene_dict(mi, lighting, bsdf, size, 16))
        return scene_pixels(scene, rng=np.random.default_rng(seed), k=k, variant=variant, name=lighting)


def band_table(sp, contrib):
    """Per (theta_light, theta_view) band: each channel's rendered light, as a share of the file's total."""
    tl = np.arctan2(np.hypot(sp.wi[:, 0], sp.wi[:, 1]), sp.wi[:, 2])
    tv = np.arctan2(np.hypot(sp.wo[:, 0], sp.wo[:, 1]), sp.wo[:, 2])
    il, iv = np.digitize(tl, BANDS) - 1, np.digitize(tv, BANDS) - 1
    out = np.zeros((len(BANDS) - 1, len(BANDS) - 1, 3))
    np.add.at(out, (il, iv), contrib)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("--cache", required=True, help="pickle (model, params) of the fit")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("-k", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    variant = select_variant(None)
    rgl = RGLBRDF(args.file, variant)
    with open(args.cache, "rb") as fh:
        model, params = pickle.load(fh)
    for lighting in LIGHTINGS:
        sp = preview_pairs(args.file, lighting, args.size, args.k, args.seed, variant)
        ci = sp.wi[:, 2:3]
        f = rgl.eval(sp.wi, sp.wo)
        ft = rgl.eval(sp.wo, sp.wi)
        brdfs = {"file": f, "transpose": ft, "symmetric >= 0": np.maximum(0.5 * (f + ft), 0.0),
                 "gonio fit": model.eval(sp.wi, sp.wo, params)}
        pix = {n: pixel_values(v * ci, sp) for n, v in brdfs.items()}
        contrib = {n: v * ci * sp.weight for n, v in brdfs.items()}
        total = contrib["file"].sum(axis=0)
        print(f"== {lighting}: {sp.n_pixels} pixels, {len(sp.wi)} pairs")
        for n in brdfs:
            de = delta_e_2000(pix[n], pix["file"])
            print(f"{n:16s} pixel dE00 {de.mean():.3f}  rgb / file {' '.join(f'{v:.3f}' for v in contrib[n].sum(0) / total)}")
        base = band_table(sp, contrib["file"])
        for n in ("symmetric >= 0", "gonio fit"):
            d = band_table(sp, contrib[n]) - base
            print(f"-- {n} minus file, blue, share of the file's blue total (rows theta_light, cols theta_view "
                  f"{np.degrees(BANDS[:-1]).astype(int).tolist()}):")
            for i in range(len(BANDS) - 1):
                print(f"   {int(np.degrees(BANDS[i])):3d}  " + " ".join(f"{v:+.3f}" for v in d[i, :, 2] / total[2])
                      + f"   | green {' '.join(f'{v:+.3f}' for v in d[i, :, 1] / total[1])}")
        print("-- file's blue share per band:")
        for i in range(len(BANDS) - 1):
            print(f"   {int(np.degrees(BANDS[i])):3d}  " + " ".join(f"{v:+.3f}" for v in base[i, :, 2] / total[2]))


if __name__ == "__main__":
    main()
