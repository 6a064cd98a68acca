"""Design weights: how much of the evaluation measure each point of a design stands for.

A sequential design puts its points where the fit learns the most, so a misspecified model
fitted to them targets a different compromise than one fitted over the hemispheres. Weighting
each point's log-likelihood by the target density over the design's density makes the
weighted fit estimate the target's minimiser (covariate-shift weighting, Shimodaira 2000,
J. Stat. Plan. Inference 90: 227-244). For a finite design the ratio is estimated by Voronoi
cells: a point's weight is the measure of the (wi, wo) pairs of a fine equal-solid-angle
reference set (theta <= 80 deg in both, what the Ngan and log errors integrate,
gonio.perf.real.metrics) whose nearest design point it is, in the isotropic feature space
of the adaptive plan with reciprocity (a pair and its swap are the same BRDF value). The
weights are in sr^2 and sum to the reference measure (2 pi (1 - cos 80 deg))^2. Public:
`design_weights`, `dataset_variable` (dataset.nc's `VARIABLE`, where `wanted`), `reference_pairs`.
"""

from __future__ import annotations

import numpy as np
import scipy.spatial

__all__ = ["design_weights", "dataset_variable", "reference_pairs", "wanted", "REFERENCE_SR2", "THETA_MAX_DEG",
           "VARIABLE", "ON_BY_DEFAULT"]

#: the evaluation measure's largest elevation, deg (gonio.perf.real.metrics' grid)
THETA_MAX_DEG = 80.0
#: the measure of the (wi, wo) pairs with both elevations <= THETA_MAX_DEG, sr^2
REFERENCE_SR2 = float((2.0 * np.pi * (1.0 - np.cos(np.radians(THETA_MAX_DEG)))) ** 2)
#: the reference set's cells: theta_i, theta_o (uniform in cos theta), phi_d (uniform in [0, pi])
GRID = (24, 24, 24)


def reference_pairs(n_theta_i: int = GRID[0], n_theta_o: int = GRID[1], n_phi: int = GRID[2]):
    """(wi, wo) at the centres of equal-measure cells of the isotropic domain (phi_i = 0,
    phi_o in [0, pi]: f(phi_d) = f(-phi_d)); every pair stands for REFERENCE_SR2 / count."""
    from gonio.core.geometry import directions

    cmax = np.cos(np.radians(THETA_MAX_DEG))
    ci = 1.0 - (1.0 - cmax) * (np.arange(n_theta_i) + 0.5) / n_theta_i
    co = 1.0 - (1.0 - cmax) * (np.arange(n_theta_o) + 0.5) / n_theta_o
    po = np.pi * (np.arange(n_phi) + 0.5) / n_phi
    ti, to, phi = np.meshgrid(np.arccos(ci), np.arccos(co), po, indexing="ij")
    return directions(ti.ravel(), np.zeros(ti.size)), directions(to.ravel(), phi.ravel())


def _canonical(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """(N, 6) features of the adaptive plan (gonio.bench.plan.alc) of each pair ordered so that
    the incident direction is the higher one: a pair and its swap (wo, wi) map to one point."""
    from gonio.bench.plan.alc import _features

    swap = (wo[:, 2] > wi[:, 2])[:, None]
    return _features(np.where(swap, wo, wi), np.where(swap, wi, wo))


def design_weights(wi: np.ndarray, wo: np.ndarray, grid: tuple[int, int, int] = GRID, reference=None) -> np.ndarray:
    """Each design point's share of the reference measure, sr^2 (module notes), shape (N,).
    ``reference``: (wi, wo) pairs of equal measure to use instead of :func:`reference_pairs`.

    Every reference pair goes to its nearest design point (both taken with the higher
    direction as the incident one); points that are the same BRDF value (a turn about the
    normal, a mirrored or a swapped pair) share their cell equally. A point no pair reaches
    keeps half a pair's measure, so every weight is > 0 (the likelihood needs it), and the
    weights are scaled to sum to REFERENCE_SR2. Deterministic: no random draw. ValueError for
    no points or a direction that is not finite."""
    wi, wo = np.atleast_2d(np.asarray(wi, float)), np.atleast_2d(np.asarray(wo, float))
    if len(wi) == 0 or wi.shape != wo.shape or wi.shape[1] != 3:
        raise ValueError("design weights need (N, 3) incident and outgoing directions, N >= 1")
    if not (np.all(np.isfinite(wi)) and np.all(np.isfinite(wo))):
        raise ValueError("design weights: a direction is not finite")
    x = _canonical(wi, wo)
    unique, group = np.unique(np.round(x, 9), axis=0, return_inverse=True)
    group = group.reshape(-1)
    ri, ro = reference_pairs(*grid) if reference is None else reference
    _, nearest = scipy.spatial.cKDTree(unique).query(_canonical(ri, ro))
    cell = np.maximum(np.bincount(nearest, minlength=len(unique)).astype(float), 0.5)
    share = cell[group] / np.bincount(group)[group]
    return share * (REFERENCE_SR2 / share.sum())


#: dataset.nc's name of the per-point design weight (sequential plans)
VARIABLE = "design_weight"
#: a sequential plan's ``[strategy] design_weights`` when its table does not say
ON_BY_DEFAULT = True


def wanted(strategy: dict | None) -> bool:
    """Whether a session's ``[strategy]`` table (None or ``fixed``: a fixed plan) asks for design
    weights: a sequential plan unless it says ``design_weights = false``."""
    strategy = strategy or {}
    return strategy.get("name", "fixed") != "fixed" and strategy.get("design_weights", ON_BY_DEFAULT) is not False


def dataset_variable(theta_i, phi_i, theta_o, phi_o) -> tuple:
    """dataset.nc's ``design_weight`` variable of a design given by its angles (deg): (dims,
    values in sr^2, attributes), as `gonio.bench.dataset.export` writes it for a sequential plan."""
    from gonio.core.geometry import directions_deg

    w = design_weights(directions_deg(np.asarray(theta_i, float), np.asarray(phi_i, float)),
                       directions_deg(np.asarray(theta_o, float), np.asarray(phi_o, float)))
    return ("point", w, {
        "units": "sr^2", "long_name": "design weight: the measure of the (wi, wo) pairs with theta_i, theta_o <= "
        f"{THETA_MAX_DEG:g} deg nearest this point (Voronoi cell of an equal-solid-angle reference set; isotropic, "
        "reciprocal); the fit weights each point's log-likelihood by it (covariate-shift weighting, Shimodaira 2000)",
        "reference_sr2": REFERENCE_SR2})
