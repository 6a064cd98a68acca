"""Model selection: model only what the data needs.

Every candidate is fitted by maximum likelihood and ranked by the Bayesian information
criterion BIC = chi^2 + k ln n (Schwarz 1978). Among the candidates whose BIC lies within
``delta`` of the best, the one with the fewest parameters wins: by Kass & Raftery (1995,
sec. 3.2) a BIC difference below 2 is "not worth more than a bare mention", so the data gives
no reason to prefer the more complex model.
"""

from __future__ import annotations

import dataclasses



from ._optimise import fit

__all__ = ["CANDIDATES", "Ranked", "select"]

#: (name, options) tried by ``--model auto``, simplest first.
CANDIDATES = (
    ("diffuse", {}),
    ("roughplastic", {"distribution": "ggx"}),
    ("roughplastic", {"distribution": "beckmann"}),
    ("roughconductor", {"distribution": "ggx"}),
    ("cooktorrance", {}),
)


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

    def row(self) -> dict:
        return {"model": self.name, "options": self.options, "k": self.k, "chi2": self.chi2,
                "bic": self.bic, "delta_bic": self.delta_bic, "chosen": self.chosen}


def select(meas, *, rng, candidates=None, delta: float = 2.0, **fit_kwargs):
    """Fit each candidate and pick the simplest one the data supports.

    Returns
    -------
    best : FitResult
    ranking : list of Ranked
        Sorted by BIC, the chosen one flagged.
    """
    import gonio.models as gm

    rows = []
    for name, options in candidates or CANDIDATES:
        try:
            model = gm.get(name, **options)
        except (KeyError, ValueError):
            continue  # a candidate this build of gonio.models does not provide
        result = fit(meas, model, rng=rng, **fit_kwargs)
        rows.append(Ranked(name, dict(options), result.space.size, result.chi2, result.bic, 0.0, False, result))
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


