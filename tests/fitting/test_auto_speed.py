"""What ``--model auto``'s cheaper choice keeps (issue 35): the work it skips changes nothing it chooses.

Each candidate draws its starts from a Generator of its own (by_data.candidate_rng), so a
candidate's fit does not depend on which candidates came before it; a nested candidate started
from its contained model's fit skips the global stage in the screen (``nested_starts=0``) and
reaches the optimum the global stage reaches; the choice's fits run on one Dr.Jit thread and
give the pool back; a fit scored twice in the scene is rendered once. Simulated data
(tests/fitting/_simdata.py).
"""

import numpy as np
import pytest

import gonio.models as gm

pytest.importorskip("colour")      # at collection: its 1.7 s import is not a test's time

GLOSSY = {"diffuse_reflectance": [0.5, 0.3, 0.2], "alpha": 0.1, "int_ior": 1.5}
TWO = {"eta": [0.2, 0.4, 1.4], "k": [3.9, 2.4, 1.6], "alpha": 0.08, "alpha2": 0.4, "weight": 0.3}


def _meas(name, options, params, seed, n=400):
    from _simdata import simulate

    model = gm.get(name, **options)
    return simulate(model, model.validate(params), np.random.default_rng(seed), n=n, rel=0.02)


def test_a_candidates_fit_does_not_depend_on_the_candidates_before_it(monkeypatch):
    """roughplastic GGX screened alone and after two others whose fits took draws: its fit is
    handed a Generator in the same state both times (before: the caller's, where the draws of
    the fits before it had moved it on), and the same parameters come back."""
    import gonio.fitting.selection.by_data as by_data

    meas = _meas("roughplastic", {"distribution": "ggx"}, GLOSSY, 11, n=300)
    target = ("roughplastic", {"distribution": "ggx"})
    seen, real_fit = {}, by_data.fit

    def spy(meas, model, *, rng, **kw):
        seen.setdefault(model.name, []).append(rng.bit_generator.state)
        return real_fit(meas, model, rng=rng, **kw)

    monkeypatch.setattr(by_data, "fit", spy)
    kw = dict(loss="log", n_local=1)
    _, alone = by_data.select(meas, rng=np.random.default_rng(5), candidates=[target], **kw)
    _, after = by_data.select(meas, rng=np.random.default_rng(5), candidates=[("diffuse", {}), ("cooktorrance", {}),
                                                                             target], **kw)
    assert seen["roughplastic"][0] == seen["roughplastic"][1]
    assert seen["diffuse"][0] != seen["roughplastic"][0]
    a, b = (next(r for r in rows if r.name == "roughplastic") for rows in (alone, after))
    assert np.allclose(a.result.x, b.result.x, rtol=1e-6)


def test_a_nested_candidate_started_from_its_layer_needs_no_global_stage():
    """roughconductor2 (two GGX lobes) on simulated two-lobe data, screened after its one-lobe
    layer: started from the layer's fit without the global stage it evaluates the model fewer
    times and reaches the objective the global stage's starts reach (relative 1e-4: the
    screen's ftol is 1e-7)."""
    from gonio.fitting.selection.by_data import select

    meas = _meas("roughconductor2", {"distribution": "ggx"}, TWO, 12)
    cands = [("roughconductor", {"distribution": "ggx"}), ("roughconductor2", {"distribution": "ggx"})]
    kw = dict(loss="log", n_local=1, use_fast=False, covariance=False, enforce_energy=False, ftol=1e-7)
    rows = {}
    for nested in (None, 0):
        _, ranking = select(meas, rng=np.random.default_rng(6), candidates=cands, nested_starts=nested, **kw)
        rows[nested] = next(r for r in ranking if r.name == "roughconductor2")
    full, skipped = rows[None].result, rows[0].result
    assert skipped.n_evals < full.n_evals
    assert skipped.objective <= full.objective * (1 + 1e-4), (skipped.objective, full.objective)


def test_the_choice_runs_on_one_jit_thread_and_gives_the_pool_back(monkeypatch):
    """choice_threads: Dr.Jit's pool has CHOICE_THREADS threads inside the block and its former
    size after it, also when the block raises; from another thread than the main one, and where
    GONIO_THREADS sets the pool, it is left alone."""
    import threading

    import drjit as dr

    from gonio.fitting.selection.auto import CHOICE_THREADS, choice_threads

    monkeypatch.delenv("GONIO_THREADS", raising=False)
    before = dr.thread_count()
    dr.set_thread_count(2)
    try:
        with choice_threads():
            assert dr.thread_count() == CHOICE_THREADS
        assert dr.thread_count() == 2
        with pytest.raises(KeyError):
            with choice_threads():
                raise KeyError("inside")
        assert dr.thread_count() == 2
        seen = []

        def worker():       # a batch's in-process Dask worker: the process's pool is left alone
            with choice_threads():
                seen.append(dr.thread_count())

        t = threading.Thread(target=worker)
        t.start()
        t.join()
        assert seen == [2]
        monkeypatch.setenv("GONIO_THREADS", "2")
        with choice_threads():
            assert dr.thread_count() == 2
    finally:
        dr.set_thread_count(before)


def test_a_fit_scored_twice_in_the_scene_is_rendered_once(monkeypatch):
    """PixelCheck.delta_e of the same model and parameters (auto's fallback scores its fits,
    then pixel_choice scores them again): the pixels are computed once, the figures the same;
    other parameters are scored anew, and a fit that renders the target exactly scores 0. The
    scene is stood in by fixed target pixels (the pairs are not needed: ``pixels`` is counted)."""
    from gonio.fitting.selection.by_pixels import PixelCheck

    model = gm.get("roughplastic", distribution="ggx")
    p = model.validate(GLOSSY)
    target = np.random.default_rng(3).uniform(0.05, 0.9, (50, 3))
    check = PixelCheck.__new__(PixelCheck)
    check.sets, check._white, check._scored = [(None, target), (None, target)], 1.0, {}
    calls = []

    def pixels(self, m, params, which=0):
        calls.append(which)
        return target * (1.0 + float(params["alpha"]) - GLOSSY["alpha"])

    monkeypatch.setattr(PixelCheck, "pixels", pixels)
    q = model.validate({**GLOSSY, "alpha": 0.2})
    first = check.delta_e(model, q)
    again = check.delta_e(model, dict(q))
    assert first == again and first[0] > 0 and len(calls) == 2
    assert check.delta_e(model, p) == (0.0, 0.0) and len(calls) == 4


def test_the_screen_takes_roughplastic_tables_from_the_grid_and_the_refit_exact():
    """select(exact_tables=False): roughplastic is screened on its precomputed table grid (the
    model says so, ``exact_tables`` False) and its BIC agrees with the exact screen's to 1e-5
    relative (the grid's diffuse term is typically 6e-5 off, roughplastic.py); auto's refit of
    that row fits the model with exact tables; a model without the keyword is untouched."""
    from gonio.fitting.selection.auto import refit
    from gonio.fitting.selection.by_data import select

    meas = _meas("roughplastic", {"distribution": "ggx"}, GLOSSY, 13, n=300)
    cands = [("diffuse", {}), ("roughplastic", {"distribution": "ggx"})]
    rows = {}
    for exact in (True, False):
        _, ranking = select(meas, rng=np.random.default_rng(8), candidates=cands, loss="log", n_local=1,
                            exact_tables=exact)
        rows[exact] = {r.name: r for r in ranking}
    grid = rows[False]["roughplastic"]
    assert grid.result.model.exact_tables is False and rows[True]["roughplastic"].result.model.exact_tables is True
    assert abs(grid.bic - rows[True]["roughplastic"].bic) <= 1e-5 * abs(grid.bic)
    assert not hasattr(rows[False]["diffuse"].result.model, "exact_tables")
    final = refit(meas, grid.result, rng=np.random.default_rng(9), loss="log")
    assert final.model.exact_tables is True and final.model.options == grid.result.model.options


@pytest.mark.parametrize("bad", [-1, 1.5, "2"])
def test_bad_counts_are_refused_in_one_line(bad):
    """A negative, fractional or text count of nested starts or of threads: ValueError naming
    the value, before any fit or any change to Dr.Jit's pool."""
    import drjit as dr

    from gonio.fitting.selection.auto import choice_threads
    from gonio.fitting.selection.by_data import select

    meas = _meas("diffuse", {}, {"reflectance": [0.5, 0.4, 0.3]}, 14, n=50)
    with pytest.raises(ValueError, match="nested_starts"):
        select(meas, rng=np.random.default_rng(0), candidates=[("diffuse", {})], nested_starts=bad)
    before = dr.thread_count()
    with pytest.raises(ValueError, match="choice_threads"):
        with choice_threads(bad):
            pass
    assert dr.thread_count() == before
