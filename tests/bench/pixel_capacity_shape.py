"""Study (issue 35): does a lobe whose shape changes with theta_d lift tabulated's pixel capacity?

:mod:`pixel_capacity` with freedoms ``tabulated`` lacks, added here (study code, not the product):
``sheen``, a second microfacet lobe A_c(theta_d) D_GGX(theta_h; alpha_s) G_GGX / (4 cos_i cos_o),
A_c piecewise linear on the Fresnel knots per channel (reciprocal: theta_h, theta_d are; albedo
at most max A_c); ``wchan``, the width factors w_c(theta_d) per channel; ``wknot``, an extra
width knot at theta_d = 25 deg. Fitted to the preview pixels (seed 0, k light samples), scored on
seed 1 (64 samples) as :mod:`pixel_capacity`. Run:
``python tests/bench/pixel_capacity_shape.py FILE.bsdf FIT.pkl [--extra sheen wchan wknot]``.
"""

from __future__ import annotations

import argparse
import math
import pickle
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from pixel_capacity import load_fit, pixel_fit, pixel_sets  # noqa: E402

import gonio.models.catalogue.tabulated as tab  # noqa: E402
from gonio.core.geometry import half_vector  # noqa: E402
from gonio.fitting.formats import RGLBRDF  # noqa: E402
from gonio.fitting.optimise.space import ParameterSpace  # noqa: E402
from gonio.fitting.selection.scene_fit import pixel_values  # noqa: E402
from gonio.models.base import Parameter  # noqa: E402
from gonio.models.mitsuba import select_variant  # noqa: E402

X25 = 1.0 - math.cos(math.radians(25.0))


def _ggx(cos_h, alpha):
    c2 = cos_h * cos_h
    return 1.0 / (math.pi * alpha**2 * (c2 + (1.0 - c2) / alpha**2) ** 2)


def _g1_ggx(cos_t, alpha):
    c2 = np.clip(cos_t * cos_t, 1e-12, 1.0)
    return 2.0 / (1.0 + np.sqrt(1.0 + alpha**2 * (1.0 - c2) / c2))


class Shape(tab.Tabulated):
    """tabulated plus the study's freedoms (``extra``: a set of names)."""

    extra = frozenset()

    def _parameters(self):
        out = []
        for p in super()._parameters():
            if p.name.startswith("width_") and "wchan" in self.extra:
                p = Parameter(p.name, np.broadcast_to(self._default(p.name, 1.0), (3,)).copy(), p.lower, p.upper,
                              p.unit, p.description, per_channel=True)
            out.append(p)
        if "wknot" in self.extra:
            out.append(Parameter("width_25", self._default("width_25", 1.0), *tab.WIDTH, "1", "w at 25 deg",
                                 per_channel="wchan" in self.extra))
        if "sheen" in self.extra:
            out.append(Parameter("sheen_alpha", self._default("sheen_alpha", 0.5), 0.05, 2.0, "1", "sheen GGX alpha"))
            for j in range(tab.N_FRESNEL):
                out.append(Parameter(f"sheen_{j}", self._default(f"sheen_{j}", 1e-4), 0.0, 1.0, "1", "sheen A",
                                     per_channel=True))
        return tuple(out)

    def _eval_parts(self, wi, wo, p):
        q = dict(p)
        for j in range(1, tab.N_FRESNEL):
            q[f"width_{j}"] = 1.0
        diffuse, _ = super()._eval_parts(wi, wo, q)
        t = tab.tables(q)
        xk = [j / (tab.N_FRESNEL - 1) for j in range(tab.N_FRESNEL)]
        wk = [np.ones(3)] + [np.broadcast_to(p[f"width_{j}"], (3,)) for j in range(1, tab.N_FRESNEL)]
        if "wknot" in self.extra:
            xk.insert(1, X25)
            wk.insert(1, np.broadcast_to(p["width_25"], (3,)))
        wk = np.array(wk)  # (nW, 3)
        ci, co = wi[:, 2], wo[:, 2]
        wh, valid = half_vector(wi, wo)
        cd = 0.5 * (np.einsum("ij,ij->i", wi, wh) + np.einsum("ij,ij->i", wo, wh))
        ok = valid & (ci > 0.0) & (co > 0.0) & (wh[:, 2] > 0.0) & (cd > 0.0)
        x = np.clip(1.0 - cd, 0.0, 1.0)
        s_f = (tab.N_FRESNEL - 1) * x
        th = tab._polar(wh)
        G = tab._interp(t.g1, tab.g_index(tab._polar(wi))) * tab._interp(t.g1, tab.g_index(tab._polar(wo)))
        F = tab._interp(t.fresnel, s_f)
        den = np.where(ok, 4.0 * ci * co, 1.0)
        lobe = np.zeros((wi.shape[0], 3))
        for c in range(3):
            w = np.interp(x, xk, wk[:, c])
            lnd = tab._interp(t.ln_d[c:c + 1], tab.knot_index(th / w))[:, 0]
            lobe[:, c] = F[:, c] * np.exp(lnd - t.ln_z[c]) / (w * w) * G[:, c] / den
        if "sheen" in self.extra:
            a = float(p["sheen_alpha"])
            A = tab._interp(np.stack([p[f"sheen_{j}"] for j in range(tab.N_FRESNEL)], axis=1), s_f)
            g2 = _g1_ggx(ci, a) * _g1_ggx(co, a)
            lobe += A * (_ggx(np.clip(wh[:, 2], 0.0, 1.0), a) * g2 / den)[:, None]
        return diffuse, np.where(ok[:, None], lobe, 0.0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("fit")
    ap.add_argument("--extra", nargs="*", default=[], choices=("sheen", "wchan", "wknot"))
    ap.add_argument("-k", type=int, default=16)
    ap.add_argument("--nfev", type=int, default=20)
    ap.add_argument("--save")
    args = ap.parse_args(argv)
    variant = select_variant(None)
    rgl = RGLBRDF(args.file, variant)
    options, params = load_fit(args.fit)
    Shape.extra = frozenset(args.extra)
    model = Shape(**options)
    start = {k: v for k, v in params.items()}
    for pdef in model.parameters:
        start.setdefault(pdef.name, pdef.default)
        if pdef.per_channel:
            start[pdef.name] = np.broadcast_to(start[pdef.name], (3,)).astype(float)
    train, test, tgt, test_pix, scale = pixel_sets(args.file, rgl, args.k, variant)
    space = ParameterSpace(model, n_channels=3)

    def residual(u):
        p = space.to_params(space.from_unit(u))
        return np.concatenate([((pixel_values(model.eval(sp.wi, sp.wo, p) * sp.wi[:, 2:3], sp) - tgt[lt])
                                / scale[lt]).ravel() for lt, sp in train.items()])

    print(f"extra {sorted(args.extra)}, {len(space.entries)} numbers")
    fitted = pixel_fit(model, space, residual, start, test, test_pix, args.nfev)
    print({k: np.round(v, 4).tolist() for k, v in fitted.items() if k.startswith(("width", "sheen"))})
    if args.save:
        with open(args.save, "wb") as fh:
            pickle.dump((options, fitted, sorted(args.extra)), fh)


if __name__ == "__main__":
    main()
