"""Study (issue 35): can ``tabulated`` render within CIEDE2000 1 of an RGL file at all?

A capacity test: the model is fitted to the preview scenes' pixels themselves (both lightings,
:func:`scene_pairs_excess.preview_pairs` with ``k`` light samples, seed 0; scipy's
``least_squares``, residuals per channel over its image rms as
:func:`gonio.fitting.selection.scene_fit.fit_in_scene` scales them), started from a pickled fit,
and scored on pairs drawn with another seed (so a fit to one draw's noise does not count).
Run: ``python tests/bench/pixel_capacity.py FILE.bsdf FIT.pkl``.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fit_data_variants import score  # noqa: E402
from scene_pairs_excess import preview_pairs  # noqa: E402

import gonio.models as gm  # noqa: E402
from gonio.fitting.formats import RGLBRDF  # noqa: E402
from gonio.fitting.optimise.space import ParameterSpace  # noqa: E402
from gonio.fitting.render.preview import LIGHTINGS  # noqa: E402
from gonio.fitting.selection.scene_fit import pixel_values  # noqa: E402
from gonio.models.mitsuba import select_variant  # noqa: E402


def load_fit(path):
    """(options, params) of a pickled tabulated fit: a dict with ``params`` (and ``options``),
    or a tuple whose first two items are the model (or its options) and the params."""
    with open(path, "rb") as fh:
        d = pickle.load(fh)
    if isinstance(d, dict):
        return d.get("options", {}), d["params"]
    model, params = d[:2]
    return (model if isinstance(model, dict) else dict(model.options)), params


def pixel_sets(file, rgl, k, variant):
    """(train, test, train pixels, test pixels, scale): both lightings' preview pairs with ``k``
    light samples (seed 0) and 64 (seed 1), the file's pixels at each, and the train pixels'
    rms per channel (the residuals' scale)."""
    train = {lt: preview_pairs(file, lt, 64, k, 0, variant) for lt in LIGHTINGS}
    test = {lt: preview_pairs(file, lt, 64, 64, 1, variant) for lt in LIGHTINGS}
    tgt = {lt: pixel_values(rgl.eval(sp.wi, sp.wo) * sp.wi[:, 2:3], sp) for lt, sp in train.items()}
    test_pix = {lt: pixel_values(rgl.eval(sp.wi, sp.wo) * sp.wi[:, 2:3], sp) for lt, sp in test.items()}
    return train, test, tgt, test_pix, {lt: np.sqrt(np.mean(t * t, axis=0)) for lt, t in tgt.items()}


def pixel_fit(model, space, residual, start, test, test_pix, nfev):
    """scipy's ``least_squares`` of ``residual`` (over the unit box of ``space``) from ``start``;
    prints the test pixels' dE00 before and after and the run's cost; returns the fitted params."""
    before = score(model, start, test, test_pix)
    t0 = time.perf_counter()
    u0 = np.clip(space.to_unit(space.from_params(model.validate(start))), 1e-6, 1 - 1e-6)
    r = least_squares(residual, u0, bounds=(0.0, 1.0), method="trf", x_scale="jac", max_nfev=nfev)
    fitted = space.to_params(space.from_unit(r.x))
    after = score(model, fitted, test, test_pix)
    for name, s in (("start", before), ("pixel fit", after)):
        print(f"{name:10s} " + "  ".join(f"{lt} dE {v[0]:.3f} rgb/file {' '.join(f'{x:.3f}' for x in v[1])}"
                                        for lt, v in s.items()) + f"  mean {np.mean([v[0] for v in s.values()]):.3f}")
    print(f"least_squares: {r.nfev} evaluations, {time.perf_counter() - t0:.0f} s, status {r.status}")
    return fitted


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("fit")
    ap.add_argument("-k", type=int, default=16)
    ap.add_argument("--nfev", type=int, default=20)
    ap.add_argument("--save")
    ap.add_argument("--log-eps", type=float, help="residuals ln(pixel + eps rms) instead (target clipped at 0, as "
                    "delta_e_2000 clips)")
    ap.add_argument("--tilt-knots", type=int, nargs="+", help="tabulated's colour-tilt knots (the start's "
                    "tilt carried over)")
    args = ap.parse_args(argv)
    variant = select_variant(None)
    rgl = RGLBRDF(args.file, variant)
    options, params = load_fit(args.fit)
    model = gm.get("tabulated", **options)
    if args.tilt_knots:
        import gonio.models.catalogue.tabulated as tab

        old = {c: sum(np.log(params.pop(f"ndf_tilt_{c}_{k}")) * b for k, b in zip(tab.TILT_KNOTS, tab.TILT_BASIS))
               for c in "rb"}
        tab.TILT_KNOTS = tuple(args.tilt_knots)
        tab.TILT_BASIS = tab._tilt_basis()
        params.update({f"ndf_tilt_{c}_{k}": float(np.exp(old[c][k])) for c in "rb" for k in tab.TILT_KNOTS})
        model = gm.get("tabulated", **model.options)
    train, test, tgt, test_pix, scale = pixel_sets(args.file, rgl, args.k, variant)
    space = ParameterSpace(model, n_channels=3)

    def residual(u):
        p = space.to_params(space.from_unit(u))
        out = []
        for lt, sp in train.items():
            pred = pixel_values(model.eval(sp.wi, sp.wo, p) * sp.wi[:, 2:3], sp)
            if args.log_eps:
                e = args.log_eps * scale[lt]
                out.append((np.log(np.maximum(pred, 0.0) + e) - np.log(np.maximum(tgt[lt], 0.0) + e)).ravel())
            else:
                out.append(((pred - tgt[lt]) / scale[lt]).ravel())
        return np.concatenate(out)

    fitted = pixel_fit(model, space, residual, params, test, test_pix, args.nfev)
    if args.save:
        with open(args.save, "wb") as fh:
            pickle.dump((dict(model.options), fitted), fh)


if __name__ == "__main__":
    main()
