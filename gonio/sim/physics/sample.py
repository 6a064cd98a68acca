"""Virtual samples: resolve a sample spec to a Mitsuba BSDF dict and its true f_r.

A sample spec is one of

``{"model": NAME, "options": {...}, "params": {...}}``
    a gonio model, ``gonio.models.get(NAME, **options)``; rendered through
    ``model.to_mitsuba(params)``, truth ``model.eval(wi, wo, params)``.
``{"bsdf_file": PATH}``
    measured data through Mitsuba's ``measured`` plugin (RGL-EPFL ``.bsdf``).
``{"mitsuba": DICT}``
    any Mitsuba BSDF dict (tests, quick experiments).
"""

# For the Mitsuba-only specs the truth is ``bsdf.eval`` divided by cos(theta_i), evaluated in
# gonio's convention through :func:`gonio.models.mitsuba.eval_cos` (the one boundary).
# A transmissive model (``Structure.sides`` holds transmission) may give ``params.ext_ior``
# (the truth uses eta = int_ior / ext_ior) and a ``slab`` table (a frosted front face on a
# polished back: :func:`slab_exit`, the second surface to first order).

from __future__ import annotations

import copy
import json
import os

import numpy as np

import gonio.models as gm
from gonio.core.channels import CHANNELS
from gonio.core.sides import Side, parse_sides, sides_mask
from gonio.models.mitsuba import eval_cos, mitsuba_variant
from gonio.models.physics.fresnel import fresnel_dielectric

__all__ = ["SampleTruth", "mitsuba_variant", "resolve_sample", "slab_exit", "at_wavelength"]


def at_wavelength(spec: dict, nm: float) -> dict:
    """The sample spec under monochromatic light at ``nm``: each parameter a ``spectra`` table
    gives (`gonio.bench.samples`: wavelengths in nm, values) interpolated linearly there, a
    per-channel parameter without a spectrum its channels' mean, both as three equal channels
    (a grey sample that renders f_r at ``nm``); a spec that is not a gonio model, unchanged."""
    if "model" not in spec:
        return copy.deepcopy(spec)
    out = copy.deepcopy(spec)
    spectra = spec.get("spectra") or {}
    params = out.setdefault("params", {})
    for name, value in list(params.items()):
        if name in spectra:
            w, v = (np.asarray(spectra[name][k], float) for k in ("wavelengths", "values"))
            params[name] = [float(np.interp(float(nm), w, v))] * CHANNELS
        elif isinstance(value, (list, tuple)) and len(value) == CHANNELS:
            params[name] = [float(np.mean(value))] * CHANNELS
    return out

_SLAB_KEYS = {"thickness_mm", "back", "absorption_per_mm"}


def slab_exit(wo, eta, thickness_mm=0.0, absorption_per_mm=0.0):
    """The polished back face of a slab of relative index ``eta``, to first order.

    Light reaching the back face inside the slab along ``wg`` leaves it into the exterior along
    ``wo`` (``wo[:, 2] < 0``, Snell: sin theta_g = sin theta_o / eta, same azimuth). Radiance
    across a smooth interface scales by its Fresnel transmittance and (n_out / n_in)^2
    (the radiance theorem: L / n^2 is kept, Nicodemus 1963; Veach 1997 eq. 5.9), and Beer's law
    takes exp(-kappa d / cos theta_g) along the path through the thickness d, so

        f_slab(wi, wo) = f_front(wi, wg) * (1 - F(cos theta_o, eta)) / eta^2 * exp(-kappa d / cos theta_g)

    (F is symmetric across the interface: Fresnel's reflectance at theta_o from outside equals it at
    theta_g from inside). Left out: light the back face reflects (F, about 4 % at eta 1.5) and
    the front face sends back down (second order, F times the front's internal reflectance), and
    the exit spot's lateral shift d tan theta_g (uniform illumination: only the square's rim).

    Returns
    -------
    wg : ndarray (N, 3)
        The direction inside the slab (toward the back face) that leaves along ``wo``.
    factor : ndarray (N,)
        The factor above; 0 where no light leaves (total internal reflection when eta < 1).
    """
    wo = np.atleast_2d(np.asarray(wo, dtype=float))
    s_o = np.hypot(wo[:, 0], wo[:, 1])
    s_g = s_o / eta
    ok = (wo[:, 2] < 0.0) & (s_g < 1.0)
    c_g = np.sqrt(np.clip(1.0 - s_g * s_g, 0.0, 1.0))
    scale = np.where(s_o > 0.0, s_g / np.where(s_o > 0.0, s_o, 1.0), 0.0)
    wg = np.stack([wo[:, 0] * scale, wo[:, 1] * scale, -c_g], axis=1)
    F = fresnel_dielectric(np.abs(wo[:, 2]), eta)[0]
    path = float(absorption_per_mm) * float(thickness_mm) / np.where(c_g > 0.0, c_g, 1.0)
    factor = np.where(ok, (1.0 - F) / (eta * eta) * np.exp(-path), 0.0)
    return wg, factor


def _slab(spec_slab, eta) -> dict | None:
    if spec_slab is None:
        return None
    if not isinstance(spec_slab, dict) or set(spec_slab) - _SLAB_KEYS:
        raise ValueError(f"sample slab: a table of {', '.join(sorted(_SLAB_KEYS))}")
    back = spec_slab.get("back", "smooth")
    if back != "smooth":
        raise ValueError(f"sample slab: back must be 'smooth' (a polished face), not {str(back)[:20]!r}")
    d = float(spec_slab.get("thickness_mm", 1.0))
    k = float(spec_slab.get("absorption_per_mm", 0.0))
    if not (np.isfinite(d) and d >= 0.0 and np.isfinite(k) and k >= 0.0):
        raise ValueError("sample slab: thickness_mm and absorption_per_mm must be finite and >= 0")
    return {"thickness_mm": d, "absorption_per_mm": k, "eta": float(eta)}

def _diffuse_fallback(params: dict) -> tuple[dict, callable]:
    rho = np.broadcast_to(np.asarray(params.get("reflectance", 0.5), dtype=float), (CHANNELS,)).copy()

    def eval_(wi, wo):
        ok = Side.REFLECT.mask(wi[:, 2], wo[:, 2])
        return np.where(ok[:, None], rho[None, :] / np.pi, 0.0)

    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho.tolist()}}, eval_


class SampleTruth:
    """A resolved sample: Mitsuba dict for rendering, exact f_r for tests.

    Parameters
    ----------
    spec : dict
        Sample spec (module docstring).
    """

    def __init__(self, spec: dict):
        if not isinstance(spec, dict):
            raise TypeError("a sample spec is a dict")
        self.spec = copy.deepcopy(spec)
        self._bsdf = None
        self._eval = None
        self.sides = parse_sides(spec.get("sides", "reflect"), "sample spec")
        self.slab = None
        if "model" in spec:
            name = spec["model"]
            options = dict(spec.get("options", {}))
            params = dict(spec.get("params", {}))
            if "ext_ior" in params:               # Mitsuba's pair of indices -> gonio's ratio
                ext = float(params.pop("ext_ior"))
                if not (np.isfinite(ext) and ext > 0.0):
                    raise ValueError("sample params: ext_ior must be finite and > 0")
                params["int_ior"] = float(params.get("int_ior", 1.5)) / ext
            try:
                get = gm.get
            except (ImportError, AttributeError):
                get = None
            if get is None:
                if name != "diffuse":
                    raise RuntimeError(f"gonio.models is not available to resolve model {name!r}")
                self.mitsuba, self._eval = _diffuse_fallback(params)
            else:
                model = get(name, **options)
                self.sides = tuple(model.structure.sides)
                self.mitsuba = model.to_mitsuba(params)
                self._eval = lambda wi, wo, m=model, p=params: np.asarray(m.eval(wi, wo, p), float)
                if "slab" in spec:
                    if Side.TRANSMIT not in self.sides or "int_ior" not in params:
                        raise ValueError(f"sample slab: model {name!r} does not transmit through an interface")
                    self.slab = _slab(spec["slab"], params["int_ior"])
                    self._eval = self._slab_eval(self._eval)
        elif "bsdf_file" in spec:
            path = os.fspath(spec["bsdf_file"])
            if not os.path.exists(path):
                raise FileNotFoundError(path)
            self.mitsuba = {"type": "measured", "filename": path}
        elif "mitsuba" in spec:
            self.mitsuba = copy.deepcopy(spec["mitsuba"])
        else:
            raise ValueError("a sample spec needs 'model', 'bsdf_file' or 'mitsuba'")

    def _slab_eval(self, front):
        sl = self.slab

        def eval_(wi, wo):
            out = np.array(front(wi, wo), dtype=float)
            t = wo[:, 2] < 0.0
            if t.any():
                wg, fac = slab_exit(wo[t], sl["eta"], sl["thickness_mm"], sl["absorption_per_mm"])
                out[t] = front(wi[t], wg) * fac[:, None]
            return out

        return eval_

    @property
    def transmits(self) -> bool:
        """Whether the sample sends light through (its sides hold transmission)."""
        return Side.TRANSMIT in self.sides

    def to_json(self) -> str:
        """The spec as JSON (for a dataset's ``sample_truth`` attribute)."""
        return json.dumps(self.spec, sort_keys=True, default=str)

    def eval(self, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """True f_r (sr^-1), shape (N, 3), for unit directions (N, 3) in the sample frame."""
        wi = np.atleast_2d(np.asarray(wi, dtype=float))
        wo = np.atleast_2d(np.asarray(wo, dtype=float))
        if self._eval is not None:
            return self._eval(wi, wo)
        return self._mitsuba_eval(wi, wo)

    def _mitsuba_eval(self, wi, wo):
        import mitsuba as mi

        variant = mitsuba_variant()
        with mi.scoped_set_variant(variant):
            if self._bsdf is None:
                self._bsdf = mi.load_dict(self.mitsuba)
        out = eval_cos(self._bsdf, wi, wo, variant)
        cos_i = wi[:, 2]
        ok = sides_mask(self.sides, cos_i, wo[:, 2])
        return np.where(ok[:, None], out / np.where(ok, cos_i, 1.0)[:, None], 0.0)


def resolve_sample(spec: dict) -> SampleTruth:
    """Resolve a sample spec (see module docstring)."""
    return SampleTruth(spec)
