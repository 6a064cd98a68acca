"""Fit a candidate to what a scene shows of the material: its pixels, not its direction pairs.

A pixel that sees the sample records L_p = integral of f_r(wi, wo_p) cos(theta_i) L(wi) dwi
over the light the scene sends it, so two BSDFs that differ in every direction pair can agree
in every pixel (under a uniform sky L_p is the sky times the directional albedo a(wo_p)), and
a fit to the pairs is the wrong fit for that scene. :func:`scene_pixels` casts one ray through
each pixel's centre, keeps the pixels whose hit carries the sample's BSDF (``id="sample"`` in
a scene file; the sphere of a preset) and samples every emitter there with its own sampling
and a visibility ray: a pixel is ``sum_j f_r(wi_j, wo_p) cos(theta_ij) w_j`` over its pairs,
the same samples for the measured BSDF and every candidate (common random numbers).
:func:`fit_in_scene` fits those pixels with scipy's ``least_squares`` in the parameter space's
unit box, the residuals per channel divided by that channel's rms over the image.
"""

# The furnace argument: a rough silver sphere and a grey Lambertian one of the same albedo look
# the same under a uniform sky, and a fit to the pairs weights every pair.
# scene_pixels: rays from the scene's camera (sensor.sample_ray); every emitter of the scene is
# sampled on its own with Emitter.sample_direction, so shadows and every emitter type count:
# a delta light (a sun, a point) is one exact direction with its exact weight, an area light
# or a sky k samples, each weighted by radiance / pdf / k. The measured BSDF is evaluated
# through Mitsuba's bsdf.eval; sharing the samples means the comparison has no Monte Carlo
# noise of its own: the fit matches the candidate's pixels to the measured material's pixels
# as the same estimator sees them.
# fit_in_scene: trust-region reflective, from the pair fit's parameters and the declared
# defaults, then seeded random starts, each only while the best fit so far leaves more than
# 2 % of the image unexplained. Per-channel rms scaling because a least-squares fit of noisy
# pixel estimates is unbiased where the model is linear in a parameter, as a reflectance is;
# a per-pixel relative residual is not.

from __future__ import annotations

import dataclasses
import time

import numpy as np

from gonio.models.mitsuba import select_variant

__all__ = ["ScenePixels", "scene_pixels", "pixel_values", "measured_pixels", "SceneFit", "fit_in_scene"]

#: The id a scene file gives the sample's BSDF (``<bsdf type="..." id="sample"/>``).
SAMPLE_ID = "sample"


@dataclasses.dataclass(frozen=True)
class ScenePixels:
    """The direction pairs a scene asks of the sample, per pixel.

    ``wi``, ``wo`` (M, 3) in the sample's local frame (gonio's convention: wi toward the light);
    ``weight`` (M, 3) the light sample's radiance / pdf over the samples its emitter drew at
    the pixel (so a pixel's value is the sum over its pairs); ``pixel`` (M,) the index of the pixel
    (0..n_pixels-1) each pair belongs to; ``mask`` (H, W) the pixels that see the sample,
    ``k`` the light samples per pixel and area or environment emitter.
    """

    wi: np.ndarray
    wo: np.ndarray
    weight: np.ndarray
    pixel: np.ndarray
    mask: np.ndarray
    k: int
    scene: str

    @property
    def n_pixels(self) -> int:
        return int(self.mask.sum())


def _sample_bsdf(mi, scene):
    found = [sh.bsdf() for sh in scene.shapes() if sh.bsdf() is not None and sh.bsdf().id() == SAMPLE_ID]
    if not found:
        raise ValueError(f"the scene has no shape with a BSDF of id {SAMPLE_ID!r}: mark the sample's material "
                         f'<bsdf type="..." id="{SAMPLE_ID}"> so that gonio knows which surface to fit')
    return found[0]


def scene_pixels(scene, *, rng, k: int = 64, variant=None, name: str = "") -> ScenePixels:
    """The pixels of ``scene`` (a loaded ``mitsuba.Scene`` whose sample BSDF has id
    ``"sample"``) that see the sample, with ``k`` light samples each (see the module).
    ``rng``: a numpy Generator (the light samples)."""
    import drjit as dr
    import mitsuba as mi

    if not isinstance(rng, np.random.Generator):
        raise TypeError("scene_pixels(rng=...) takes a numpy.random.Generator")
    if int(k) < 1:
        raise ValueError(f"k = {k}: at least one light sample a pixel")
    k = int(k)
    select_variant(variant)
    target = mi.BSDFPtr(_sample_bsdf(mi, scene))
    sensor = scene.sensors()[0]
    w, h = (int(v) for v in sensor.film().crop_size())
    x, y = np.meshgrid(np.arange(w), np.arange(h))
    pos = mi.Point2f(((x.ravel() + 0.5) / w).astype(np.float32), ((y.ravel() + 0.5) / h).astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    on = np.array(si.is_valid() & (si.bsdf() == target), dtype=bool)
    mask = on.reshape(h, w)
    idx = np.flatnonzero(on)
    if idx.size == 0:
        raise ValueError("no pixel of the scene's camera sees the sample")
    # every emitter on its own (no random choice between them): a delta light (a sun, a point)
    # once a pixel with its exact weight, any other k times; shadows by a visibility ray
    px, py = np.array(pos.x)[idx], np.array(pos.y)[idx]
    parts = []
    for emitter in scene.emitters():
        n = 1 if mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta) else k
        rep = np.repeat(np.arange(idx.size), n)
        ray_n, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(px[rep], py[rep]), mi.Point2f(0.5, 0.5))
        si_n = scene.ray_intersect(ray_n)
        u = rng.random((2, rep.size)).astype(np.float32)
        ds, spec = emitter.sample_direction(si_n, mi.Point2f(u[0], u[1]))
        seen = ~scene.ray_test(si_n.spawn_ray_to(ds.p))
        light = np.array(spec, dtype=np.float64).T * np.array(seen, dtype=np.float64)[:, None] / n
        parts.append((np.array(si_n.to_local(ds.d), dtype=np.float64).T, np.array(si_n.wi, dtype=np.float64).T, light,
                      rep))
    dr.eval()
    wi, wo, weight, pixel = (np.concatenate([q[i] for q in parts]) for i in range(4))
    keep = (wi[:, 2] > 1e-6) & (wo[:, 2] > 1e-6) & np.all(np.isfinite(weight), axis=1) & np.any(weight > 0, axis=1)
    wi, wo, weight, pixel = wi[keep], wo[keep], weight[keep], pixel[keep]
    return ScenePixels(wi / np.linalg.norm(wi, axis=1, keepdims=True), wo / np.linalg.norm(wo, axis=1, keepdims=True),
                       weight, pixel, mask, k, str(name))


def pixel_values(f_cos: np.ndarray, sp: ScenePixels) -> np.ndarray:
    """(n_pixels, C) pixel estimates from f_r cos(theta_i) (M, C) at ``sp``'s pairs."""
    contrib = np.asarray(f_cos, dtype=np.float64) * sp.weight
    return np.stack([np.bincount(sp.pixel, weights=contrib[:, c], minlength=sp.n_pixels)
                     for c in range(contrib.shape[1])], axis=1)


def measured_pixels(measured, sp: ScenePixels, variant=None) -> np.ndarray:
    """The measured material's pixels (Mitsuba's ``bsdf.eval`` at ``sp``'s pairs)."""
    import mitsuba as mi

    from gonio.models.mitsuba import eval_cos

    from gonio.fitting.render.preview import measured_bsdf_dict

    variant = select_variant(variant)
    with mi.scoped_set_variant(variant):
        bsdf = mi.load_dict(measured_bsdf_dict(measured, variant))
        return pixel_values(eval_cos(bsdf, sp.wi, sp.wo, variant), sp)


@dataclasses.dataclass
class SceneFit:
    """A candidate fitted to a scene's pixels: ``model``, ``params``, ``space`` (the
    ParameterSpace), ``rms_rel`` (rms pixel residual over the image's rms, per channel), ``seconds``, ``starts``."""

    model: object
    params: dict
    space: object
    rms_rel: float
    seconds: float
    starts: int


def fit_in_scene(model, sp: ScenePixels, target: np.ndarray, *, rng, start: dict | None = None,
                 n_random: int = 3, good_enough: float = 0.02) -> SceneFit:
    """Fit ``model`` to the pixels ``target`` (n_pixels, C) of :func:`measured_pixels`:
    from ``start`` (the candidate's fit to the data), the declared defaults, then up to
    ``n_random`` seeded random starts, each tried only while the best rms residual so far is
    above ``good_enough`` of the image's rms."""
    from scipy.optimize import least_squares

    from gonio.fitting.optimise.space import ParameterSpace

    if not isinstance(rng, np.random.Generator):
        raise TypeError("fit_in_scene(rng=...) takes a numpy.random.Generator")
    target = np.asarray(target, dtype=np.float64)
    if target.shape != (sp.n_pixels, target.shape[-1]) or not np.all(np.isfinite(target)):
        raise ValueError("fit_in_scene: target must be finite, one row per pixel of the scene")
    t0 = time.perf_counter()
    space = ParameterSpace(model, n_channels=target.shape[1])
    # per channel, the image's rms: a pixel's estimate is noisy (k light samples of a lobe that
    # may be sharp; heavy-tailed where few samples hit it), so a per-pixel relative residual
    # would let the pixels whose samples missed the lobe (near-zero estimates) pull the fit down
    scale = np.maximum(np.sqrt(np.mean(target * target, axis=0)), 1e-300)
    cos_i = sp.wi[:, 2:3]

    def residual(u):
        p = space.to_params(space.from_unit(u))
        pred = pixel_values(model.eval(sp.wi, sp.wo, p) * cos_i, sp)
        return ((pred - target) / scale).ravel()

    first = [space.to_unit(space.default())]
    if start is not None:
        first.insert(0, space.to_unit(space.from_params(model.validate(start))))
    best, n = None, 0
    for u0 in first + list(rng.random((int(n_random), space.size))):
        if best is not None and np.sqrt(2.0 * best.cost / best.fun.size) < good_enough:
            break                      # the data's fit (or the defaults) already explain the scene
        r = least_squares(residual, np.clip(u0, 1e-6, 1 - 1e-6), bounds=(0.0, 1.0), method="trf",
                          x_scale="jac", max_nfev=100)
        n += 1
        if best is None or r.cost < best.cost:
            best = r
    x = space.from_unit(best.x)
    rms = float(np.sqrt(2.0 * best.cost / best.fun.size))
    return SceneFit(model, space.to_params(x), space, rms, time.perf_counter() - t0, n)
