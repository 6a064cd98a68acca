"""Close the loop: render a fitted BSDF in Mitsuba 3 at the measured geometry.

The virtual gonioreflectometer is a flat square sample (normal +z) with the fitted BSDF, a
``directional`` emitter of unit irradiance arriving from ``wi``, and a ``radiancemeter``
aimed at the sample's centre from ``wo``, rendered with the ``direct`` integrator. For this
scene Mitsuba returns L = f_r(wi, wo) * E * cos(theta_i) exactly (no Monte Carlo noise: the
light is a delta and the sensor a single ray; checked in ../shared/notes/tech-facts.md to
4e-7), so f_r_render = L / cos(theta_i) is what Mitsuba *renders* for the exported model,
independently of gonio's own evaluation. Differences between the two are export errors;
differences from the measurement are the model's or the measurement's.

The scene is built once and re-posed per point through ``mi.traverse`` (no recompilation).
"""

from __future__ import annotations

import time

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.core.geometry import angles_deg, finite_directions
from gonio.core.sides import REFLECTION_ONLY, sides_mask
from gonio.models.mitsuba import SCENE_VARIANT

from gonio.fitting.render.batch import check_renders_in, render_brdf_batch, renders_in

__all__ = ["DEFAULT_VARIANT", "VirtualGonio", "check_renders_in", "loop_closure", "render_brdf", "renders_in",
           "scene_check"]

#: The per-pose scene's variant (:data:`gonio.models.mitsuba.SCENE_VARIANT`: scalar).
DEFAULT_VARIANT = SCENE_VARIANT


def _look_at_matrix(origin, target, up):
    """4x4 camera-to-world matrix, Mitsuba's look_at convention (camera looks along +z)."""
    origin, target, up = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    d = target - origin
    d /= np.linalg.norm(d)
    left = np.cross(up, d)
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, origin
    return m


def _rotation_to_z(w):
    """Rotation matrix whose rows are an orthonormal basis with the last row equal to ``w``.

    ``rot @ w = (0, 0, 1)``: as a local-to-world map it turns ``w`` onto the world z axis.
    """
    w = w / np.linalg.norm(w)
    a = np.cross(_up_for(w), w)
    a /= np.linalg.norm(a)
    b = np.cross(w, a)
    return np.stack([a, b, w])


def _up_for(direction):
    """Any unit vector not parallel to ``direction``."""
    return np.array([1.0, 0.0, 0.0]) if abs(direction[2]) > 0.9 else np.array([0.0, 0.0, 1.0])


class VirtualGonio:
    """A Mitsuba scene that measures f_r like the bench does, one pose at a time.

    Parameters
    ----------
    bsdf : dict
        A Mitsuba BSDF dict (``model.to_mitsuba(params)``).
    variant : str, optional
        Mitsuba variant (default :data:`DEFAULT_VARIANT`); set only for this object's calls.
    tangent_deg : float
        The frame ``bsdf`` is written in (``model.tangent_deg(params)``): the sample turned by
        it about its normal.
    """

    def __init__(self, bsdf: dict, variant: str | None = None, tangent_deg: float = 0.0):
        import mitsuba as mi

        t = np.radians(float(tangent_deg))
        self._turn = np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])
        self.variant = variant or DEFAULT_VARIANT
        self._mi = mi
        if mi.variant() is None:  # scoped_set_variant cannot restore "no variant"
            mi.set_variant(self.variant)
        with mi.scoped_set_variant(self.variant):
            self._build(bsdf)

    def _build(self, bsdf):
        mi = self._mi
        self.scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "direct"},
            "sample": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([10.0, 10.0, 1.0]), "bsdf": bsdf},
            "lamp": {"type": "directional", "direction": [0.0, 0.0, -1.0], "irradiance": {"type": "rgb", "value": 1.0}},
            "meter": {"type": "radiancemeter", "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                      "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "rgb"}},
        })
        self.params = mi.traverse(self.scene)
        self._lamp_key = next(k for k in self.params.keys() if k.startswith("lamp") and k.endswith("to_world"))
        self._sample_key = "sample.to_world"

    def radiance(self, wi, wo) -> np.ndarray:
        """Rendered radiance (W m^-2 sr^-1 per unit irradiance), shape (3,), for one pose."""
        with self._mi.scoped_set_variant(self.variant):
            return self._radiance(wi, wo)

    def _radiance(self, wi, wo) -> np.ndarray:
        mi = self._mi
        wi, wo = np.asarray(wi, dtype=np.float64), np.asarray(wo, dtype=np.float64)
        # The meter stays on the world z axis; the sample turns so that its local wo points
        # at it (Mitsuba does not traverse a radiancemeter's to_world).
        rot = _rotation_to_z(wo)  # local -> world: the sample's wo lands on the meter's axis
        to_world = np.eye(4)
        to_world[:3, :3] = rot @ self._turn @ np.diag([10.0, 10.0, 1.0])
        self.params[self._sample_key] = mi.Transform4f(to_world)
        # The directional emitter sends light along its frame's +z: toward the sample, i.e. -wi.
        wi_world = rot @ wi
        self.params[self._lamp_key] = mi.Transform4f(_look_at_matrix([0, 0, 0], -wi_world, _up_for(wi_world)))
        self.params.update()
        image = mi.render(self.scene, spp=1)
        return np.asarray(image, dtype=np.float64).reshape(-1)[:3]

    def brdf(self, wi, wo, sides=REFLECTION_ONLY) -> np.ndarray:
        """f_r as rendered, shape (N, 3); 0 for pairs on none of ``sides`` (reflection: either
        direction at or below the horizon). A transmitted pose turns the sample so that the
        meter looks at its far face, lit from the front: the ``direct`` integrator's shadow ray
        to the lamp leaves from the surface, which does not occlude itself."""
        wi, wo = np.atleast_2d(wi), np.atleast_2d(wo)
        out = np.zeros((wi.shape[0], CHANNELS))
        ok = sides_mask(sides, wi[:, 2], wo[:, 2], 1e-9)
        with self._mi.scoped_set_variant(self.variant):
            for n in np.flatnonzero(ok):
                out[n] = self._radiance(wi[n], wo[n]) / wi[n, 2]
        return out


def render_brdf(model, params, wi, wo, variant: str | None = None):
    """Render f_r of a gonio model in Mitsuba at each (wi, wo); returns (f_r (N, 3), seconds, variant)."""
    import mitsuba as mi

    t0 = time.perf_counter()
    variant = variant or DEFAULT_VARIANT
    check_renders_in(model, variant)
    if mi.variant() is None:  # scoped_set_variant cannot restore "no variant"
        mi.set_variant(variant)
    with mi.scoped_set_variant(variant):  # Python BSDFs register per variant
        bsdf = model.to_mitsuba(params)
    gonio = VirtualGonio(bsdf, variant, float(getattr(model, "tangent_deg", lambda p: 0.0)(params)))
    fr = gonio.brdf(wi, wo, model.structure.sides)
    return fr, time.perf_counter() - t0, gonio.variant


def loop_closure(model, params, meas, variant: str | None = None, n_worst: int = 5) -> dict:
    """Render the fit at every measured pose and compare with gonio's evaluation and the data.

    All poses go through the batched wavefront evaluation (:mod:`gonio.fitting.render.batch`, one kernel
    in llvm_ad_rgb); 50 of them are also rendered with the per-pose scene
    (:class:`VirtualGonio`) to show the two are the same render (``scene_check``).

    Returns a JSON-ready dict: the rendered f_r, the export check (render vs ``model.eval``),
    residuals of the measurement against the render in units of its 1-sigma, and the worst
    points with their geometry (degrees).
    """
    rendered, seconds, used_variant = render_brdf_batch(model, params, meas.wi, meas.wo, variant)
    check = scene_check(model, params, meas.wi, meas.wo, n=50, rng=0, variant=used_variant,
                        scene_variant=DEFAULT_VARIANT if renders_in(model, DEFAULT_VARIANT) else used_variant)
    evaluated = model.eval(meas.wi, meas.wo, params)
    floor = 1e-6
    mask = np.abs(evaluated) > floor
    export_rel = np.abs(rendered - evaluated)[mask] / np.abs(evaluated)[mask]
    resid = (meas.brdf - rendered) / meas.brdf_std
    used = np.where(meas.use, resid, 0.0)
    per_point = np.sqrt(np.sum(used ** 2, axis=1) / np.maximum(meas.use.sum(axis=1), 1))
    order = np.argsort(per_point)[::-1][:n_worst]

    ti, pi_ = angles_deg(meas.wi)
    to, po = angles_deg(meas.wo)
    worst = [{"point": int(k), "theta_i": float(ti[k]), "phi_i": float(pi_[k]), "theta_o": float(to[k]),
              "phi_o": float(po[k]), "residual_sigma": float(per_point[k])} for k in order]
    return {
        "variant": used_variant, "points": int(meas.n_points), "time_s": seconds,
        "brdf_render": rendered.tolist(), "brdf_model": evaluated.tolist(),
        "residual_sigma": resid.tolist(),
        "scene_check": {"poses": int(check["indices"].size), "max_rel": check["max_rel"],
                        "variant": check["scene_variant"]},
        "summary": {
            "export_max_rel": float(export_rel.max()) if export_rel.size else 0.0,
            "export_median_rel": float(np.median(export_rel)) if export_rel.size else 0.0,
            "residual_rms_sigma": float(np.sqrt(np.mean(resid[meas.use] ** 2))),
            "residual_max_sigma": float(np.max(np.abs(resid[meas.use]))),
            "worst": worst,
        },
    }


def scene_check(model, params, wi, wo, n: int = 50, rng=None, variant: str | None = None,
                scene_variant: str | None = None, floor: float = 1e-6) -> dict:
    """Re-render ``n`` of the poses with the one-scene-per-pose virtual gonioreflectometer.

    Shows that the batched evaluation *is* the render: both numbers come from Mitsuba, one
    from the scene (``VirtualGonio``: rectangle, directional lamp, radiancemeter, ``direct``
    integrator), one from :func:`render_brdf_batch`.

    Returns a dict: ``indices`` (the poses checked), ``batch`` and ``scene`` (f_r, (n, 3)),
    ``max_rel`` (largest |batch - scene| / |scene| where f_r * cos(theta_i) > ``floor``),
    ``variant`` and ``scene_variant``.
    """
    wi = finite_directions(wi, "wi")
    wo = finite_directions(wo, "wo")
    rng = np.random.default_rng(rng)
    idx = np.sort(rng.choice(wi.shape[0], size=min(n, wi.shape[0]), replace=False))
    batch, _, used = render_brdf_batch(model, params, wi[idx], wo[idx], variant)
    scene_variant = scene_variant or used
    scene, _, _ = render_brdf(model, params, wi[idx], wo[idx], scene_variant)
    weight = np.abs(scene) * np.clip(wi[idx, 2], 0, None)[:, None]
    mask = weight > floor
    rel = np.abs(batch - scene)[mask] / np.abs(scene)[mask]
    return {"indices": idx, "batch": batch, "scene": scene, "max_rel": float(rel.max()) if rel.size else 0.0,
            "n_compared": int(mask.sum()), "variant": used, "scene_variant": scene_variant}
