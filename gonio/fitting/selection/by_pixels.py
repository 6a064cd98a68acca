"""``--model auto``'s rendered check, cheaply: every candidate's pixels from the scene's own pairs.

The default scene's pixels that see the sample are found once, with ``k`` light samples each
(:func:`gonio.fitting.selection.scene_fit.scene_pixels`); the measured material's pixels and
every fitted candidate's are then sums of f_r cos over those same pairs (common random numbers),
so a candidate costs one ``model.eval``, not a render. Two independent sets of pairs give each
difference and its noise (half their spread). In :func:`pixel_choice` the candidates, not
degenerate (:func:`degenerate`), whose difference is within
``tolerance`` of the closest candidate's keep their place (none renders visibly better), and
the data's evidence (BIC) chooses among them. Where no candidate comes within ``threshold`` of
the measured material, ``fallback`` (the data-driven tabulated fit) is tried too.
"""

# Tolerance: a mean CIEDE2000 of 0.5 is half the threshold of a just-noticeable difference
# (Sharma, Wu & Dalal 2005 give 1 as the order of a JND), so a candidate within 0.5 of the best
# does not render visibly worse. Degenerate (issue 35): a non-colour parameter at its box bound
# (a conductor's k at its limit, a roughness at its floor, a second lobe's weight at 0 or 1),
# or a roughness below the finest angular step the data can resolve (MIN_ALPHA: a lobe
# narrower than about 1 deg). A weight such as principled's metallic or sheen at 0 is a
# material, not an edge.

from __future__ import annotations

import time

import numpy as np

from gonio.models.mitsuba import select_variant

from gonio.fitting.render.preview import delta_e_2000

__all__ = ["PixelCheck", "degenerate", "pixel_choice", "MIN_ALPHA", "PINNED", "THRESHOLD", "TOLERANCE"]

#: a roughness below this is a lobe narrower than the data's angular resolution (~1 deg)
MIN_ALPHA = 0.01
#: chosen: the simplest candidate within this mean CIEDE2000 of the closest one
TOLERANCE = 0.5
#: the fallback and a refinement are tried only where no candidate renders within this (a JND)
THRESHOLD = 1.0
#: parameters whose box bound is not a material but the optimiser's edge: a conductor's eta and
#: k, an index of refraction, a roughness, a second lobe's weight (0 or 1: the lobe unused)
PINNED = ("eta", "k", "int_ior", "alpha", "alpha2", "alpha_u", "alpha_v", "roughness", "weight")


def degenerate(result) -> list:
    """What makes ``result`` degenerate, one string a parameter: a :data:`PINNED` parameter at
    its box bound, or a roughness below :data:`MIN_ALPHA`. Empty: a proper fit."""
    space = result.space
    out = []
    pinned = space.at_bound(result.x, rtol=1e-4)
    for e, x, at in zip(space.entries, result.x, pinned):
        if e.param.startswith(("alpha", "roughness")) and x < MIN_ALPHA:
            out.append(f"{e.name} = {x:.3g} (< {MIN_ALPHA:g})")
        elif at and e.param in PINNED:
            out.append(f"{e.name} = {x:.4g} (at its bound)")
    return out


class PixelCheck:
    """A scene's pixels of the measured material, found once; :meth:`delta_e` of any fit."""

    def __init__(self, measured, *, scene="product-shot", size=32, k=16, seed=0, variant=None):
        from gonio.fitting.selection.by_scene import scene_pairs
        from gonio.fitting.selection.scene_fit import measured_pixels

        self.variant = select_variant(variant)
        self.scene, self.size, self.k = str(scene), int(size), int(k)
        rng = np.random.default_rng([int(seed), 35])
        self.sets = []
        for _ in range(2):      # two independent sets of light samples: the comparison's noise
            pairs = scene_pairs(scene, size, rng=rng, k=k, variant=self.variant)
            self.sets.append((pairs, measured_pixels(measured, pairs, self.variant)))
        self._white = max(float(np.percentile(self.sets[0][1], 99.5)), 1e-12)
        self._scored = {}       # delta_e of a (model, parameters) scored already (auto's fallback, then the ranking)

    def pixels(self, model, params, which=0) -> np.ndarray:
        """The model's pixels from the pairs of set ``which`` (0 or 1)."""
        from gonio.fitting.selection.scene_fit import pixel_values

        p = self.sets[which][0]
        f = np.asarray(model.eval(p.wi, p.wo, params), dtype=np.float64) * p.wi[:, 2:3]
        if not np.all(np.isfinite(f)):
            raise FloatingPointError(f"{model.name} is not finite at the scene's pairs")
        return pixel_values(f, p)

    def delta_e(self, model, params) -> tuple:
        """(mean CIEDE2000 of the model's pixels against the measured ones, its noise): the
        mean over the two sets of pairs and half their difference (both images scaled so the
        measured image's 99.5th percentile is white, as an exposure would). The same model and
        parameters again: the figures already found."""
        key = (model.name, repr(sorted(model.options.items())),
               tuple((k, np.asarray(v).tobytes(), np.asarray(v).dtype.str) for k, v in sorted(params.items())))
        if key not in self._scored:
            de = [float(delta_e_2000(self.pixels(model, params, i) / self._white, target / self._white).mean())
                  for i, (_, target) in enumerate(self.sets)]
            self._scored[key] = (0.5 * (de[0] + de[1]), 0.5 * abs(de[0] - de[1]))
        return self._scored[key]


def pixel_choice(ranking, measured, *, scene="product-shot", size=32, k=16, seed=0, threshold=THRESHOLD,
                 tolerance=TOLERANCE, delta=2.0, variant=None, fallback=None, progress=None):
    """Choose among ``ranking`` (select's rows, every candidate fitted) by their pixels.
    ``measured``: the measured file (or its :class:`PixelCheck`, made once).

    Each row gets ``delta_e`` and ``noise`` (the pair sets' floor). The scene keeps the proper
    rows (:func:`degenerate` empty) whose difference is within ``tolerance`` plus the floor of
    the closest proper row's; the data chooses among them: the simplest whose BIC is within
    ``delta`` of their lowest (as :func:`gonio.fitting.selection.by_data.select`). Where no row
    renders within ``threshold``, ``fallback()``'s fits are added (rows of their own) first.
    Returns ``(result, ranking, note)`` as :func:`gonio.fitting.selection.by_scene.rendered_choice`.
    """
    from gonio.fitting.selection.by_data import Ranked

    t0 = time.perf_counter()
    if progress is not None:
        progress(0, None, f"the {scene} scene's pixels")
    check = measured if isinstance(measured, PixelCheck) else PixelCheck(measured, scene=scene, size=size, k=k,
                                                                         seed=seed, variant=variant)

    def score(rows):
        for r in rows:
            try:
                r.delta_e, r.noise = check.delta_e(r.result.model, r.result.params)
            except FloatingPointError:
                r.delta_e, r.noise = float("inf"), float("inf")

    score(ranking)
    proper = [r for r in ranking if not degenerate(r.result) and np.isfinite(r.delta_e)]
    extra_note = ""
    if fallback is not None and (not proper or min(r.delta_e for r in proper) > threshold):
        if progress is not None:
            progress(0, None, "fitting the fallback")
        extra = list(fallback())
        added = [Ranked(res.model.name, dict(res.model.options), res.space.size, res.chi2, res.bic, 0.0, False,
                        res, res.loss, res.neg2_loglik) for res in extra]
        score(added)
        ranking.extend(added)
        best_bic = min(r.bic for r in ranking)
        for r in ranking:
            r.delta_bic = r.bic - best_bic
        proper += [r for r in added if not degenerate(r.result) and np.isfinite(r.delta_e)]
        extra_note = f"; none within CIEDE2000 {threshold:g}, so {', '.join(r.name for r in added)} was fitted too"
    ranking.sort(key=lambda r: r.bic)
    for r in ranking:
        r.chosen = False
    if not proper:
        pick = min(ranking, key=lambda r: r.bic)
        pick.chosen = True
        return pick.result, ranking, "every candidate is degenerate or not finite in the scene: the lowest BIC stands"
    best = min(proper, key=lambda r: r.delta_e)
    limit = best.delta_e + tolerance + best.noise
    alike = [r for r in proper if r.delta_e <= limit]          # none renders visibly better than these
    low = min(r.bic for r in alike)
    pick = min((r for r in alike if r.bic - low <= delta), key=lambda r: (r.k, r.bic))
    pick.chosen = True
    kept = {id(r) for r in proper}          # by identity: rows compare their FitResults' arrays
    skipped = [r.name for r in ranking if id(r) not in kept]
    note = (f"{pick.name} (k = {pick.k}): the data's choice (BIC) among the {len(alike)} proper candidates whose "
            f"{check.scene} pixels lie within CIEDE2000 {tolerance:g} (+ floor {best.noise:.2f}) of the closest "
            f"({best.name} {best.delta_e:.2f}; chosen {pick.delta_e:.2f}){extra_note}")
    if skipped:
        note += f"; degenerate, not chosen: {', '.join(sorted(set(skipped)))}"
    return pick.result, ranking, note + f" ({time.perf_counter() - t0:.1f} s)"
