"""Model only what a scene needs (issue 16): render every fitted candidate and the measured
BSDF in the scene the material will be used in, with matched seeds, and pick the simplest
candidate whose rendered difference is below a perceptual threshold.

A scene is a preset (:data:`PRESETS`; each puts the material on a sphere):

* ``overcast``: a uniform sky (constant emitter) and nothing else -- every direction lights
  the sample equally, so the specular lobe's shape integrates away;
* ``product-shot``: a small area light and a dim fill, the preview's "area" lighting;
* ``close-up-sun``: a directional sun and a dim sky, the camera close to the sample -- the
  highlight's shape fills the frame.

For each candidate: the mean CIEDE2000 (Sharma et al. 2005, through colour-science) of its
render against the measured BSDF's render with the same seed, over the pixels that see the
material; the noise floor of that comparison from a second matched pair of seeds
(:func:`gonio.fitting.preview.matched_noise_floor`); and Mitsuba's evaluation cost of the
candidate's BSDF (seconds per 2^16 ``bsdf.eval`` calls, the best of three after the JIT's
first call). The candidates with their (cost, error) form the speed-versus-error front
(:func:`front`: the candidates no other one beats on both). The chosen one is the simplest
(fewest parameters, then cheapest) whose mean difference is below ``threshold``; the
comparison is refused (ValueError) when the noise floor itself is not below half the
threshold: more samples per pixel are needed to tell.

The fit is weighted by the scene (:func:`scene_samples`): the direction pairs the scene's
camera and lights ask of the material (one per pixel that sees the sphere and light sample:
the view direction and a light direction in the local frame), each weighted by the light it
carries (the sun's irradiance; sky radiance times pi / K for K cosine-distributed sky
samples), the measured BSDF evaluated there. Not done yet: Mitsuba scene files (presets only).
"""

from __future__ import annotations

import time

import numpy as np

from gonio.models.mitsuba import select_variant

from .preview import delta_e_2000, matched_noise_floor, measured_bsdf_dict

__all__ = ["PRESETS", "scene_dict", "scene_directions", "scene_samples", "render_in_scene", "rank_in_scene", "front"]

PRESETS = ("overcast", "product-shot", "close-up-sun")
_SUN = np.array([-0.45, 0.55, 0.7]) / np.linalg.norm([-0.45, 0.55, 0.7])   # toward the sun


def scene_dict(mi, preset, bsdf, size, spp):
    """The Mitsuba dict of a preset scene with ``bsdf`` on its sphere."""
    if preset not in PRESETS:
        raise ValueError(f"scene preset {preset!r}: choose one of {', '.join(PRESETS)} or give a Mitsuba scene file")
    close = preset == "close-up-sun"
    dist, fov = (2.6, 24.0) if close else (4.5, 30.0)
    scene = {
        "type": "scene",
        "integrator": {"type": "direct"},
        "sphere": {"type": "sphere", "radius": 1.0, "bsdf": bsdf},
        "camera": {"type": "perspective", "fov": fov, "fov_axis": "x",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, dist], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
    }
    if preset == "overcast":
        scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": 0.8}}
    elif preset == "product-shot":
        scene["lamp"] = {"type": "sphere", "radius": 0.15, "center": [-2.9, 2.9, 3.5],
                         "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 900.0}}}
        scene["fill"] = {"type": "constant", "radiance": {"type": "rgb", "value": 0.03}}
    else:
        scene["sun"] = {"type": "directional", "direction": (-_SUN).tolist(), "irradiance": {"type": "rgb", "value": 2.5}}
        scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": 0.05}}
    return scene


def _frame(n):
    """Tangent frames (t, b, n) of unit normals n (N, 3) (Duff et al. 2017)."""
    sign = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=-1)
    bb = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=-1)
    return t, bb, n


def scene_directions(preset, size, rng, k_sky=8):
    """(wi, wo, weight) in the local shading frame: the pairs a preset scene asks of the
    material (see the module). ``rng``: a numpy Generator (the sky samples)."""
    if preset not in PRESETS:
        raise ValueError(f"scene preset {preset!r}: choose one of {', '.join(PRESETS)}")
    dist, fov = (2.6, 24.0) if preset == "close-up-sun" else (4.5, 30.0)
    half = np.tan(np.radians(fov) / 2.0)
    g = ((np.arange(size) + 0.5) / size * 2.0 - 1.0) * half
    X, Y = np.meshgrid(g, -g)
    d = np.stack([X.ravel(), Y.ravel(), -np.ones(X.size)], axis=-1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.array([0.0, 0.0, dist])
    bq = d @ o
    disc = bq * bq - (o @ o - 1.0)
    hit = disc > 0.0
    tq = -bq[hit] - np.sqrt(disc[hit])
    n = o + tq[:, None] * d[hit]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t, b, n = _frame(n)
    to_local = lambda v: np.stack([np.sum(v * t, 1), np.sum(v * b, 1), np.sum(v * n, 1)], axis=-1)  # noqa: E731
    wo = to_local(-d[hit])
    sky = {"overcast": 0.8, "product-shot": 0.03, "close-up-sun": 0.05}[preset]
    u = rng.random((2, wo.shape[0] * k_sky))
    r, ph = np.sqrt(u[0]), 2.0 * np.pi * u[1]
    wi = [np.stack([r * np.cos(ph), r * np.sin(ph), np.sqrt(1.0 - u[0])], axis=-1)]
    wos = [np.repeat(wo, k_sky, axis=0)]
    weight = [np.full(wi[0].shape[0], sky * np.pi / k_sky)]
    if preset != "overcast":
        lamp = _SUN if preset == "close-up-sun" else np.array([-2.9, 2.9, 3.5]) / np.linalg.norm([-2.9, 2.9, 3.5])
        e = 2.5 if preset == "close-up-sun" else 900.0 * np.pi * 0.15 ** 2 / (np.linalg.norm([-2.9, 2.9, 3.5]) - 1.0) ** 2
        li = to_local(np.broadcast_to(lamp, n.shape))
        wi.append(li)
        wos.append(wo)
        weight.append(np.full(li.shape[0], e))
    wi, wo, weight = np.concatenate(wi), np.concatenate(wos), np.concatenate(weight)
    ok = (wi[:, 2] > 1e-3) & (wo[:, 2] > 1e-3)
    return wi[ok], wo[ok], weight[ok]


def scene_samples(measured, preset, *, size=24, rng, rel_std=0.02, floor=1e-4, variant=None):
    """Measurements of the measured BSDF at the pairs the scene asks of it, with the scene's
    light as each pair's weight (:func:`scene_directions`); a nominal sigma as rgl_samples."""
    import mitsuba as mi

    from gonio.models.mitsuba import divide_cos, eval_cos

    from ._data import Measurements

    if not isinstance(rng, np.random.Generator):
        raise TypeError("scene_samples(rng=...) takes a numpy.random.Generator")
    variant = select_variant(variant)
    wi, wo, weight = scene_directions(preset, size, rng)
    with mi.scoped_set_variant(variant):
        bsdf = mi.load_dict(measured_bsdf_dict(measured, variant))
        f = divide_cos(eval_cos(bsdf, wi, wo, variant), wi, wo)
    std = rel_std * np.maximum(np.abs(f), floor)
    attrs = {"source": f"scene {preset}", "nominal_sigma": True, "rel_std": rel_std, "floor": floor,
             "sampling": f"directions the {preset} scene asks ({size} px, weighted by its light)"}
    return Measurements(wi, wo, f, std, np.ones(f.shape, bool), attrs, weight=weight * wi.shape[0] / weight.sum())


def _load(mi, scene, bsdf, size, spp):
    return mi.load_dict(scene_dict(mi, str(scene), bsdf, size, spp))


def render_in_scene(bsdf, scene, size, spp, seeds, variant=None):
    """Renders of ``bsdf`` (a Mitsuba dict) in ``scene`` at each seed, linear RGB (size, size, 3)."""
    import mitsuba as mi

    variant = select_variant(variant)
    with mi.scoped_set_variant(variant):
        s = _load(mi, scene, bsdf, int(size), int(spp))
        return [np.array(mi.render(s, spp=int(spp), seed=int(seed)), dtype=np.float64)[..., :3] for seed in seeds]


def eval_cost(bsdf, variant=None, n=1 << 16):
    """Seconds per ``n`` Mitsuba ``bsdf.eval`` calls (the best of three, after a first call)."""
    import mitsuba as mi

    from gonio.models.mitsuba import eval_cos

    variant = select_variant(variant)
    rng = np.random.default_rng(0)
    v = rng.normal(size=(2, n, 3))
    v[..., 2] = np.abs(v[..., 2])
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    with mi.scoped_set_variant(variant):
        b = mi.load_dict(bsdf)
        eval_cos(b, v[0], v[1], variant)
        best = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            eval_cos(b, v[0], v[1], variant)
            best = min(best, time.perf_counter() - t0)
    return best


def front(rows):
    """The speed-versus-error front: rows no other row beats on both cost and error."""
    return [r for r in rows if not any((o["cost_s"] <= r["cost_s"] and o["delta_e"] < r["delta_e"])
                                       or (o["cost_s"] < r["cost_s"] and o["delta_e"] <= r["delta_e"]) for o in rows)]


def rank_in_scene(fits, measured, scene, *, size=32, spp=16, seed=0, threshold=1.0, variant=None):
    """Rank fitted candidates by their rendered difference from the measured BSDF in a scene.

    Parameters
    ----------
    fits : sequence of FitResult
        The fitted candidates (e.g. every row of ``select``'s ranking).
    measured : Mitsuba BSDF dict, RGL ``.bsdf`` / MERL ``.binary`` path, RGLBRDF or MerlBRDF
        The measured material.
    scene : str
        A preset (:data:`PRESETS`); anything else is refused (ValueError).
    size, spp, seed : int
        Render size (pixels, square), samples per pixel, the first seed (seed + 1 for the
        noise floor's second pair).
    threshold : float
        Mean CIEDE2000 below which a candidate is good enough.

    Returns
    -------
    dict
        ``rows`` (one per candidate: model, options, k, delta_e, noise, cost_s, chosen),
        ``front`` (the speed-versus-error front, cheapest first), ``chosen`` (the row, or
        None when no candidate is below the threshold), ``scene``, ``size``, ``spp``, ``seed``,
        ``threshold``.
    """
    if not fits:
        raise ValueError("rank_in_scene: no fitted candidates")
    variant = select_variant(variant)
    meas_bsdf = measured_bsdf_dict(measured, variant)
    ref_a, ref_b = render_in_scene(meas_bsdf, scene, size, spp, (seed, seed + 1), variant)
    seen = np.any(np.maximum(ref_a, ref_b) > 0.0, axis=-1)
    rows = []
    for res in fits:
        bsdf = res.model.to_mitsuba(res.params)
        img_a, img_b = render_in_scene(bsdf, scene, size, spp, (seed, seed + 1), variant)
        de = delta_e_2000(img_a, ref_a)[seen]
        noise = matched_noise_floor(img_a, ref_a, img_b, ref_b)[seen]
        rows.append({"model": res.model.name, "options": dict(res.model.options), "k": int(res.space.size),
                     "delta_e": float(de.mean()), "noise": float(noise.mean()), "cost_s": eval_cost(bsdf, variant),
                     "chosen": False})
    worst_floor = max(r["noise"] for r in rows)
    if not worst_floor < 0.5 * threshold:
        raise ValueError(f"scene {scene}: the noise floor of the comparison ({worst_floor:.2f} CIEDE2000) is not "
                         f"below half the threshold {threshold:g}: raise spp (now {spp})")
    good = [r for r in rows if r["delta_e"] < threshold]
    chosen = min(good, key=lambda r: (r["k"], r["cost_s"])) if good else None
    if chosen is not None:
        chosen["chosen"] = True
    return {"rows": rows, "front": sorted(front(rows), key=lambda r: r["cost_s"]), "chosen": chosen,
            "scene": str(scene), "size": int(size), "spp": int(spp), "seed": int(seed), "threshold": float(threshold)}
