"""A small but complete output folder for report tests: dataset.nc, fit.json (with selection
and a posterior), speed.json, render/render.json and render/preview/preview.json with its PNG.

Built in about two seconds from a synthetic diffuse capture, so the report's security tests do
not need the simulated instrument or Mitsuba.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

TRUTH = {"model": "diffuse", "options": {}, "params": {"reflectance": [0.5, 0.3, 0.2]}}


def _dataset(path: Path, n: int = 40) -> None:
    import xarray as xr

    import gonio.models as gm
    from gonio.fitting.measurements import direction

    rng = np.random.default_rng(0)
    ti = np.tile([0.0, 20.0, 40.0, 60.0], n // 4)
    to = np.linspace(5.0, 70.0, n)
    pi = np.zeros(n)
    po = np.where(np.arange(n) % 2, 180.0, 0.0)
    po[::5] = 90.0
    model = gm.get("diffuse")
    f = model.eval(direction(np.radians(ti), np.radians(pi)), direction(np.radians(to), np.radians(po)),
                   model.validate(TRUTH["params"]))
    sd = 0.01 * f + 1e-4
    partner = -np.ones(n, int)
    partner[0], partner[1] = 1, 0
    deg = {"units": "degree"}
    ds = xr.Dataset(
        {"brdf": (("point", "channel"), f + sd * rng.standard_normal(f.shape)),
         "brdf_std": (("point", "channel"), sd),
         "saturated": ("point", np.zeros(n, bool)),
         "reciprocal_partner": ("point", partner)},
        coords={"point": np.arange(n), "channel": ["R", "G", "B"],
                **{k: ("point", v, deg) for k, v in (("theta_i", ti), ("phi_i", pi), ("theta_o", to), ("phi_o", po))}},
        attrs={"seed": 3, "plan": json.dumps({"name": "quick", "points": [[0, 0, 0, 0]] * n, "description": "test"}),
               "gonio_version": "0.test", "sample_truth": json.dumps(TRUTH), "capture_wall_s": 12.5,
               "lamp_drift": 0.001, "scale_rel_std": 0.005})
    ds.to_netcdf(path, engine="h5netcdf")


def _png(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(1, 1))
    ax.plot([0, 1], [0, 1])
    fig.savefig(path, format="png", dpi=40)
    plt.close(fig)


def copy(pristine: Path, tmp_path: Path) -> Path:
    """A fresh copy of a built folder at ``tmp_path / "out"``, its preview naming its own image
    by absolute path, as `gonio render` writes it."""
    import shutil

    folder = Path(tmp_path) / "out"
    shutil.copytree(pristine, folder, symlinks=True)
    preview = folder / "render" / "preview" / "preview.json"
    doc = json.loads(preview.read_text())
    doc["side_by_side_png"] = str(folder / "render" / "preview" / "side_by_side.png")
    preview.write_text(json.dumps(doc))
    return folder


def build(out: Path) -> Path:
    """Write the folder under ``out``; return ``out``."""
    from gonio.cli.fit import fit_dataset
    from gonio.fitting import load_dataset, write_json_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    _dataset(out / "dataset.nc")
    meas = load_dataset(out / "dataset.nc")
    result, doc, _ = fit_dataset(meas, model="auto", seed=1, dataset_path=out / "dataset.nc")
    names = list(doc["parameters"])
    rng = np.random.default_rng(1)
    x = np.array([doc["parameters"][k]["value"] for k in names])
    doc["posterior"] = {"converged": True, "walkers": 8, "names": names, "steps": 100, "tau": [5.0] * len(names),
                        "independent_samples": 160.0, "acceptance": 0.4, "time_s": 0.1, "advice": "none needed",
                        "samples": (x + 0.01 * rng.standard_normal((200, len(names)))).tolist()}
    write_json_atomic(out / "fit.json", doc)
    fitted = result.model.eval(meas.wi, meas.wo, result.params)
    write_json_atomic(out / "speed.json", {
        "points": meas.n_points, "model": doc["model"]["name"], "seed": 1,
        "rows": [{"optimiser": "nlopt", "time_s": 0.01, "evaluations": 12, "chi2": 100.0, "max_pull": 0.5,
                  "rmse_fr": 0.001}]})
    (out / "render" / "preview").mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "render" / "render.json", {
        "variant": "scalar_rgb", "points": meas.n_points, "time_s": 0.5, "brdf_render": fitted.tolist(),
        "brdf_model": fitted.tolist(),
        "scene_check": {"poses": 5, "max_rel": 1e-6, "variant": "scalar_rgb"},
        "summary": {"export_max_rel": 1e-7, "residual_rms_sigma": 1.0, "residual_max_sigma": 2.5,
                    "worst": [{"point": 3, "theta_i": 20.0, "phi_i": 0.0, "theta_o": 10.0, "phi_o": 180.0,
                               "residual_sigma": 2.5}]},
        "provenance": {"fit": str(out / "fit.json")}})
    side = out / "render" / "preview" / "side_by_side.png"
    _png(side)
    write_json_atomic(out / "render" / "preview" / "preview.json", {
        "images": {"env": {"model_png": str(side)}}, "side_by_side_png": str(side),
        "delta_e": {"env": {"mean": 1.5, "p95": 3.0, "noise_mean": 0.5, "noise_p95": 1.0}},
        "delta_e_mean": 1.5, "delta_e_p95": 3.0, "variant": "scalar_rgb", "time_s": 2.0, "size": 64, "spp": 16,
        "seed": 0})
    return out
