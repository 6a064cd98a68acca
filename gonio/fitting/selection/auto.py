"""``--model auto`` on a measured material: screen on a subsample, choose by pixels, refit once.

Every candidate (and the data-driven ``tabulated`` model where none renders well enough, and
its tabulated body where that renders closer by more than the noise) is
fitted to a seeded random subsample of :data:`SCREEN_POINTS` samples, one local refinement
each (:func:`screen`); the ranking by BIC is the subsample's. The choice is
:func:`gonio.fitting.selection.by_pixels.pixel_choice`'s: the simplest proper candidate that
renders, in the default scene's own pixels, within half a just-noticeable difference of the
closest one. Where that choice does not render within the threshold either, its family's
refinement, if it declares one (gratingpaint's ring table; a matte tabulated fit's sheen,
fitted with the luminance loss), takes its place where it renders closer beyond the noise.
Only the chosen candidate is then fitted to every sample, started from its screened fit
(:func:`refit`), so choosing costs the screen, one scene's pairs and one fit (or two).
"""

# Why a subsample: the candidates' BIC gaps on measured files are thousands (acrylic_felt_white:
# 535 to 74,000 at 7,700 samples), so 2,000 samples keep the order; a model's fit time is
# mostly its evaluations, which scale with the samples. One local refinement: the global
# stage's start scores and the default start find the basin; the other refinements changed
# no choice on the materials screened (docs/performance.md, gonio.perf.real).

# One Dr.Jit thread while the choice fits (CHOICE_THREADS): its kernels run on 2,000 to 8,000
# pairs, a work item or two of the LLVM backend, so a second thread in the pool adds hand-offs,
# not parallel work. auto_fit on cardboard, three runs each in one process at load 4-5 on the
# 2-core machine: pool of 2, 9.9-12.6 s wall and 5.4-7.1 s CPU; pool of 1, 7.5-9.4 s wall and
# 3.8-5.2 s CPU. The scene's pairs are found with the pool as it was (Mitsuba's OpenEXR reader
# waits forever on a pool without a worker: gonio.fitting.render.preview._exr_threads).

from __future__ import annotations

import contextlib
import dataclasses
import os
import threading
import time

import numpy as np

__all__ = ["CHOICE_THREADS", "SCREEN_FTOL", "SCREEN_POINTS", "auto_fit", "choice_threads", "refit", "screen",
           "subsample"]

#: samples each candidate is screened on
SCREEN_POINTS = 2000
#: a screening fit stops where a step would lower its objective by less than this fraction:
#: the profiled likelihood -2 ln L = n ln(S / n) then moves by n * 1e-7, 6e-4 at the 6000
#: values of 2000 RGB samples, against BIC gaps of hundreds to thousands (1e-5 let a slowly
#: converging two-lobe fit stop far from its optimum on irid_flake_paint2)
SCREEN_FTOL = 1e-7
#: the screen's roughplastic takes its tables from the precomputed grid (exact quadrature
#: outside the grid's checked cells; diffuse term typically 6e-5 from Mitsuba's): the same BIC
#: (to 0.01) and CIEDE2000 (to 0.001) on cardboard and vch_golden_yellow, 0.02-0.2 s CPU a fit
#: where the exact quadrature of every new (alpha, eta) took 0.24-0.6 s; the refit is exact
SCREEN_EXACT_TABLES = False
#: fit rounds of the tabulated body's screening fit (it starts from the plain fit's optimum). The
#: body table is fitted first with the plain fit's NDF held, then with everything free: from the
#: plain optimum with all free at once, the new freedom's first steps can trade the lobe for a
#: flat, bright one (acrylic_felt_white: every NDF knot at its bound, albedo 1.1-2.5, rendered
#: CIEDE2000 6.6), a basin the staged fit does not enter (0.88); cardboard's lands where the
#: one-stage fit does (docs/performance.md, gonio.fitting.optimise.lm)
BODY_ROUNDS = 1
#: threads of Dr.Jit's pool while the choice fits (module notes); ``GONIO_THREADS`` overrides
CHOICE_THREADS = 1
#: the refit to every sample runs on CHOICE_THREADS up to this many samples (RGL files: 6,000 to
#: 8,000, measured); above it on the pool as it is (the crossover is not measured)
ONE_THREAD_POINTS = 20_000


@contextlib.contextmanager
def choice_threads(n=CHOICE_THREADS):
    """Dr.Jit's pool at ``n`` threads inside the block, as it was after it; left alone where
    ``GONIO_THREADS`` sets it, the pool is that size already, or the caller is not the main
    thread (the pool is the process's: a batch's in-process Dask workers fit side by side,
    and a pool resized under another thread's replayed kernel is what freeze.py warns of)."""
    import drjit as dr

    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ValueError(f"choice_threads({n!r}): give a whole number of threads >= 1")
    before = dr.thread_count()
    if (os.environ.get("GONIO_THREADS", "").strip() or before == int(n)
            or threading.current_thread() is not threading.main_thread()):
        yield
        return
    dr.set_thread_count(int(n))
    try:
        yield
    finally:
        dr.set_thread_count(before)


def subsample(meas, n: int, rng):
    """A seeded random subsample of ``n`` of ``meas``'s samples (all of them when there are
    not twice as many), their solid-angle weights kept."""
    if not isinstance(rng, np.random.Generator):
        raise TypeError("subsample(rng=...) takes a numpy.random.Generator")
    if meas.n_points < 2 * int(n):
        return meas
    return meas.subset(np.sort(rng.choice(meas.n_points, size=int(n), replace=False)))


def screen(sub, *, rng, loss, candidates=None, progress=None):
    """Every candidate fitted to ``sub`` with one local refinement, no sandwich covariance and
    no energy polish (the chosen one's refit has both): ``(best, ranking)`` as
    :func:`gonio.fitting.selection.by_data.select`."""
    from gonio.fitting.selection.by_data import select

    return select(sub, rng=rng, loss=loss, candidates=candidates, progress=progress, n_local=1, covariance=False,
                  enforce_energy=False, ftol=SCREEN_FTOL, nested_starts=0, exact_tables=SCREEN_EXACT_TABLES)


def refit(meas, result, *, rng, loss):
    """``result``'s model fitted to every sample of ``meas``, started from ``result``'s
    parameters (its held parameters held), one local refinement, with exact tables where the
    screen interpolated them (:data:`SCREEN_EXACT_TABLES`); the FitResult."""
    from gonio.fitting.optimise.mle import fit

    model = result.model
    if getattr(model, "exact_tables", True) is False:
        model = type(model)(**model.options)
    fixed = dict(result.space.fixed) or None
    start = {k: v for k, v in result.params.items() if k not in (fixed or {})}
    return fit(meas, model, rng=rng, loss=loss, fixed=fixed, start=start, n_starts=0, n_local=1)


def _refined(chosen, sub, check, note, *, seed, loss, threshold=None, progress=None):
    """The chosen family's nested refinement (``model.refinement(params)``: gratingpaint's ring
    table, a matte tabulated fit's sheen), fitted to ``sub`` from the chosen fit with the
    chosen model's ``REFINEMENT_LOSS`` (``loss`` where it declares none); (it, note, its
    ranking row) where its pixels are closer by more than both rows' noise (the tabulated
    body's rule), else (``chosen``, ``note``, None). Not tried where the chosen fit's pixels
    are within ``threshold`` already (as the fallback: the scene needs no more)."""
    from gonio.fitting.selection.by_data import Ranked
    from gonio.fitting.selection.by_pixels import THRESHOLD

    make = getattr(chosen.model, "refinement", None)
    try:
        if make is not None and check.delta_e(chosen.model, chosen.params)[0] <= (THRESHOLD if threshold is None
                                                                                   else threshold):
            return chosen, note, None
        model = make(chosen.params) if make is not None else None
    except (ValueError, FloatingPointError):    # its gate cannot read the fit (not finite where it looks)
        model = None
    if model is None:
        return chosen, note, None
    from gonio.fitting.likelihood import loss as _loss
    from gonio.fitting.optimise.mle import fit

    rank_loss, loss = loss, getattr(chosen.model, "REFINEMENT_LOSS", None) or loss
    if progress is not None:
        progress(0, None, f"refining {chosen.model.name}: {model.name} {dict(model.options)}, {loss} loss")
    r = fit(sub, model, rng=np.random.default_rng([int(seed), 353]), loss=loss, start=model.start_from(chosen.params),
            n_starts=0, n_local=1, covariance=False, enforce_energy=False, ftol=SCREEN_FTOL)
    try:
        (de_c, noise_c), (de_r, noise_r) = (check.delta_e(x.model, x.params) for x in (chosen, r))
    except FloatingPointError:      # not finite at the scene's pairs
        return chosen, note, None
    if de_c - de_r <= noise_c + noise_r:
        return chosen, note, None
    # its row's -2 ln L and BIC under the ranking's loss, as every other row's (a profiled scale of
    # another loss is in other units: not comparable)
    ranked = r if loss == rank_loss else dataclasses.replace(
        r, loss=rank_loss, objective=_loss.objective(rank_loss, _loss.residuals(rank_loss, model.eval(sub.wi, sub.wo, r.params), sub)))
    row = Ranked(model.name, dict(model.options), r.space.size, r.chi2, ranked.bic, 0.0, False, r, rank_loss,
                 ranked.neg2_loglik, de_r, noise_r)
    return r, f"{note}; refined to {model.name} {model.options}, {loss} loss (pixels {de_c:.2f} -> {de_r:.2f})", row


def auto_fit(meas, measured, *, seed=0, loss, rng=None, scene="product-shot", n=SCREEN_POINTS, candidates=None,
             size=32, k=16, progress=None):
    """``--model auto`` on ``meas`` sampled from the measured file ``measured`` (a path
    Mitsuba renders: RGL ``.bsdf``, MERL ``.binary``, or a Mitsuba BSDF dict); ``candidates``
    (name, options) pairs, default every registered one; ``size``, ``k``: the scene's pixels
    and light samples a pixel. Returns ``(result, ranking, note)``:
    the chosen candidate refitted to every sample, the subsample's ranking (its chosen row's
    result replaced by that refit, ``delta_e`` re-measured), and a line saying what decided."""
    from gonio.fitting.optimise.tabulated_start import fit_tabulated
    from gonio.fitting.selection.by_pixels import PixelCheck, pixel_choice

    rng = np.random.default_rng(seed) if rng is None else rng
    t0 = time.perf_counter()
    sub = subsample(meas, n, np.random.default_rng([int(seed), 351]))
    with choice_threads():
        _, ranking = screen(sub, rng=rng, loss=loss, candidates=candidates, progress=progress)

    def fallback():     # tabulated; its body="table" variant, started from it (nested), where it renders closer
        kw = dict(loss=loss, n_starts=0, n_local=1, covariance=False, enforce_energy=False, ftol=SCREEN_FTOL)
        with choice_threads():
            plain = fit_tabulated(sub, rng=np.random.default_rng([int(seed), 16]), **kw)
            lobe = {k: v for k, v in plain.params.items() if k.startswith("ndf")}     # held while the body adapts
            body = fit_tabulated(sub, rng=np.random.default_rng([int(seed), 17]), body="table", start=plain.params,
                                 rounds=BODY_ROUNDS, fixed=lobe, **kw)
            body = fit_tabulated(sub, rng=np.random.default_rng([int(seed), 18]), body="table", start=body.params,
                                 rounds=BODY_ROUNDS, **kw)
        try:
            (de_p, noise_p), (de_b, noise_b) = (check.delta_e(r.model, r.params) for r in (plain, body))
        except FloatingPointError:      # not finite at the scene's pairs: pixel_choice scores it so
            return [plain]
        return [plain] + ([body] if de_p - de_b > noise_p + noise_b else [])

    check = PixelCheck(measured, scene=scene, size=size, k=k, seed=seed)
    with choice_threads():      # the pairs are found: the scoring reads no image
        chosen, ranking, note = pixel_choice(ranking, check, fallback=fallback, progress=progress)
    with choice_threads():
        chosen, note, added = _refined(chosen, sub, check, note, seed=seed, loss=loss, progress=progress)
    if added is not None:           # the refinement is a row of its own, with its own BIC
        for r in ranking:
            r.chosen = False
        added.chosen = True
        ranking.append(added)
        best_bic = min(r.bic for r in ranking)
        for r in ranking:
            r.delta_bic = r.bic - best_bic
        ranking.sort(key=lambda r: r.bic)
    if progress is not None:
        progress(0, None, f"fitting {chosen.model.name} to all {meas.n_points} samples")
    t1 = time.perf_counter()
    with choice_threads() if meas.n_points <= ONE_THREAD_POINTS else contextlib.nullcontext():
        final = refit(meas, chosen, rng=np.random.default_rng([int(seed), 352]), loss=chosen.loss)
    row = next(r for r in ranking if r.chosen)
    row.result, row.options, row.k = final, dict(final.model.options), final.space.size
    with choice_threads():
        row.delta_e, row.noise = check.delta_e(final.model, final.params)
    screened = "" if sub is meas else f"ranked on {sub.n_points} of {meas.n_points} samples; "
    note = (f"{screened}{note}; refitted to all samples in {time.perf_counter() - t1:.1f} s "
            f"(CIEDE2000 {row.delta_e:.2f}); choosing took {time.perf_counter() - t0:.1f} s")
    return final, ranking, note
