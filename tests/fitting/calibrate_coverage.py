"""Measure the true coverage of gonio's uncertainty intervals, outside the suite (issue 12).

    .venv/bin/python tests/fitting/calibrate_coverage.py CASE N [--first SEED] [--out FILE.json]
    .venv/bin/python tests/fitting/calibrate_coverage.py --summarise tests/fitting/data/coverage/*.json

CASE: laplace-roughplastic, laplace-orennayar, emcee-roughplastic, emcee-orennayar (the
configurations of tests/fitting/test_coverage.py, same simulator and settings). Runs N
seeded captures (seeds disjoint from the suite's), prints each parameter's coverage with
its binomial sigma, and writes the per-capture hits to FILE.json (saved every 25
captures). The suite's acceptance regions and their power are computed from the files in
tests/fitting/data/coverage/, which this script wrote; ``--summarise`` prints their table
(the one in test_coverage.py's docstring) with the false-alarm bound and the power at the
in-suite sizes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import test_coverage as T  # noqa: E402


def _save(out, case, first, names, hits):
    """The format test_coverage.load_calibration reads (tests/fitting/data/coverage/)."""
    if out:
        h = np.asarray(hits, dtype=int)  # (captures, 2, parameters)
        doc = {"case": case, "first_seed": first, "captures": len(h), "names": list(names),
               "made_by": "tests/fitting/calibrate_coverage.py",
               "nominal": ["".join(map(str, h[:, 0, j])) for j in range(h.shape[2])],
               "narrow": ["".join(map(str, h[:, 1, j])) for j in range(h.shape[2])]}
        Path(out).write_text(json.dumps(doc, indent=1) + "\n")


def run(case: str, n: int, first: int, out=None):
    kind, model_name = case.split("-", 1)
    model, truth, settings = T.CASES[model_name]
    hits = []
    t0 = time.perf_counter()
    for s in range(first, first + n):
        if kind == "laplace":
            names, h = T.laplace_hits(model, truth, s, **settings["laplace"])
        else:
            names, h, _, _ = T.emcee_hits(model, truth, s, **settings["emcee"])
        hits.append(h.tolist())
        if (s - first + 1) % 25 == 0:  # saved as it goes: a long run can be stopped
            _save(out, case, first, names, hits)
            cov = np.mean(hits, axis=0)[0]
            print(f"{s - first + 1} captures, {time.perf_counter() - t0:.0f} s:", dict(zip(names, np.round(cov, 3))),
                  flush=True)
    return names, np.array(hits, dtype=bool)


def summarise(files, n_boot=20000, seed=0):
    """From saved runs: the CALIBRATED table (coverage, binomial sigma, coverage 20 %
    narrower) and, for the in-suite sizes, the Bonferroni false-alarm bound and the
    probability that a 20 % too narrow posterior passes, both from the binomial and by
    resampling the measured captures (which keeps the dependence between parameters)."""
    for f in files:
        d, hits = T.read_calibration(f)
        kind, case = d["case"].split("-", 1)
        m = len(hits)
        cov, narrow = hits.mean(axis=0)
        print(f'    ("{kind}", "{case}"): {{  # {m} captures, seeds from {d["first_seed"]}')
        for name, c, c8 in zip(d["names"], cov, narrow):
            print(f'        "{name}": ({c:.4f}, {np.sqrt(c * (1 - c) / m):.4f}, {c8:.4f}),')
        print("    },")
        n = (T.N_LAPLACE if kind == "laplace" else T.N_EMCEE)[case]
        b = np.array([T.region(kind, case, nm, n) for nm in d["names"]])
        fa = T.false_alarm(n, cov, b[:, 0], b[:, 1]) + T.ALPHA_POOLED
        passes, narrow_passes = T.resampled_pass_rates(kind, case, n, draws=n_boot, seed=seed)
        print(f"    #   in-suite n = {n}: regions {[tuple(map(int, r)) for r in b]}, pooled misses in "
              f"{T.pooled_region(kind, case, n)}; false-alarm bound {fa:.1e} (resampled {1 - passes:.1e}); "
              f"a posterior 20 % too narrow passes {narrow_passes:.1e} (resampled, {n_boot} draws)")


def main():
    if sys.argv[1:2] == ["--summarise"]:
        return summarise(sys.argv[2:])
    ap = argparse.ArgumentParser()
    ap.add_argument("case")
    ap.add_argument("n", type=int)
    ap.add_argument("--first", type=int, default=100_000)
    ap.add_argument("--out")
    a = ap.parse_args()
    names, hits = run(a.case, a.n, a.first, a.out)
    _save(a.out, a.case, a.first, names, hits)
    cov, narrow = hits.mean(axis=0)
    p = T.LAPLACE_P0 if a.case.startswith("laplace") else T.EMCEE_P0
    for name, c, c8 in zip(names, cov, narrow):
        sd = np.sqrt(c * (1 - c) / len(hits))
        print(f"{a.case} {name:26s} coverage {c:.3f} +- {sd:.3f} (nominal {p:.3f}; 20 % narrower: {c8:.3f})")



if __name__ == "__main__":
    main()
