"""The budget's chi-square test on transmission captures of the frosted glass, over seeds.

    .venv/bin/python tests/bench/transmission_adequacy.py [--seeds 0-11] [--fit ggx] [--errors JSON] [--worst 3]

For each seed: a roughdielectric GGX alpha 0.3, eta 1.5 plate through the ``transmission`` plan
on the simulator under ``--errors typical`` (``--errors`` merges a JSON table into it), the
settings of tests/bench/test_transmission_capture.py (1 us shutter, 16 flat frames, no
open-beam certificate), exported and fitted with ``--fit`` as distribution (``beckmann``: the
test's power on a wrong family). Prints per seed T, dof, p, alpha and the points the test left
out (their angle law reaches a cutoff of f_r); with ``--worst`` the points of largest
|data - model| / brdf_std with the model at the point and averaged over 0.5 deg apertures (the
typical simulator's, which the session declares). At the end the
false alarms at 1e-3 and 0.05. Figures in docs/performance.md ("The transmission adequacy test
at a lobe's edge").
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from _seeds import seed_list



def run(seed: int, fit: str, errors: dict, worst: int) -> dict:
    from gonio.bench.dataset.export import export
    from gonio.bench.dataset.reader import open_fit_input
    from gonio.bench.plan.plans import load_plan
    from gonio.bench.session.simulated import capture_sim
    from gonio.bench.settings import default_settings
    from gonio.cli.fit import fit_dataset
    from gonio.core.geometry import angles
    from gonio.fitting.likelihood.aperture import aperture_mean

    import gonio.fitting.uncertainty.budget as _budget

    seen = []
    test = getattr(_budget.adequacy_test, "__wrapped__", _budget.adequacy_test)

    def recorded(*args, **kw):                      # the test's own dict (its left_out points)
        seen.append(test(*args, **kw))
        return seen[-1]
    recorded.__wrapped__ = test
    _budget.adequacy_test = recorded
    sample = {"model": "roughdielectric", "options": {"distribution": "ggx"}, "params": {"alpha": 0.3, "int_ior": 1.5}}
    d = default_settings()
    with tempfile.TemporaryDirectory() as tmp:
        capture_sim(Path(tmp) / "s", sample=sample, plan=load_plan("transmission"), seed=seed, progress=False,
                    settings={**d, "transmission": {"rel_std": 0.0}, "errors": {"preset": "typical", **errors},
                              "capture": {**d["capture"], "exposure_min_s": 1e-6, "flat_frames": 16}})
        given = open_fit_input(export(Path(tmp) / "s"), seed=seed)
        res, doc, _ = fit_dataset(given, model="roughdielectric", options={"distribution": fit}, seed=seed)
    a = doc["goodness"]["adequacy"]
    out = {"seed": seed, "T": a["statistic"], "dof": a["dof"], "p": a["p_value"],
           "alpha": doc["parameters"]["alpha"]["value"], "worst": [], "left_out": []}
    if seen:
        ti, pi = angles(given.meas.wi)
        to, po = angles(given.meas.wo)
        out["left_out"] = [f"{np.degrees(ti[n]):.0f}/{np.degrees(pi[n]):.0f}/{np.degrees(to[n]):.0f}/"
                           f"{np.degrees(po[n]):.0f}" for n in seen[-1].get("left_out", [])]
    if worst:
        meas = given.meas
        f = np.asarray(res.model.eval(meas.wi, meas.wo, res.params), float)
        z = np.where(meas.use, (meas.brdf - f) / np.where(meas.use, meas.brdf_std, 1.0), 0.0)
        ti, pi = angles(meas.wi)
        to, po = angles(meas.wo)
        for n in np.argsort(-np.abs(z).max(axis=1))[:worst]:
            avg = aperture_mean(res.model, meas.wi[n:n + 1], meas.wo[n:n + 1], res.params, 0.5, 0.5)[0]
            out["worst"].append(f"theta_i {np.degrees(ti[n]):.0f} phi_i {np.degrees(pi[n]):.0f} theta_o "
                                f"{np.degrees(to[n]):.0f} phi_o {np.degrees(po[n]):.0f}: data {meas.brdf[n, 0]:.4g} "
                                f"sd {meas.brdf_std[n, 0]:.2g} model {f[n, 0]:.4g} aperture mean {avg[0]:.4g} "
                                f"z {z[n, 0]:.0f}")
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-11")
    ap.add_argument("--fit", default="ggx")
    ap.add_argument("--errors", default="{}")
    ap.add_argument("--worst", type=int, default=0)
    args = ap.parse_args(argv)
    rows = []
    for seed in seed_list(args.seeds):
        r = run(seed, args.fit, json.loads(args.errors), args.worst)
        rows.append(r)
        print(f"seed {seed:3d}  T {r['T']:10.1f}  dof {r['dof']}  p {r['p']:.2e}  alpha {r['alpha']:.4f}  "
              f"left out (ti/pi/to/po) {' '.join(r['left_out']) or '-'}", flush=True)
        for line in r["worst"]:
            print("    " + line)
    p = np.array([r["p"] for r in rows])
    print(f"p < 1e-3: {int((p < 1e-3).sum())}/{len(p)}, p < 0.05: {int((p < 0.05).sum())}/{len(p)}")


if __name__ == "__main__":
    main()
