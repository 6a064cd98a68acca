"""One input for every fit of a dataset: `gonio fit` and each `gonio fit --batch` worker take
the same :class:`gonio.fitting.pipeline.FitInput` (Measurements and budget,
gonio.bench.dataset.reader.open_fit_input), and the fit document is built from it.

The defect this guards: the batch handed its workers the Measurements alone and wrote the fit
file against the budget of ``meas.attrs``, so an uncalibrated capture's type-B angle inputs
(and the value's second-order angle correction) were missing: diffuse_reflectance[R]
0.5499391 (batch) against 0.5498815 (single) on the demo's capture.
"""

import dataclasses
import functools

import numpy as np
import pytest

from gonio.fitting.pipeline import FitInput, fit_dataset, fit_document_of


def _same(a, b, where):
    """Field by field: arrays equal (dtype and NaN placement too), dicts and lists item by item."""
    if dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            _same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), where
        for k in a:
            _same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for k, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{k}]")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape, where
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, float) and np.isnan(a):
        assert isinstance(b, float) and np.isnan(b), where
    else:
        assert a == b, where


def test_the_handed_off_input_is_the_loaded_one(uncalibrated, tmp_path):
    from gonio.bench.dataset.reader import open_fit_input
    from gonio.fitting.batch import handoff
    from gonio.fitting.batch.dask_batch import _load

    inp = open_fit_input(uncalibrated, 3)
    assert isinstance(inp, FitInput) and inp.budget is not None
    assert inp.budget.angles, "an uncalibrated typical capture carries its stages' errors as angle inputs"
    assert any(c.gum_type == "B" for c in inp.budget.components)
    handoff.write(inp, tmp_path / "h.bin")
    _same(inp, handoff.read(tmp_path / "h.bin"), "handoff")                   # in memory, through a file
    _same(inp, _load(functools.partial(open_fit_input, uncalibrated, 3)), "loader")   # a worker's own read


def test_a_batch_fit_document_is_the_single_fits(uncalibrated):
    """fit_serial (the batch's worker function, in this process) and fit_document_of against
    `gonio fit`'s fit_dataset: the same values, u_c and budget."""
    from gonio.bench.dataset.reader import open_fit_input
    from gonio.fitting.batch.dask_batch import fit_serial

    inp = open_fit_input(uncalibrated, 3)
    _, single, _ = fit_dataset(inp, model="roughplastic", options={"distribution": "ggx"}, seed=3)
    (result,) = fit_serial([inp], ("roughplastic", {"distribution": "ggx"}), rng_seed=3, loss="chi2")
    batch = fit_document_of(result, inp, seed=3)
    assert single["uncertainty"]["components"] == batch["uncertainty"]["components"]
    for name, p in single["parameters"].items():
        q = batch["parameters"][name]
        assert q["value"] == pytest.approx(p["value"], rel=1e-12, abs=1e-15), name
        assert q["u_combined"] == pytest.approx(p["u_combined"], rel=1e-9), name
    assert any("angle_second_order_correction" in p for p in single["parameters"].values())


def test_a_fit_input_and_a_budget_are_not_given_twice(uncalibrated):
    from gonio.bench.dataset.reader import open_fit_input

    inp = open_fit_input(uncalibrated, 3)
    with pytest.raises(TypeError):
        fit_dataset(inp, model="roughplastic", budget=inp.budget)
