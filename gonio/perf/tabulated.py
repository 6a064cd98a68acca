"""The ``tabulated`` model on real materials next to the plain peer.

With the helpers of :mod:`gonio.perf.real` (one dense grid, Ngan and log metrics, rendered
CIEDE2000). Per RGL file: gonio's fit
(:func:`gonio.fitting.optimise.tabulated_start.fit_tabulated`: the data-driven start, then
:func:`gonio.fitting.fit` with the ``log`` loss on the file's own weighted samples) and the
peer (:func:`gonio.perf.real.peer_fit`: scipy ``least_squares`` on the unweighted log
residuals, 8 starts, the same model instance, so the same data-driven start as its first).
``python -m gonio.perf.tabulated FILE...`` prints one line per fit.
"""

from __future__ import annotations

import sys

import numpy as np

from gonio.perf.real import dense_grid, measured_on_grid, metrics, peer_fit, rendered_delta_e
from gonio.fitting.realdata import rgl_samples
from gonio.fitting.optimise.tabulated_start import fit_tabulated

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
