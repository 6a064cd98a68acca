"""Regress a coverage run's errors on the simulator's drawn truths (issue 15, 2026-12-02).

    .venv/bin/python tests/fitting/decompose/wedge_regression.py FILE.json [FILE.json ...]

For each session the seed's hidden truth (gonio/sim/physics/errors.ErrorModel.draw: the certificate factor
n_rho, the sample's wedge w0, w1 in units of its 0.05 deg) is redrawn, and each parameter's
error (fit - truth) / mean u_c, and its z, are fitted by least squares on
[1, n_rho, w0, w1, w0^2 - 1, w1^2 - 1, w0 w1]: the intercept is the mean error at a typical
wedge, the quadratic coefficients the wedge's second-order effect (their sum its mean). With
``z_fitted`` in the records (budget_coverage.py after d56b7a9) the same for the values before
the second-order correction.
"""
import json
import sys

import numpy as np
from gonio.sim.physics.errors import error_model

TRUTH = np.array([0.5, 0.35, 0.2, 0.05, 1.5])
LABELS = ["1", "n_rho", "w0", "w1", "w0^2-1", "w1^2-1", "w0w1"]


def main(files):
    model = error_model("typical")
    rows = []
    for f in files:
        rows += json.load(open(f))["sessions"]
    names = rows[0]["names"]
    st = [model.draw(r["seed"], 1.0) for r in rows]
    nr = np.array([t.rho_factor - 1.0 for t in st])
    w = np.array([t.wedge_deg for t in st]) / model.alignment.wedge_deg
    n = len(rows)
    X = np.column_stack([np.ones(n), nr, w, w[:, 0] ** 2 - 1, w[:, 1] ** 2 - 1, w[:, 0] * w[:, 1]])
    print(f"{n} sessions; drawn means (sd units, their sd {1 / np.sqrt(n):.2f}): n_rho {nr.mean():+.2f}, "
          f"w0 {w[:, 0].mean():+.2f}, w1 {w[:, 1].mean():+.2f}")
    keys = [("z_c", "z (reported value)")] + ([("z_fitted", "z (fitted, uncorrected)")] if "z_fitted" in rows[0] else [])
    for j, name in enumerate(names):
        for key, label in keys:
            y = np.array([r[key][j] for r in rows])
            c, *_ = np.linalg.lstsq(X, y, rcond=None)
            res = y - X @ c
            sd = np.sqrt(np.diag(np.sum(res ** 2) / (n - X.shape[1]) * np.linalg.inv(X.T @ X)))
            print(f"  {name:24s} {label:24s} mean {y.mean():+.3f} ({y.std(ddof=1) / np.sqrt(n):.3f}); "
                  + " ".join(f"{k} {v:+.3f}({s:.3f})" for k, v, s in zip(LABELS, c, sd)))


if __name__ == "__main__":
    main(sys.argv[1:])
