"""The sequential plans' family choice: which model a capture's data need.

A lab does not know the sample's family before it measures. :func:`choose_cv` picks, among
candidate families (:data:`FAMILIES`), the one that predicts held-out points best over the
evaluation measure (importance-weighted cross-validation); `gonio perf acquisition --model
choose` applies it to every plan's final data, the dense grid's included, so each plan is scored
on the family its own data chose. ``[strategy] candidates`` (default ``[]``: the plan's ``model`` alone) lets a
sequential plan choose before each batch too, by BIC (:func:`choose`: the simplest within 2 of
the best, `gonio.fitting.selection.by_data.select`; Schwarz 1978, Kass & Raftery 1995), and
place the batch for that family. Public: `FAMILIES`, `FOLDS`, `parse`, `as_doc`, `choose`,
`choose_cv`, `label`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["FAMILIES", "FOLDS", "parse", "as_doc", "choose", "choose_cv", "label"]

#: :func:`choose_cv`'s folds
FOLDS = 5

#: the default candidates, simplest first: a plastic (diffuse body and a GGX coat), a GGX
#: conductor (coloured Fresnel, no body), Cook-Torrance (a body and a coloured Beckmann lobe)
#: and Disney's principled GGX (metallic, sheen, clear coat)
FAMILIES: tuple[tuple[str, dict], ...] = (("roughplastic", {"distribution": "ggx"}),
                                          ("roughconductor", {"distribution": "ggx"}),
                                          ("cooktorrance", {}),
                                          ("principled", {"distribution": "ggx"}))


def label(name: str, options: dict) -> str:
    """``name`` with its distribution, as a row says it: ``roughplastic:ggx``."""
    dist = dict(options or {}).get("distribution")
    return f"{name}:{dist}" if dist else str(name)


def parse(value: Any) -> tuple[tuple[str, dict], ...]:
    """``[strategy] candidates`` (a list of ``{model = NAME, options = {...}}`` tables, or of
    ``"NAME"`` / ``"NAME:DISTRIBUTION"`` strings) as ``((name, options), ...)``, simplest first
    (fewest parameters; ties by name); ValueError, one line, for what is not a known model."""
    import gonio.models as gm

    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
        raise ValueError(f"[strategy] candidates = {str(value)[:40]!r}: give a list of model names "
                         "(e.g. [\"roughplastic:ggx\", \"cooktorrance\"]), or [] for the plan's model alone")
    out = []
    for item in value:
        if isinstance(item, str):
            name, _, dist = item.partition(":")
            options = {"distribution": dist} if dist else {}
        elif isinstance(item, dict) and set(item) <= {"model", "options"} and isinstance(item.get("options", {}), dict):
            name, options = item.get("model"), dict(item.get("options", {}))
        else:
            raise ValueError(f"[strategy] candidates: {str(item)[:40]!r} is not a model name or a "
                             "{model, options} table")
        try:
            model = gm.get(str(name), **options)
        except Exception as exc:
            raise ValueError(f"[strategy] candidates: {str(name)[:40]!r}: {str(exc)[:80]}") from None
        out.append((sum(3 if p.per_channel else 1 for p in model.parameters), str(name), dict(options)))
    if len({(n, tuple(sorted(o.items()))) for _, n, o in out}) < len(out):
        raise ValueError("[strategy] candidates: a model is named twice")
    return tuple((n, o) for _, n, o in sorted(out, key=lambda t: (t[0], t[1])))


def as_doc(candidates) -> list[dict]:
    """session.toml's form of :func:`parse`'s result (it reads it back)."""
    return [{"model": n, "options": dict(o)} for n, o in candidates]


def choose(meas, candidates, *, rng: np.random.Generator, **fit_kwargs):
    """The simplest of ``candidates`` whose BIC is within 2 of the best on ``meas``
    (`gonio.fitting.selection.by_data.select` with ``delta = 2``): ``(result, ranking)``.
    ``fit_kwargs`` go to each candidate's fit (starts, loss)."""
    from gonio.fitting.selection.by_data import select

    values = int(np.asarray(meas.use).sum())
    fits = [c for c in candidates if _size(*c) < values]     # a fit needs more values than parameters
    if not fits:
        raise ValueError(f"{values} measured values: too few to fit any candidate family")
    return select(meas, rng=rng, candidates=tuple(fits), delta=2.0, **fit_kwargs)


def _size(name: str, options: dict) -> int:
    import gonio.models as gm

    return sum(3 if p.per_channel else 1 for p in gm.get(name, **options).parameters)


def choose_cv(meas, candidates, *, seed: int, folds: int = FOLDS, **fit_kwargs):
    """The candidate that predicts held-out points best over the evaluation measure:
    ``(name, options, scores)``. BIC assumes the family is right; where none is and the data
    are precise, it keeps whichever family bends closest to the points measured, however it
    does between them. Here each candidate is fitted ``folds`` times, each time without one
    fold (a seeded permutation, ``default_rng([seed, 53])``), and scored on the points left
    out: Ngan's relative error of f_r cos(theta_i) and the log error (gonio.perf.real.metrics'
    forms), each point weighted by its design weight, its share of the measure those errors
    integrate (gonio.bench.plan.design_weights): importance-weighted cross-validation (Sugiyama,
    Krauledat & Mueller 2007, JMLR 8: 985-1005). The least sum of the two errors, each over its
    best, wins; ties go to the simpler. ``scores``: (name, Ngan, log) per candidate."""
    import gonio.models as gm

    from gonio.bench.plan.design_weights import design_weights
    from gonio.fitting.optimise.mle import fit

    n = meas.n_points
    if n < 2 * folds:
        raise ValueError(f"{n} points: too few for {folds}-fold cross-validation")
    w = design_weights(meas.wi, meas.wo)[:, None] * np.ones(meas.brdf.shape)
    fold = np.random.default_rng([int(seed), 53]).permutation(n) % folds
    cos_i = np.clip(np.asarray(meas.wi)[:, 2:3], 0.0, 1.0)
    rows = []
    for k, (name, options) in enumerate(candidates):
        model = gm.get(name, **options)
        pred = np.full(meas.brdf.shape, np.nan)
        for j in range(folds):
            out = fold == j
            res = fit(meas.subset(np.flatnonzero(~out)), model, rng=np.random.default_rng([int(seed), 54, k, j]),
                      covariance=False, **fit_kwargs)
            pred[out] = np.asarray(model.eval(meas.wi[out], meas.wo[out], res.params), float)
        use = np.asarray(meas.use, bool) & np.isfinite(pred) & np.isfinite(meas.brdf)
        d, m = np.where(use, (pred - meas.brdf) * cos_i, 0.0), np.where(use, meas.brdf * cos_i, 0.0)
        ngan = float(np.sqrt(np.sum(w * d ** 2) / np.sum(w * m ** 2)))
        lm = np.log1p(np.maximum(np.where(use, pred, 0.0) * cos_i, -0.999))
        lerr = float(np.sqrt(np.sum(w * use * (lm - np.log1p(np.maximum(m, -0.999))) ** 2) / np.sum(w * use)))
        rows.append((name, options, ngan if use.any() else np.inf, lerr if use.any() else np.inf))
    best_n, best_l = min(r[2] for r in rows), min(r[3] for r in rows)
    score = [r[2] / best_n + r[3] / best_l for r in rows]
    k = int(np.argmin(score))           # candidates come simplest first: argmin keeps the first of a tie
    return rows[k][0], dict(rows[k][1]), [(label(r[0], r[1]), r[2], r[3]) for r in rows]
