"""Plan strategies driven without an instrument (the adaptive and NDF-seeded tests): a glossy
plastic's f_r at a plan's points with 1 % noise, and the session's run loop as a strategy sees it."""

import numpy as np

import gonio.models as gm
from gonio.core.geometry import directions_deg

ALPHA = 0.15
TRUTH = {"diffuse_reflectance": np.array([0.5, 0.37, 0.25]), "alpha": ALPHA, "int_ior": 1.49}


def synthetic(plan, seed=0):
    """(f_r, 1-sigma) at every point of ``plan``: GGX roughplastic ``TRUTH``, sigma 1 % + 1e-4."""
    m = gm.get("roughplastic", distribution="ggx")
    a = plan.angles
    f = m.eval(directions_deg(a[:, 0], a[:, 1]), directions_deg(a[:, 2], a[:, 3]), TRUTH)
    sd = 0.01 * f + 1e-4
    return f + sd * np.random.default_rng(seed).standard_normal(f.shape), sd


def run(strat, f, sd, results=None, todo=None, stop_after=None):
    """Drive ``strat`` as the session's run does (each point journalled before the next is
    asked for), from ``results`` and ``todo`` (a resume) or from its first pass, stopping after
    ``stop_after`` results; the results."""
    results = dict(results or {})
    todo = list(todo if todo is not None else strat.first(set()))
    n = 0
    while n < len(todo):
        if stop_after is not None and len(results) == stop_after:
            break
        todo.extend(strat.more(results, tuple(todo)))
        if todo[n] not in results:
            results[todo[n]] = (f[todo[n]], sd[todo[n]])
        n += 1
    return results
