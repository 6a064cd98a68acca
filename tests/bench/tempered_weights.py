"""Study (issue 38): the design weights flattened, w^lambda (Shimodaira 2000, sec. 4), on the
sequential plans' captures.

Per material and seed: ``gonio perf acquisition``'s dense, D-optimal and alc captures (budget
9.5 % of dense, typical errors, roughplastic GGX by chi2 with the budget), then each sequential
capture refitted with its ``design_weight`` raised to lambda and rescaled to the same sum
(lambda 0: unweighted, 1: the full covariate-shift weight). Prints one CSV row per (plan,
lambda): the weights' effective sample size over the points ((sum w)^2 / sum w^2 / N), Ngan
and log against the truth on the dense grid, and the dense grid's.
Run: ``python tests/bench/tempered_weights.py FILE.bsdf --seeds 0-1 [--lambdas 0,0.5,1]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _seeds import seed_list  # noqa: E402


def tempered(weight: np.ndarray, lam: float) -> np.ndarray:
    """``weight ** lam`` rescaled to ``weight``'s sum."""
    w = np.asarray(weight, float) ** float(lam)
    return w * (float(np.sum(weight)) / float(np.sum(w)))


def refits(path: Path, sample: dict, seed: int, lambdas) -> list[dict]:
    """The capture at ``path`` refitted at each lambda: dicts of lambda, ngan, log, points."""
    from gonio.bench.dataset.reader import open_budget, open_dataset
    from gonio.fitting.pipeline import fit_measurements
    from gonio.perf.acquisition import score

    out = []
    for lam in lambdas:
        meas = open_dataset(path, seed=seed)
        if meas.weight is None:
            raise ValueError(f"{path}: no design_weight (a fixed plan?)")
        meas.weight = tempered(meas.weight, lam)
        res = fit_measurements(meas, model="roughplastic", options={"distribution": "ggx"}, seed=seed,
                               budget=open_budget(path, meas), dataset_path=path)[0]
        m = score(res, sample, render=False)
        w = meas.weight
        out.append({"lambda": lam, "ngan": m["ngan"], "log": m["log"], "points": meas.n_points,
                    "ess": float(w.sum() ** 2 / np.sum(w * w)) / meas.n_points})
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("--seeds", type=seed_list, default=[0])
    ap.add_argument("--lambdas", default="0,0.25,0.5,0.75,1")
    ap.add_argument("--budget-fraction", type=float, default=0.095)
    args = ap.parse_args(argv)
    from gonio.bench.samples import load_sample
    from gonio.perf.acquisition import run

    lambdas = [float(v) for v in args.lambdas.split(",")]
    sample = load_sample(args.file)
    print("material,seed,plan,lambda,points,ess_fraction,time_pct,ngan,log,dense_ngan,dense_log", flush=True)
    for seed in args.seeds:
        with tempfile.TemporaryDirectory() as tmp:
            rows = run(["dense", "adaptive", "alc"], sample, model="roughplastic", options={"distribution": "ggx"},
                       seed=seed, folder=Path(tmp), budget_fraction=args.budget_fraction)
            dense = next(r for r in rows if r["plan"] == "dense")
            for r in rows:
                if r["plan"] == "dense":
                    continue
                path = Path(tmp) / r["plan"] / "dataset.nc"
                pct = 100.0 * r["time_s"] / dense["time_s"]
                for f in refits(path, sample, seed, lambdas):
                    print(f"{Path(args.file).stem},{seed},{r['plan']},{f['lambda']:g},{f['points']},{f['ess']:.3f},{pct:.2f},"
                          f"{f['ngan']:.5f},{f['log']:.6f},{dense['ngan']:.5f},{dense['log']:.6f}", flush=True)


if __name__ == "__main__":
    main()
