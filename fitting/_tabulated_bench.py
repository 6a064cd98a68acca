"""The ``tabulated`` model on real materials next to the plain peer, with the helpers of
:mod:`gonio.fitting._realbench` (one dense grid, Ngan and log metrics, rendered CIEDE2000).

Per RGL file: gonio's fit (:func:`gonio.fitting._tabulated_start.fit_tabulated`: the
data-driven start, then :func:`gonio.fitting.fit` with the ``log`` loss on the file's own
weighted samples) and the peer (:func:`gonio.fitting._realbench.peer_fit`: scipy
``least_squares`` on the unweighted log residuals, 8 starts, the same model instance, so
the same data-driven start as its first). ``python -m gonio.fitting._tabulated_bench
FILE...`` prints one line per fit.

Measured 2026-12-02 on the shared 2-core machine (two benchmarks running at once, so the
times are inflated by about 2x; both sides of a row ran in the same process):

=====================  =====  ======  =====  ======  ======  ======  =====
material               Ngan   log     dE00   time s  peer    peer    peer
                                      (floor)         Ngan    log     time s
=====================  =====  ======  =====  ======  ======  ======  =====
vch_golden_yellow      0.152  0.0224  2.52   58      0.153   0.0232  209
                                      (0.58)                          (dE 3.55)
colodur_napoli_4f      0.068  0.0023  0.69   81      0.068   0.0024  137
                                      (0.24)                          (dE 0.74)
paper_white            0.105  0.0162  2.91   164     0.043   0.0068  367
                                      (0.42)                          (dE 0.88)
=====================  =====  ======  =====  ======  ======  ======  =====

paper_white: gonio's unconstrained optimum broke albedo <= 1 (the model does not conserve
energy by construction, so gonio's fit enforces it) and the SLSQP polish stopped at its
time cap (``maxtime reached``) far from the optimum; the peer has no energy constraint. A
near-white Lambertian body is not this model's case (the BIC choice, cooktorrance, had
Ngan 0.06, log 0.010, dE 0.90 in issue 16's table).
"""

from __future__ import annotations

import sys

import numpy as np

from ._realbench import dense_grid, measured_on_grid, metrics, peer_fit, rendered_delta_e
from ._realdata import rgl_samples
from ._tabulated_start import fit_tabulated

__all__ = ["compare_tabulated"]


def compare_tabulated(path, *, seed=0, render=True, peer=True) -> dict:
    """One material: gonio's and the peer's metrics, times and rendered dE (module notes)."""
    meas = rgl_samples(path)
    wi, wo = dense_grid()
    f_meas = measured_on_grid(path, wi, wo)
    res = fit_tabulated(meas, rng=np.random.default_rng(seed))
    model = res.model
    row = {"material": str(path).rsplit("/", 1)[-1].removesuffix(".bsdf"), "gonio_time_s": res.time_s,
           "converged": res.converged, **{f"gonio_{k}": v for k, v in metrics(model.eval(wi, wo, res.params), f_meas, wi).items()}}
    if render:
        row["gonio_de00"], row["de00_noise"] = rendered_delta_e(model, res.params, path, seed)
    if peer:
        space, x, t_peer = peer_fit(meas, model, np.random.default_rng([seed, 1]))
        params = space.to_params(x)
        row.update({f"peer_{k}": v for k, v in metrics(model.eval(wi, wo, params), f_meas, wi).items()})
        row["peer_time_s"] = t_peer
        if render:
            row["peer_de00"] = rendered_delta_e(model, params, path, seed)[0]
    return row


if __name__ == "__main__":  # pragma: no cover - a measurement, run by hand
    for f in sys.argv[1:]:
        print(compare_tabulated(f), flush=True)
