"""`TwoLobe`: a model made of two layers of one single-lobe model that differ only in roughness.

    f_r = (1 - w) layer(common, alpha) + w layer(common, alpha2)

is exactly Mitsuba's ``blendbsdf`` of the two layers (:meth:`TwoLobe.to_mitsuba`), so the model
renders through the layer's plugins and matches Mitsuba wherever the layer does; a convex
combination of two energy-conserving BRDFs conserves energy, and the albedo is the same
combination of the layers' albedos. A subclass names its layer model (``LAYER``), the
parameters the two layers share (``COMMON``), and declares its parameters (``alpha``,
``alpha2`` and ``weight`` among them). Used by ``roughconductor2`` and ``roughplastic2``.
"""

from __future__ import annotations

import numpy as np

from gonio.models.base import Model, eval_dtype, eval_inputs
from gonio.models.structure import Structure

__all__ = ["TwoLobe"]


class TwoLobe(Model):
    """Two layers of ``LAYER`` sharing ``COMMON``, roughness ``alpha`` and ``alpha2``, mixed by ``weight``."""

    LAYER: type[Model]
    COMMON: tuple[str, ...]

    def __init__(self, **options):
        super().__init__(**options)
        self._layer = self.LAYER(distribution=self.options["distribution"])

    @property
    def structure(self):
        return Structure()  # evaluates through the layer's own (compiled) path; no kernel of its own

    def layers(self, p):
        """The two layers' parameter sets and the second one's weight."""
        common = {k: p[k] for k in self.COMMON}
        return dict(common, alpha=p["alpha"]), dict(common, alpha=p["alpha2"]), float(p["weight"])

    def _mix(self, fn, wi, wo, params, dtype=np.float64):
        wi, wo, p = eval_inputs(self, wi, wo, params, dtype)
        p1, p2, w = self.layers(p)
        a = fn(wi, wo, p1) if w < 1.0 else 0.0
        b = fn(wi, wo, p2) if w > 0.0 else 0.0
        return np.asarray((1.0 - w) * a + w * b, dtype=dtype) + np.zeros((wi.shape[0], self.n_channels(p)), dtype)

    def eval(self, wi, wo, params, backend="auto"):
        """The two layers' ``eval`` mixed; float32 directions give float32 (each layer's
        float32 path, mixed in float32; ``backend="numpy"``: the float64 reference rounded
        to float32), as :meth:`Model.eval`."""
        if backend not in ("auto", "numpy", "drjit"):
            raise ValueError(f"backend={backend!r}: give 'auto', 'numpy' or 'drjit'")
        if backend == "numpy":  # the float64 reference, rounded once (as Model.eval)
            return self.eval_reference(wi, wo, params).astype(eval_dtype(wi, wo), copy=False)
        return self._mix(lambda a, b, p: self._layer.eval(a, b, p, backend=backend), wi, wo, params,
                         eval_dtype(wi, wo))

    def eval_reference(self, wi, wo, params):
        return self._mix(self._layer.eval_reference, wi, wo, params)

    def _eval(self, wi, wo, p):
        p1, p2, w = self.layers(p)
        return (1.0 - w) * self._layer._eval(wi, wo, p1) + w * self._layer._eval(wi, wo, p2)

    def albedo(self, wo, params, **quadrature):
        """The weighted sum of the two layers' albedos (each by the layer's own quadrature)."""
        p1, p2, w = self.layers(self.validate(params))
        out = [self._layer.albedo(wo, q, **quadrature) for q in (p1, p2)]
        if quadrature.get("return_error"):
            return (1.0 - w) * out[0][0] + w * out[1][0], np.maximum(out[0][1], out[1][1])
        return (1.0 - w) * out[0] + w * out[1]

    def start_from(self, layer_params):
        """A start next to a fit of the single layer (``layer_params``): that layer as the first
        lobe, a second lobe three times as rough carrying 10 % of the weight. The two-lobe
        model contains the one-lobe one (weight 0), so from here its fit can only improve on
        the layer's; from the declared defaults it may not find that basin (roughconductor2 on
        an RGL paint ended at 1.2-1.8x the one-lobe model's Ngan error)."""
        p = dict(self._layer.validate(layer_params))
        alpha = float(p.pop("alpha"))
        return dict({k: p[k] for k in self.COMMON}, alpha=alpha, alpha2=min(1.0, 3.0 * alpha), weight=0.1)

    def to_mitsuba(self, params):
        p1, p2, w = self.layers(self.validate(params))
        return {"type": "blendbsdf", "weight": w, "lobe1": self._layer.to_mitsuba(p1),
                "lobe2": self._layer.to_mitsuba(p2)}
