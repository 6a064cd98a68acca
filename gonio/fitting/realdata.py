"""Real measured materials fitted on their own samples, with solid-angle weights.

:func:`rgl_samples` reproduces the layout of an RGL-EPFL ``.bsdf`` file (Dupuy & Jakob 2018:
at each measured ``theta_i``, outgoing directions warped by the material's own visible-normal
distribution) through Mitsuba's ``measured`` plugin: at every measured ``theta_i`` below
``theta_max``, ``n_side^2`` outgoing directions from the material's own importance sampling
and ``n_side^2`` cosine-distributed ones, each pair with a solid-angle weight (outgoing: the
balance heuristic, Veach 1997, sec. 9.2; incident: the band between the midpoints of
neighbouring measured elevations). A MERL ``.binary`` file is sampled at every bin that holds
data (a seeded subset of ``n`` bins when asked), weighted by each bin's solid angle in
Rusinkiewicz coordinates (:func:`merl_weights`).

Neither format carries an uncertainty: the values get a nominal sigma (``rel_std``) that only
the plain chi2 loss uses, and ``attrs["nominal_sigma"] = True`` tells the discrepancy
likelihood to fit the variance instead.
"""

# RGL layout: the file is measured at a set of incident elevations (its theta_i field) and,
# for each, on a grid of outgoing directions dense in the specular peak, sparse in the tail;
# the measured plugin interpolates that grid. The importance-sampled directions come from
# bsdf.sample on a stratified grid (peak-aware: the peak resolved by about half of them); the
# cosine-distributed ones cover the diffuse tail and grazing angles.
# Weights: outgoing, the balance-heuristic estimator weight 1 / (n (p_bsdf + p_cos) / 2) of
# the two sample sets together, so that a weighted sum over samples is an unbiased estimate of
# an integral over the outgoing hemisphere; incident, the solid angle 2 pi (cos a - cos b) of
# the band. merl_weights is the Jacobian of the half/difference parametrisation.
# References:
# Dupuy, J., Jakob, W. (2018). An adaptive parameterization for efficient material acquisition
# and rendering. ACM TOG 37(6), 274.
# Veach, E. (1997). Robust Monte Carlo methods for light transport simulation. PhD thesis,
# Stanford, ch. 9.
# Rusinkiewicz, S. (1998). A new change of variables for efficient BRDF representation. EGWR.

from __future__ import annotations

import dataclasses

import numpy as np

from gonio.core.geometry import directions
from gonio.models.mitsuba import interaction, quarter_turns, select_variant, turn

from gonio.fitting.measurements import Measurements
from gonio.fitting.formats import RGLBRDF, half_diff_angles, merl_to_measurements, rgl_field

__all__ = ["rgl_theta_i", "rgl_samples", "merl_samples", "merl_weights"]

#: default samples per incident elevation and sample set: 2 * 24^2 = 1152 outgoing directions
N_SIDE = 24


def rgl_theta_i(path) -> np.ndarray:
    """The measured incident elevations of an RGL ``.bsdf`` file (radians)."""
    values = rgl_field(path, "theta_i").ravel()
    return np.radians(values) if values.max() > 2.0 else values


def _band_weights(theta, theta_max):
    """Solid angle of the band of each elevation between the midpoints to its neighbours."""
    edges = np.concatenate([[0.0], 0.5 * (theta[1:] + theta[:-1]), [theta_max]])
    edges = np.clip(edges, 0.0, theta_max)
    return 2.0 * np.pi * (np.cos(edges[:-1]) - np.cos(edges[1:]))


def rgl_samples(path, *, n_side: int = N_SIDE, theta_max_deg: float = 80.0, rel_std: float = 0.02,
                floor: float = 1e-4, variant: str | None = None, rng=None) -> Measurements:
    """An RGL file's own measurement layout (see the module), as weighted Measurements.

    ``rng`` (a numpy Generator): the ``n_side^2`` sample points of each set are drawn
    uniformly at random instead of on the stratified grid -- a random geometry of the same
    layout and weights (the resampling test refits on such geometries)."""
    import mitsuba as mi

    variant = select_variant(variant)
    if not variant.startswith(("llvm", "cuda")):
        raise ValueError(f"sampling an RGL file's own layout needs a vectorised Mitsuba variant, not {variant}")
    rgl = RGLBRDF(path, variant)
    theta_max = np.radians(theta_max_deg)
    theta_all = np.sort(rgl_theta_i(path))
    theta = theta_all[theta_all <= theta_max + 1e-9]
    band = _band_weights(theta, theta_max)
    g = (np.arange(n_side) + 0.5) / n_side
    U, V = [a.reshape(-1) for a in np.meshgrid(g, g, indexing="ij")]
    if rng is not None:
        if not isinstance(rng, np.random.Generator):
            raise TypeError("rgl_samples(rng=...) takes a numpy.random.Generator")
        U, V = rng.random((2, n_side * n_side))
    m = U.size
    # cosine-distributed set (Malley's method on the stratified grid)
    r, ph = np.sqrt(U), 2.0 * np.pi * V
    cos_set = np.stack([r * np.cos(ph), r * np.sin(ph), np.sqrt(np.clip(1.0 - U, 0.0, 1.0))], axis=-1)
    wis, wos, weights, clusters = [], [], [], []
    point = np.concatenate([np.arange(m), np.arange(m)])     # the (U, V) draw behind each outgoing direction
    with mi.scoped_set_variant(variant):
        ctx = mi.BSDFContext()
        for t, wband in zip(theta, band):
            d = directions(np.full(2 * m, t), np.zeros(2 * m))     # the file's incident direction (phi 0: isotropic)
            k = quarter_turns(d) if rgl.isotropic else np.zeros(2 * m, int)   # as RGLBRDF.eval_cos
            si, _ = interaction(turn(d[:m], k[:m]), turn(d[:m], k[:m]))
            bs, _ = rgl._bsdf.sample(ctx, si, mi.Float(np.full(m, 0.5, np.float32)),
                                     mi.Point2f(U.astype(np.float32), V.astype(np.float32)))
            sampled = turn(np.array(bs.wo, dtype=np.float64).reshape(3, m).T, -k[:m])
            out = np.concatenate([sampled, cos_set])
            out /= np.linalg.norm(out, axis=1, keepdims=True)
            si2, w2 = interaction(turn(out, k), turn(d, k))
            p_bsdf = np.array(rgl._bsdf.pdf(ctx, si2, w2), dtype=np.float64).reshape(-1)
            p_cos = np.clip(out[:, 2], 0.0, None) / np.pi
            ok = (out[:, 2] > np.cos(theta_max)) & np.isfinite(p_bsdf) & ((p_bsdf + p_cos) > 0)
            # 2m samples, mixture pdf (p_bsdf + p_cos) / 2
            w_out = np.divide(1.0, m * (p_bsdf + p_cos), out=np.zeros(2 * m), where=ok)
            wis.append(out[ok])                                 # gonio's wi: toward the light
            wos.append(d[:m][:1].repeat(ok.sum(), 0))           # gonio's wo: the file's incident direction
            weights.append(w_out[ok] * wband)
            clusters.append(point[ok])
    wi, wo, weight = np.concatenate(wis), np.concatenate(wos), np.concatenate(weights)
    f = rgl.eval(wi, wo)
    std = rel_std * np.maximum(np.abs(f), floor)
    use = np.repeat(((wi[:, 2] > 1e-9) & (wo[:, 2] > 1e-9))[:, None], 3, axis=1)
    attrs = {"source": "RGL", "path": rgl.path, "rel_std": rel_std, "floor": floor, "variant": variant,
             "nominal_sigma": True, "isotropic": True, "sampling": f"own layout: {theta.size} measured theta_i <= {theta_max_deg:g} deg, "
             f"{2 * m} outgoing each (half by the material's importance sampling, half cosine), MIS weights"}
    return Measurements(wi, wo, f, std, use, attrs, weight=weight, cluster=np.concatenate(clusters))


def merl_weights(wi, wo) -> np.ndarray:
    """Solid-angle weight of each MERL bin centre: the bin's volume in Rusinkiewicz
    coordinates times the Jacobian sin(theta_h) sin(theta_d) (Rusinkiewicz 1998), up to a
    constant factor (theta_h bins are quadratic: d theta_h = 2 sqrt(theta_h (pi/2)) / 90)."""
    th, _, td, _ = half_diff_angles(wi, wo)
    dth = np.sqrt(np.clip(th, 1e-6, None) * (np.pi / 2)) / 45.0
    return np.clip(np.sin(th) * np.sin(td) * dth, 1e-12, None)


def merl_samples(path, *, n: int | None = None, rng=None, theta_max_deg: float = 80.0) -> Measurements:
    """Every MERL bin with data (or a seeded subset of ``n``), weighted (:func:`merl_weights`)."""
    meas = merl_to_measurements(path, n=n, rng=rng)
    cmax = np.cos(np.radians(theta_max_deg))
    keep = (meas.wi[:, 2] > cmax) & (meas.wo[:, 2] > cmax) & meas.use.any(axis=1)
    meas = meas.subset(keep)
    attrs = dict(meas.attrs, nominal_sigma=True, isotropic=True, sampling="every MERL bin with data" if n is None else f"{n} MERL bins (seeded)")
    return dataclasses.replace(meas, attrs=attrs, weight=merl_weights(meas.wi, meas.wo))
