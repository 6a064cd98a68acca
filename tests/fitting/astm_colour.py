"""Issue 39's proof, per ASTM file: a fit's colour against the measured spectra under D65.

Usage: ``python tests/fitting/astm_colour.py FILE.astm [FILE.astm ...] [--model auto]``, or
``--fits FIT.json ...`` (one per file, fitted already: the wall time is then not measured).
Prints one row per file: file, model, mean and max CIEDE2000 over the bright points (the
brighter half by measured Y, gonio.fitting.colour.fit_colour_error), the fit's -2 ln L (its
loss's profiled likelihood, the BIC's first term) and wall time.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def main(argv=None) -> None:
    from gonio.fitting import load_fit
    from gonio.fitting.colour import fit_colour_error
    from gonio.fitting.formats.astm import astm_measurements
    from gonio.fitting.pipeline import fit_measurements

    ap = argparse.ArgumentParser()
    ap.add_argument("files", nargs="+")
    ap.add_argument("--model", default="auto")
    ap.add_argument("--fits", nargs="*", default=None)
    ap.add_argument("--illuminant", default="D65")
    args = ap.parse_args(argv)
    print(f"{'file':<18} {'model':<40} {'mean dE00':>9} {'max dE00':>9} {'bright':>6} {'-2 ln L':>10} {'wall s':>7}")
    for k, path in enumerate(args.files):
        meas = astm_measurements(path)
        if args.fits:
            fitted = load_fit(args.fits[k])
            model, params, wall, n2ll = fitted.model, fitted.params, float("nan"), float("nan")
        else:
            t = time.perf_counter()
            result = fit_measurements(meas, model=args.model, seed=0)[0]
            wall = time.perf_counter() - t
            model, params, n2ll = result.model, result.params, result.neg2_loglik
        err = fit_colour_error(meas, model, params, illuminant=args.illuminant)
        name = model.name + "".join(f" {v}" for v in dict(model.options).values())
        print(f"{Path(path).name:<18} {name:<40} {err['mean']:9.2f} {err['max']:9.2f} {err['n_bright']:6d} "
              f"{n2ll:10.0f} {wall:7.1f}", flush=True)


if __name__ == "__main__":
    main()
