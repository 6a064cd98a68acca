"""Study (issue 35): render :mod:`pixel_capacity_shape`'s fits, which no plugin renders, through a table.

Each pickled fit (options, params[, extra]) is evaluated on :mod:`reciprocal_bound`'s grid (1 deg
theta_i, theta_o by 2 deg phi) and rendered by its trilinear table BSDF in the preview scenes
beside the file (``measured``), as ``reciprocal_bound.py`` renders the file's own table: mean
CIEDE2000 per lighting at each spp, with each channel's rendered total over the file's. The
table's interpolation is part of the figure: the file's own table is the path's floor.
Run: ``python tests/bench/render_shape_table.py FILE.bsdf FIT.pkl... [--spp 256 4096]``.
"""

from __future__ import annotations

import argparse
import math
import pickle
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from pixel_capacity_shape import Shape  # noqa: E402
from reciprocal_bound import N_PHI, N_THETA, compare, table_dict, theta_nodes  # noqa: E402

from gonio.core.geometry import directions  # noqa: E402
from gonio.fitting.render.preview import LIGHTINGS, _render_seeds  # noqa: E402
from gonio.models.mitsuba import select_variant  # noqa: E402


def model_table(model, params):
    """f (3, n_theta_i, n_theta_o, n_phi) of the model at reciprocal_bound's grid nodes."""
    t = theta_nodes()
    TI, TO, P = np.meshgrid(t, t, np.linspace(0.0, math.pi, N_PHI), indexing="ij")
    f = model.eval(directions(TI.ravel(), P.ravel()), directions(TO.ravel(), np.zeros(TO.size)), params)
    return np.ascontiguousarray(f.T.reshape(3, N_THETA, N_THETA, N_PHI))


def load(path):
    with open(path, "rb") as fh:
        d = pickle.load(fh)
    if isinstance(d, dict):
        return d.get("options", {}), d["params"], []
    return d[0], d[1], (list(d[2]) if len(d) > 2 else [])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("fits", nargs="+")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=int, nargs="+", default=[256])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    variant = select_variant(None)
    meas_dict = {"type": "measured", "filename": str(args.file)}
    meas = {(lt, spp): _render_seeds(meas_dict, lt, args.size, spp, [args.seed, args.seed + 1], variant)
            for lt in LIGHTINGS for spp in args.spp}
    for path in args.fits:
        options, params, extra = load(path)
        Shape.extra = frozenset(extra)
        bsdf = table_dict(path, model_table(Shape(**options), params), variant)
        for spp in args.spp:
            r = compare(bsdf, meas, args.size, spp, args.seed, variant)
            print(f"{Path(path).name:28s} spp {spp:5d}  env {r['env'][0]:.3f} (floor {r['env'][1]:.3f})  "
                  f"area {r['area'][0]:.3f} (floor {r['area'][1]:.3f})  mean {0.5 * (r['env'][0] + r['area'][0]):.3f}  "
                  f"rgb / file: env {' '.join(f'{v:.3f}' for v in r['env'][2])}, "
                  f"area {' '.join(f'{v:.3f}' for v in r['area'][2])}", flush=True)


if __name__ == "__main__":
    main()
