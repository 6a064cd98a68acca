"""Study (issue 35): :mod:`pixel_capacity_shape`'s freedoms fitted to an RGL file's samples, as the product would.

gonio's ``fit``, one local refinement, numpy values and differenced derivatives, started from a
pickled fit (``--set NAME=VALUE`` overrides start values); the loss: log, or ``--lum K``
(:func:`fit_data_variants.luminance_sigma`'s chi2), or ``--chan K`` (chi2, sigma_c = K a_c /
cos_i, a_c the channel's mean f cos_i); ``--data``: the file's variants; ``--staged DEG``: first
the samples with theta_d < DEG, the sheen held. Scored by the preview scenes' pixels against the
file's (seed 0, 64 light samples, :func:`fit_data_variants.score`): do the data, not the pixels,
lead the extra lobe where the render needs it? Run:
``python tests/bench/fit_shape_data.py FILE.bsdf FIT.pkl [--extra sheen ...] [--lum K]``.
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

from fit_data_variants import channel_scale, luminance_sigma, score, variant_data  # noqa: E402
from pixel_capacity_shape import Shape, load_fit  # noqa: E402
from scene_pairs_excess import preview_pairs  # noqa: E402

from gonio.core.geometry import half_vector  # noqa: E402
from gonio.fitting.formats import RGLBRDF  # noqa: E402
from gonio.fitting.optimise.lm import levenberg_marquardt  # noqa: E402
from gonio.fitting.optimise.mle import fit  # noqa: E402
from gonio.fitting.realdata import rgl_samples  # noqa: E402
from gonio.fitting.render.preview import LIGHTINGS  # noqa: E402
from gonio.fitting.selection.scene_fit import pixel_values  # noqa: E402
from gonio.models.mitsuba import select_variant  # noqa: E402
from gonio.models.structure import Structure  # noqa: E402


class DataShape(Shape):
    """:class:`Shape` with no compiled kernel and no tabulated Jacobian (the fit differences)."""

    jacobian_host = None
    jacobian_reference = None

    @property
    def structure(self):
        return Structure(kernel=None)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("fit")
    ap.add_argument("--extra", nargs="*", default=[], choices=("sheen", "wchan", "wknot"))
    ap.add_argument("--lum", type=float)
    ap.add_argument("--chan", type=float, help="chi2 with sigma_c = K a_c / cos_i, a_c the channel's mean f cos_i")
    ap.add_argument("--data", default="file", choices=("file", "clamped", "symmetric>=0"))
    ap.add_argument("--staged", type=float, help="first fit the samples with theta_d below this (deg), the "
                    "sheen held at 0, then all of them")
    ap.add_argument("--set", nargs="*", default=[], help="NAME=VALUE: start values over the pickle's")
    ap.add_argument("--maxeval", type=int, default=20000, help="model evaluations of the local run (fit's "
                    "default 2000 stops a 58-number fit with differenced derivatives before it converges)")
    ap.add_argument("--max-iter", type=int, default=400, help="Levenberg-Marquardt iterations (gonio's 60 stop it "
                    "first)")
    ap.add_argument("--save")
    args = ap.parse_args(argv)
    levenberg_marquardt.__kwdefaults__["max_iter"] = args.max_iter    # study only: the product keeps its 60
    variant = select_variant(None)
    rgl = RGLBRDF(args.file, variant)
    meas = variant_data(rgl_samples(args.file), rgl, args.data)
    options, params = load_fit(args.fit)
    DataShape.extra = frozenset(args.extra)
    model = DataShape(**options)
    start = dict(params)
    for pdef in model.parameters:
        start.setdefault(pdef.name, pdef.default)
        if pdef.per_channel:
            start[pdef.name] = np.broadcast_to(start[pdef.name], (3,)).astype(float)
    for item in args.set:
        name, value = item.split("=")
        start[name] = np.broadcast_to(float(value), np.shape(start[name])).astype(float)
    loss = "log"
    if args.lum is not None:
        meas, loss = luminance_sigma(meas, args.lum), "chi2"
    if args.chan is not None:
        ci = np.clip(meas.wi[:, 2:3], 1e-3, 1.0)
        a = args.chan * channel_scale(meas, 1.0)
        meas, loss = dataclasses.replace(meas, brdf_std=np.broadcast_to(a / ci, meas.brdf.shape).copy()), "chi2"
    pairs = {lt: preview_pairs(args.file, lt, 64, 64, 0, variant) for lt in LIGHTINGS}
    file_pix = {lt: pixel_values(rgl.eval(sp.wi, sp.wo) * sp.wi[:, 2:3], sp) for lt, sp in pairs.items()}
    t0 = time.perf_counter()
    if args.staged is not None:
        wh, _ = half_vector(meas.wi, meas.wo)
        small = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", meas.wi, wh), -1.0, 1.0))) < args.staged
        held = {q.name: start[q.name] for q in model.parameters if q.name.startswith("sheen_")}
        r0 = fit(meas.subset(np.flatnonzero(small)), model, loss=loss, rng=np.random.default_rng(0), fixed=held,
                 start={k: v for k, v in start.items() if k not in held}, n_starts=0, n_local=1, use_fast=False,
                 covariance=False, enforce_energy=False)
        start = {**start, **r0.params}
        for q in model.parameters:
            if q.name.startswith("sheen_") and q.name != "sheen_alpha":
                start[q.name] = np.full(3, 0.05)
    r = fit(meas, model, loss=loss, rng=np.random.default_rng(0), start=start, n_starts=0, n_local=1,
            use_fast=False, covariance=False, enforce_energy=False, maxeval=args.maxeval)
    for name, p in (("start", start), ("data fit", r.params)):
        s = score(model, p, pairs, file_pix)
        print(f"{name:9s} " + "  ".join(f"{lt} dE {v[0]:.3f} rgb/file {' '.join(f'{x:.3f}' for x in v[1])}"
                                       for lt, v in s.items()) + f"  mean {np.mean([v[0] for v in s.values()]):.3f}")
    print(f"extra {sorted(args.extra)} data {args.data} loss {loss}: {time.perf_counter() - t0:.0f} s, "
          f"objective {r.objective:.6g}, "
          f"{r.n_evals} evaluations, converged {r.converged} ({r.message})")
    print({k: np.round(v, 4).tolist() for k, v in r.params.items() if k.startswith(("width", "sheen"))})
    if args.save:
        with open(args.save, "wb") as fh:
            pickle.dump((options, dict(r.params), sorted(args.extra)), fh)


if __name__ == "__main__":
    main()
