"""The budget's chi-square test on spectral captures that revisit their geometries, over seeds.

    .venv/bin/python tests/bench/spectral_adequacy.py [--step 100] [--seeds 0-11] [--errors JSON] [--settings JSON]

For each seed: the red lacquer (GGX alpha 0.12) through ``spectral:STEP`` (wavelength the
slowest axis at 100 nm: the stage revisits every geometry at each wavelength) on the simulator
under ``--errors typical`` (``--errors`` merges a JSON table into it, e.g. '{"aperture":
{"source_half_deg": 0, "detector_half_deg": 0}}'; ``--settings`` into the instrument settings),
exported and fitted as ``gonio fit`` does. Prints per seed the adequacy statistic T, its dof and
p-value and z = (alpha - 0.12) / u_c; at the end the mean T against its dof (sd sqrt(2 dof / n))
and the false alarms at 1e-3 and 0.05. A calibrated test gives p roughly uniform. Figures in
docs/performance.md ("The spectral adequacy test with per-visit angle lines").
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import xarray as xr

sys.path.insert(0, str(Path(__file__).parent))

from _seeds import seed_list  # noqa: E402



def run(step: str, seed: int, errors: dict, extra: dict) -> dict:
    import test_spectral_budget as T

    from gonio.bench.dataset.export import export
    from gonio.bench.dataset.reader import open_fit_input
    from gonio.bench.plan.plans import load_plan
    from gonio.bench.samples import load_sample
    from gonio.bench.session.simulated import capture_sim
    from gonio.bench.settings import default_settings
    from gonio.cli.fit import fit_dataset

    sample = load_sample(T.LACQUER)
    settings = {**default_settings(), "monochromator": {}, "errors": {"preset": "typical", **errors}, **extra}
    with tempfile.TemporaryDirectory() as tmp:
        capture_sim(Path(tmp) / "s", sample=sample, plan=load_plan(f"spectral:{step}"), seed=seed,
                    settings=settings, progress=False)
        path = export(Path(tmp) / "s")
        with xr.open_dataset(path) as ds:
            per_visit = "wavelength" in ds["angle_shift_shared"].dims
        _, doc, _ = fit_dataset(open_fit_input(path, seed=seed), model=sample["model"], options=sample["options"],
                                seed=seed)
    a = doc["goodness"]["adequacy"]
    alpha, u = doc["parameters"]["alpha"]["value"], doc["uncertainty"]["parameters"]["alpha"]["u_combined"]
    return {"seed": seed, "per_visit": per_visit, "T": a["statistic"], "dof": a["dof"], "p": a["p_value"],
            "z": (alpha - 0.12) / u}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step", default="100")
    ap.add_argument("--seeds", default="0-11")
    ap.add_argument("--errors", default="{}")
    ap.add_argument("--settings", default="{}")
    args = ap.parse_args(argv)
    rows = []
    for seed in seed_list(args.seeds):
        r = run(args.step, seed, json.loads(args.errors), json.loads(args.settings))
        rows.append(r)
        print(f"seed {seed:3d}  per_visit {r['per_visit']}  T {r['T']:7.1f}  dof {r['dof']}  p {r['p']:.4f}  "
              f"z {r['z']:+.2f}", flush=True)
    T, p = np.array([r["T"] for r in rows]), np.array([r["p"] for r in rows])
    dof = rows[0]["dof"]
    print(f"mean T {T.mean():.1f} (dof {dof}, sd of the mean {np.sqrt(2 * dof / len(T)):.1f}); "
          f"p < 1e-3: {int((p < 1e-3).sum())}/{len(p)}, p < 0.05: {int((p < 0.05).sum())}/{len(p)}")


if __name__ == "__main__":
    main()
