"""Mitsuba scene of the sample holder, built once and re-posed per stage pose.

Everything is expressed in the sample's local frame (z = 0 the holder plane, +z the normal):
the geometry never moves, only the ``directional`` emitter (light arriving from ``wi``) and
the ``orthographic`` sensor (looking along ``-wo``, image right/up from the kinematics) are
updated through ``mi.traverse``, so kernels compile once.

The emitter has unit irradiance on a surface facing it, so the rendered radiance on a flat
square is ``f_r(wi, wo) * cos(theta_i)`` (sr^-1); the ``direct`` integrator with a delta
light makes it exact, with no Monte Carlo noise, away from the squares' edges.
A transmissive sample (``sample_truth``) sits in an open holder: seen from the rear detector
(``wo`` below the surface) only the sample square shows, its coverage of each pixel rendered
as a unit-radiance square facing the rear and scaled by f(wi, wo) cos(theta_i) of the truth
(exact: the directions are the same at every pixel; this Mitsuba has no ``difftrans``).
``open_beam`` images the lamp through the empty aperture the same way (ASTM E2387).
"""

from __future__ import annotations

import numpy as np

import gonio.models as gm
from gonio.models.mitsuba import mitsuba_variant, tangent_square

from gonio.sim.physics.holder_markers import holder_transform, marker_shapes

__all__ = ["HolderScene", "sample_tangent_deg"]

_SQUARE_LIFT = 0.0        # sample and reference squares lie in z = 0
_HOLDER_DROP = 2e-4       # the dark holder plate lies just below them (holder units)
_HOLDER_HALF = 50.0       # holder plate half-size: covers the view up to grazing angles
_DISTANCE = 10.0          # sensor distance from the sample centre (holder units)


def _frame(origin, forward, up, scale_xy=1.0) -> np.ndarray:
    """4x4 camera-style to_world (Mitsuba ``look_at`` convention: x = up x forward)."""
    f = np.asarray(forward, float)
    f = f / np.linalg.norm(f)
    left = np.cross(up, f)
    nrm = np.linalg.norm(left)
    if nrm < 1e-9:                       # forward parallel to up: any perpendicular will do
        left = np.cross([1.0, 0.0, 0.0] if abs(f[0]) < 0.9 else [0.0, 1.0, 0.0], f)
        nrm = np.linalg.norm(left)
    left = left / nrm
    new_up = np.cross(f, left)
    m = np.eye(4)
    m[:3, 0] = left * scale_xy
    m[:3, 1] = new_up * scale_xy
    m[:3, 2] = f
    m[:3, 3] = origin
    return m


def sample_tangent_deg(sample_truth) -> float:
    """The tangent of a resolved sample (`gonio.sim.physics.sample.SampleTruth`) from the
    holder's x axis, deg: the frame its Mitsuba dict is written in (an anisotropic model's
    ``tangent_deg``); 0 for every other sample."""
    spec = getattr(sample_truth, "spec", None) or {}
    if "model" not in spec:
        return 0.0
    model = gm.get(spec["model"], **dict(spec.get("options", {})))
    if not hasattr(model, "tangent_deg"):
        return 0.0
    return float(model.tangent_deg(dict(spec.get("params", {}))))


class HolderScene:
    """The holder (sample square, reference square, dark plate) seen by the camera.

    Parameters
    ----------
    sample_bsdf, reference_bsdf : dict
        Mitsuba BSDF dicts (the sample's in its tangent frame: :func:`sample_tangent_deg`).
    width, height : int
        Image size, pixels.
    pixel_size : float
        Holder units per pixel at the sample.
    sample_half, offset, holder_reflectance : float
        Holder layout (docs/interfaces.md section 3).
    spp : int
        Samples per pixel (anti-aliasing of the squares' edges only).
    markers : dict, optional
        ArUco markers or a ChArUco board on the holder (``[holder] markers``, gonio/sim/physics/holder_markers.py).
    holder_pose : (dx, dy, angle_deg), optional
        Where the holder really sits in the sample plane (the simulator's truth; default where
        the settings put it).
    """

    def __init__(self, sample_bsdf: dict, reference_bsdf: dict, *, width: int, height: int,
                 pixel_size: float, sample_half: float, offset: float,
                 holder_reflectance: float, spp: int = 4, markers=None, holder_pose=None,
                 sample_truth=None):
        import mitsuba as mi

        self.variant = mitsuba_variant()
        self.width, self.height = int(width), int(height)
        self.half_width = 0.5 * self.width * float(pixel_size)
        self.spp = int(spp)
        self.sample_truth = sample_truth if getattr(sample_truth, "transmits", False) else None
        self._layout = (float(sample_half), float(offset), holder_pose)
        with mi.scoped_set_variant(self.variant):
            T = mi.ScalarTransform4f
            scene = {
                **self._base(mi),
                # an anisotropic sample's tangent: the square's texture frame turned (its footprint kept)
                "sample": tangent_square(sample_bsdf, self._square(mi, -offset), sample_tangent_deg(sample_truth)),
                "reference": {"type": "rectangle", "to_world": self._square(mi, offset), "bsdf": reference_bsdf},
                "holder": {
                    "type": "rectangle",
                    "to_world": T().translate([0.0, 0.0, -_HOLDER_DROP]) @ T().scale([_HOLDER_HALF, _HOLDER_HALF, 1.0]),
                    "bsdf": {"type": "diffuse",
                             "reflectance": {"type": "rgb", "value": float(holder_reflectance)}},
                },
                **marker_shapes(markers, holder_pose, mi),
            }
            self._scene = mi.load_dict(scene)
            self._params = mi.traverse(self._scene)
            self._beam = None
        self.renders = 0

    def _base(self, mi) -> dict:
        return {
            "type": "scene",
            "integrator": {"type": "direct"},
            "sensor": {
                "type": "orthographic",
                "film": {"type": "hdrfilm", "width": self.width, "height": self.height,
                         "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                "sampler": {"type": "independent", "sample_count": self.spp},
            },
            "lamp": {"type": "directional", "irradiance": {"type": "rgb", "value": 1.0}},
        }

    def _square(self, mi, cx):
        T = mi.ScalarTransform4f
        half, _, holder_pose = self._layout
        return holder_transform(T, holder_pose) @ T().translate([cx, 0.0, _SQUARE_LIFT]) @ T().scale([half, half, 1.0])

    def render(self, wi, wo, right, up) -> np.ndarray:
        """Radiance image for unit irradiance from ``wi``, seen from ``wo``.

        Parameters
        ----------
        wi, wo, right, up : (3,) array
            Unit vectors in the sample frame: to the lamp, to the camera, image right, image up.

        Returns
        -------
        (height, width, 3) float64 array
            Radiance, sr^-1 (times the irradiance), row 0 at the top of the image.
        """
        import mitsuba as mi

        wi = np.asarray(wi, float)
        wo = np.asarray(wo, float)
        up = np.asarray(up, float)
        if self.sample_truth is not None and wo[2] < 0.0:   # the open holder from behind
            f = np.asarray(self.sample_truth.eval(wi[None, :], wo[None, :]), dtype=float)[0]
            return self.aperture(wo, up) * (f * max(float(wi[2]), 0.0))[None, None, :]
        with mi.scoped_set_variant(self.variant):
            scene, p = self._scene, self._params
            # directional: light travels along the emitter's local +z, i.e. along -wi
            p["lamp.to_world"] = mi.Transform4f(_frame([0.0, 0.0, 0.0], -wi, up))
            p["sensor.to_world"] = mi.Transform4f(_frame(_DISTANCE * wo, -wo, up, self.half_width))
            p.update()
            img = mi.render(scene, spp=self.spp, seed=0)
            out = np.array(img, dtype=np.float64)[..., :3]
        self.renders += 1
        return out

    def open_beam(self, radiance: float, wo, up) -> np.ndarray:
        """The open-beam frame (ASTM E2387): the sample out of the holder, the lamp straight
        behind the aperture, seen from ``wo`` (the rear detector on the beam's axis).

        The camera sees the lamp's exit through the sample's empty aperture at ``radiance``
        (sr^-1 per unit irradiance at the sample: the beam's attenuation over its solid
        angle) and nothing else (an orthographic camera, so the aperture's image does not
        depend on the distance to the lamp). Returns (height, width, 3) radiance.
        """
        return self.aperture(wo, up) * float(radiance)

    def aperture(self, wo, up) -> np.ndarray:
        """How much of each pixel the sample's aperture fills, seen from ``wo`` below the
        surface (a unit-radiance square facing the rear), (height, width, 3)."""
        import mitsuba as mi

        wo = np.asarray(wo, float)
        up = np.asarray(up, float)
        with mi.scoped_set_variant(self.variant):
            if self._beam is None:
                T = mi.ScalarTransform4f
                flip = T().rotate([1.0, 0.0, 0.0], 180.0)        # the exit faces the rear (-z)
                base = self._base(mi)
                base.pop("lamp")
                self._beam = mi.load_dict({**base, "aperture": {
                    "type": "rectangle", "to_world": self._square(mi, -self._layout[1]) @ flip,
                    "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}})
            p = mi.traverse(self._beam)
            p["sensor.to_world"] = mi.Transform4f(_frame(_DISTANCE * wo, -wo, up, self.half_width))
            p.update()
            img = mi.render(self._beam, spp=self.spp, seed=0)
            out = np.array(img, dtype=np.float64)[..., :3]
        self.renders += 1
        return out
