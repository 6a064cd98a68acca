"""Model selection: model only what the data needs.

Every candidate is fitted with one loss and ranked by the Bayesian information criterion
BIC = -2 ln L + k ln n (Schwarz 1978) of that same loss (:attr:`FitResult.bic`: chi^2 for the
chi2 loss, the profiled Gaussian likelihood of the log or cosine residuals, the discrepancy
likelihood). Among the candidates whose BIC lies within
``delta`` of the best, the one with the fewest parameters wins: by Kass & Raftery (1995,
sec. 3.2) a BIC difference below 2 is "not worth more than a bare mention", so the data gives
no reason to prefer the more complex model.
"""

from __future__ import annotations

import dataclasses

import numpy as np

import gonio.models as gm
from gonio.core.sides import Side, side_of

from gonio.fitting.optimise.mle import fit

__all__ = ["CANDIDATES", "Ranked", "option_candidates", "select", "candidates_for"]

#: (name, options) tried by ``--model auto``, simplest first (fewest parameters): every
#: registered model that does not declare ``auto_candidate = False`` (the model declares,
#: selection reads: a new model file in gonio.models is a candidate without edits here).
#: Every microfacet distribution a model declares (``OPTIONS["distribution"]``) is a
#: candidate of its own: a Beckmann conductor is not "explained" by another model.
def _candidates(names=None):
    out = []
    for name in names or gm.names():
        try:
            model = gm.get(name)
        except (KeyError, ValueError):
            continue
        cls = type(model)
        if names is None and not getattr(cls, "auto_candidate", True):
            continue
        k = sum(3 if p.per_channel else 1 for p in model.parameters)
        for dist in cls.OPTIONS.get("distribution", (None,)):
            out.append((k, name, {} if dist is None else {"distribution": dist}))
    return tuple((name, opts) for _, name, opts in sorted(out, key=lambda t: (t[0], t[1])))


CANDIDATES = _candidates()


def _transmission_candidates():
    """Every registered model that scatters through the surface (``Structure.sides`` holds
    transmission) with a finite f (``delta`` models, the smooth dielectrics, are left out),
    one per declared distribution: roughdielectric beckmann and ggx, difftrans."""
    names = []
    for name in gm.names():
        try:
            model = gm.get(name)
        except (KeyError, ValueError):
            continue
        if Side.TRANSMIT in tuple(model.structure.sides) and not getattr(type(model), "delta", False):
            names.append(name)
    return _candidates(names) if names else ()


def candidates_for(meas):
    """The ``--model auto`` candidates for ``meas``: `CANDIDATES` for a BRDF; the transmission
    models when any used point lies on the transmitted side (a reflection model predicts 0
    there, so it cannot explain those points and is not offered)."""
    used = np.asarray(meas.use).any(axis=1)
    side = side_of(np.asarray(meas.wi)[used, 2], np.asarray(meas.wo)[used, 2])
    return _transmission_candidates() if np.any(side == 1) else CANDIDATES


def option_candidates(name, options=None):
    """The candidates a named model stands for: one per declared microfacet distribution
    when ``options`` does not choose one (so that ``--model roughplastic`` on a GGX sample
    is not silently fitted as Beckmann), else just ``(name, options)``."""
    options = dict(options or {})
    allowed = type(gm.get(name, **options)).OPTIONS.get("distribution")
    if not allowed or "distribution" in options:
        return ((name, options),)
    return tuple((name, {**options, "distribution": d}) for d in allowed)


@dataclasses.dataclass
class Ranked:
    name: str
    options: dict
    k: int
    chi2: float
    bic: float
    delta_bic: float
    chosen: bool
    result: object = dataclasses.field(repr=False, default=None)
    loss: str = "chi2"
    neg2_loglik: float = 0.0
    delta_e: float | None = None      # rendered difference in the default scene (fitting.scene.rendered_choice)
    noise: float | None = None        # ... and its noise floor

    def row(self) -> dict:
        row = {"model": self.name, "options": self.options, "k": self.k, "chi2": self.chi2, "loss": self.loss,
               "neg2_loglik": self.neg2_loglik, "bic": self.bic, "delta_bic": self.delta_bic, "chosen": self.chosen}
        if self.delta_e is not None:
            row.update(delta_e=self.delta_e, noise=self.noise)
        return row


def _nested_start(model, rows):
    """A model that contains a simpler candidate already fitted (a two-lobe model and its
    single layer, ``start_from``) starts from that fit: a nested model must fit at least as
    well as the model it contains."""
    layer = getattr(model, "_layer", None)
    if not hasattr(model, "start_from") or layer is None:
        return None
    for r in rows:
        if r.name == layer.name and dict(r.result.model.options) == dict(layer.options):
            return model.start_from(r.result.params)
    return None


def select(meas, *, rng, candidates=None, delta: float = 2.0, progress=None, **fit_kwargs):
    """Fit each candidate and pick the simplest one the data supports.

    ``progress``: called as ``progress(done, total, label)`` before each candidate's fit and
    once at the end (a terminal's bar: gonio/cli/progress.py); None says nothing.

    Returns
    -------
    best : FitResult
    ranking : list of Ranked
        Sorted by BIC, the chosen one flagged.
    """
    rows = []
    todo = tuple(candidates or candidates_for(meas))
    for k, (name, options) in enumerate(todo):
        if progress is not None:
            progress(k, len(todo), f"{name} {' '.join(map(str, options.values()))}".strip())
        try:
            model = gm.get(name, **options)
        except (KeyError, ValueError):
            continue  # a candidate this build of gonio.models does not provide
        result = fit(meas, model, rng=rng, start=_nested_start(model, rows), **fit_kwargs)
        rows.append(Ranked(name, dict(options), result.space.size, result.chi2, result.bic, 0.0, False, result,
                           result.loss, result.neg2_loglik))
    if progress is not None:
        progress(len(todo), len(todo), "candidates fitted")
    if not rows:
        raise ValueError("no candidate model could be fitted")
    best_bic = min(r.bic for r in rows)
    for r in rows:
        r.delta_bic = r.bic - best_bic
    supported = [r for r in rows if r.delta_bic <= delta]
    chosen = min(supported, key=lambda r: (r.k, r.bic))
    chosen.chosen = True
    rows.sort(key=lambda r: r.bic)
    return chosen.result, rows


