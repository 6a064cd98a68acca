"""The data of the report's interactive view: the measured points and the fitted lobe.

The report embeds this as JSON in a ``<script type="application/json">`` element (escaped by
Jinja2's ``tojson``: ``<``, ``>``, ``&`` and ``'`` become ``\\u`` escapes, so no value can close
the element), and its one inline script (allowed by hash in the page's Content-Security-Policy)
draws it on a canvas: no library, no network. Values are rounded to 4 significant digits
(the view is for looking; the numbers are in dataset.nc).
"""

from __future__ import annotations

import numpy as np

from gonio.core.geometry import angles

__all__ = ["view_data"]

MAX_POINTS = 20_000
MAX_INCIDENCES = 8
THETA = np.linspace(0.0, 85.0, 18)       # the lobe's grid (degrees): 5 deg in theta_o
PHI = np.linspace(-180.0, 180.0, 37)     # 10 deg in phi_o


def _r4(a) -> list:
    """Rounded to 4 significant digits, non-finite values as None (JSON has no NaN)."""
    a = np.asarray(a, dtype=float)
    out = np.where(np.isfinite(a), a, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mag = np.where(out != 0, 10.0 ** (3 - np.floor(np.log10(np.abs(out)))), 1.0)
    rounded = np.round(out * mag) / mag
    return [None if not ok else float(v) for v, ok in zip(rounded.ravel(), np.isfinite(a).ravel())]


def _groups(ti, pi) -> list[tuple[float, float, np.ndarray]]:
    """Incidence groups (theta_i, phi_i rounded to a degree), the most populous first."""
    key = np.round(ti) * 1000 + np.round(np.mod(pi, 360.0))
    keys, counts = np.unique(key, return_counts=True)
    order = np.argsort(-counts, kind="stable")[:MAX_INCIDENCES]
    out = []
    for k in keys[order]:
        sel = key == k
        out.append((float(np.median(ti[sel])), float(np.median(pi[sel])), sel))
    return sorted(out, key=lambda g: (g[0], g[1]))


def view_data(meas, model=None, params=None) -> dict:
    """Points and (with a fit) lobes for each incidence group, as plain JSON values."""
    theta_i, phi_i = angles(meas.wi)
    theta_o, phi_o = angles(meas.wo)
    ti, pi, to, po = (np.degrees(a) for a in (theta_i, phi_i, theta_o, phi_o))
    n = min(meas.n_points, MAX_POINTS)
    groups = _groups(ti[:n], pi[:n])
    incidences = []
    for g_ti, g_pi, sel in groups:
        entry = {"theta_i": round(g_ti, 2), "phi_i": round(g_pi, 2), "points": np.flatnonzero(sel).tolist(), "lobe": None}
        if model is not None:
            t, p = np.meshgrid(np.radians(THETA), np.radians(PHI), indexing="ij")
            wo = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
            a, b = np.radians(g_ti), np.radians(g_pi)
            wi = np.tile([np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)], (wo.shape[0], 1))
            f = np.asarray(model.eval(wi, wo, params), dtype=float)        # (T * P, C)
            entry["lobe"] = [_r4(f[:, c]) for c in range(f.shape[1])]
        incidences.append(entry)
    return {"channels": [str(c)[:40] for c in meas.channels],
            "theta_o_grid": THETA.tolist(), "phi_o_grid": PHI.tolist(),
            "points": {"theta_i": _r4(ti[:n]), "phi_i": _r4(pi[:n]), "theta_o": _r4(to[:n]), "phi_o": _r4(po[:n]),
                       "f": [_r4(meas.brdf[:n, c]) for c in range(meas.n_channels)],
                       "u": [_r4(meas.brdf_std[:n, c]) for c in range(meas.n_channels)]},
            "incidences": incidences, "fitted": model is not None}
