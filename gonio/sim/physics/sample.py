"""Virtual samples: resolve a sample spec to a Mitsuba BSDF dict and its true f_r.

A sample spec is one of

``{"model": NAME, "options": {...}, "params": {...}}``
    a gonio model, ``gonio.models.get(NAME, **options)``; rendered through
    ``model.to_mitsuba(params)``, truth ``model.eval(wi, wo, params)``.
``{"bsdf_file": PATH}``
    measured data through Mitsuba's ``measured`` plugin (RGL-EPFL ``.bsdf``).
``{"mitsuba": DICT}``
    any Mitsuba BSDF dict (tests, quick experiments).

For the Mitsuba-only specs the truth is ``bsdf.eval`` divided by cos(theta_i), evaluated in
gonio's convention through :func:`gonio.models.mitsuba.eval_cos` (the one boundary).
"""

from __future__ import annotations

import copy
import json
import os

import numpy as np

import gonio.models as gm
from gonio.core.channels import CHANNELS
from gonio.core.sides import Side
from gonio.models.mitsuba import eval_cos, mitsuba_variant

__all__ = ["SampleTruth", "mitsuba_variant", "resolve_sample"]

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
        if "model" in spec:
            name = spec["model"]
            options = dict(spec.get("options", {}))
            params = dict(spec.get("params", {}))
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
                self.mitsuba = model.to_mitsuba(params)
                self._eval = lambda wi, wo, m=model, p=params: np.asarray(m.eval(wi, wo, p), float)
        elif "bsdf_file" in spec:
            path = os.fspath(spec["bsdf_file"])
            if not os.path.exists(path):
                raise FileNotFoundError(path)
            self.mitsuba = {"type": "measured", "filename": path}
        elif "mitsuba" in spec:
            self.mitsuba = copy.deepcopy(spec["mitsuba"])
        else:
            raise ValueError("a sample spec needs 'model', 'bsdf_file' or 'mitsuba'")

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
        ok = Side.REFLECT.mask(cos_i, wo[:, 2])
        return np.where(ok[:, None], out / np.where(ok, cos_i, 1.0)[:, None], 0.0)


def resolve_sample(spec: dict) -> SampleTruth:
    """Resolve a sample spec (see module docstring)."""
    return SampleTruth(spec)
