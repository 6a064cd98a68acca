"""Mitsuba scene of the sample holder, built once and re-posed per stage pose.

Everything is expressed in the sample's local frame (z = 0 the holder plane, +z the normal):
the geometry never moves, only the ``directional`` emitter (light arriving from ``wi``) and
the ``orthographic`` sensor (looking along ``-wo``, image right/up from the kinematics) are
updated through ``mi.traverse``, so kernels compile once.

The emitter has unit irradiance on a surface facing it, so the rendered radiance on a flat
square is ``f_r(wi, wo) * cos(theta_i)`` (sr^-1); the ``direct`` integrator with a delta
light makes it exact, with no Monte Carlo noise, away from the squares' edges.
"""

from __future__ import annotations

import numpy as np

from gonio.models.mitsuba import mitsuba_variant

from gonio.sim.physics.holder_markers import holder_transform, marker_shapes

__all__ = ["HolderScene"]

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


class HolderScene:
    """The holder (sample square, reference square, dark plate) seen by the camera.

    Parameters
    ----------
    sample_bsdf, reference_bsdf : dict
        Mitsuba BSDF dicts.
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
                 holder_reflectance: float, spp: int = 4, markers=None, holder_pose=None):
        import mitsuba as mi

        self.variant = mitsuba_variant()
        self.width, self.height = int(width), int(height)
        self.half_width = 0.5 * self.width * float(pixel_size)
        self.spp = int(spp)
        with mi.scoped_set_variant(self.variant):
            T = mi.ScalarTransform4f

            pose = holder_transform(T, holder_pose)

            def square(cx):
                return pose @ T().translate([cx, 0.0, _SQUARE_LIFT]) @ T().scale([sample_half, sample_half, 1.0])

            scene = {
                "type": "scene",
                "integrator": {"type": "direct"},
                "sensor": {
                    "type": "orthographic",
                    "film": {"type": "hdrfilm", "width": self.width, "height": self.height,
                             "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                    "sampler": {"type": "independent", "sample_count": self.spp},
                },
                "lamp": {"type": "directional", "irradiance": {"type": "rgb", "value": 1.0}},
                "sample": {"type": "rectangle", "to_world": square(-offset), "bsdf": sample_bsdf},
                "reference": {"type": "rectangle", "to_world": square(offset), "bsdf": reference_bsdf},
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
        self.renders = 0

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
        with mi.scoped_set_variant(self.variant):
            p = self._params
            # directional: light travels along the emitter's local +z, i.e. along -wi
            p["lamp.to_world"] = mi.Transform4f(_frame([0.0, 0.0, 0.0], -wi, up))
            p["sensor.to_world"] = mi.Transform4f(_frame(_DISTANCE * wo, -wo, up, self.half_width))
            p.update()
            img = mi.render(self._scene, spp=self.spp, seed=0)
            out = np.array(img, dtype=np.float64)[..., :3]
        self.renders += 1
        return out
