"""Issue 39's proof, per ASTM file: a fit's colour against the measured spectra under D65.

Usage: ``python tests/fitting/astm_colour.py FILE.astm [FILE.astm ...] [--model auto]``, or
``--fits FIT.json ...`` (one per file, fitted already: the wall time is then not measured);
``--preview PNG``: each fit drawn on a sphere (:func:`preview`) beside the others, one panel a file.
Prints one row per file: file, model, mean and max CIEDE2000 over the bright points (the
brighter half by measured Y, gonio.fitting.colour.fit_colour_error), the fit's -2 ln L (its
loss's profiled likelihood, the BIC's first term), its wall time and this process's CPU time
(on a shared machine the wall time depends on the others' load).
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
    ap.add_argument("--preview", default=None)
    args = ap.parse_args(argv)
    panels = []
    print(f"{'file':<18} {'model':<40} {'mean dE00':>9} {'max dE00':>9} {'bright':>6} {'-2 ln L':>10} {'wall s':>7} {'cpu s':>7}")
    for k, path in enumerate(args.files):
        meas = astm_measurements(path)
        if args.fits:
            fitted = load_fit(args.fits[k])
            model, params, wall, n2ll, cpu = fitted.model, fitted.params, float("nan"), float("nan"), float("nan")
        else:
            t, c = time.perf_counter(), time.process_time()
            result = fit_measurements(meas, model=args.model, seed=0)[0]
            wall, cpu = time.perf_counter() - t, time.process_time() - c
            model, params, n2ll = result.model, result.params, result.neg2_loglik
        err = fit_colour_error(meas, model, params, illuminant=args.illuminant)
        name = model.name + "".join(f" {v}" for v in dict(model.options).values())
        print(f"{Path(path).name:<18} {name:<40} {err['mean']:9.2f} {err['max']:9.2f} {err['n_bright']:6d} "
              f"{n2ll:10.0f} {wall:7.1f} {cpu:7.1f}", flush=True)
        if args.preview:
            panels.append((f"{Path(path).stem}: {name}", preview(model, params, meas.attrs["wavelengths_nm"])))
    if args.preview:
        _save(panels, args.preview)


def preview(model, params, wavelengths, size=200, light_deg=(35.0, 200.0), illuminant="D65"):
    """An orthographic sphere lit by one distant light (``light_deg``: its polar and azimuth
    angles from the view direction) under ``illuminant``: each pixel's spectral radiance
    f_r(wi, wo) cos(theta_i) at the fit's wavelengths, to XYZ and sRGB by colour-science (the
    light's irradiance set so that a white Lambertian facing it would be Y = 1); no shadows, no
    other light. Returns an (size, size, 3) sRGB image in [0, 1]."""
    import colour
    import numpy as np

    from gonio.fitting.colour import spectral_xyz

    y, x = np.mgrid[1:-1:complex(0, size), -1:1:complex(0, size)]
    inside = x * x + y * y < 0.995
    n = np.stack([x[inside], y[inside], np.sqrt(1.0 - x[inside] ** 2 - y[inside] ** 2)], 1)
    t = np.cross(n, [0.0, 1.0, 0.0])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t)
    th, ph = np.radians(light_deg)
    light = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    view = np.array([0.0, 0.0, 1.0])

    def local(v):
        return np.stack([t @ v, b @ v, n @ v], 1)

    wi, wo = local(light), local(view)
    ok = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    f = np.zeros((n.shape[0], len(wavelengths)))
    f[ok] = np.asarray(model.eval(wi[ok], wo[ok], params), float) * wi[ok, 2:3]
    xyz = spectral_xyz(f, wavelengths, illuminant)
    rgb = colour.XYZ_to_RGB(xyz, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_encoding=True)
    img = np.zeros((size, size, 3))
    img[inside] = np.clip(np.nan_to_num(rgb), 0.0, 1.0)
    return img


def _save(panels, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.5), squeeze=False)
    for ax, (title, img) in zip(axes[0], panels):
        ax.imshow(img)
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


if __name__ == "__main__":
    main()
