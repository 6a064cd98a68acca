"""One fit, the same everywhere: `gonio fit`, `gonio fit --batch`, the library's batch and a
notebook's `gonio.fitting.fit_dataset` of the same data, model, options and seed give the same
model, options and parameters (gonio.fitting.pipeline).

The defect this guards: `gonio fit --batch D --model roughplastic` fitted the registry's
default distribution (Beckmann) to a GGX sample where the single fit compared both declared
distributions and kept GGX by BIC.
"""

import json

import numpy as np
import pytest

import gonio.models as gm
from gonio.fitting import fit_dataset, fit_measurements
from gonio.fitting.batch.dask_batch import fit_batch, fit_serial

from _simdata import simulate

TRUTH = {"diffuse_reflectance": np.array([0.5, 0.35, 0.2]), "alpha": 0.12, "int_ior": 1.5}


def _ggx_data(seed, n=300):
    return simulate(gm.get("roughplastic", distribution="ggx"), TRUTH, np.random.default_rng(seed), n=n, rel=0.01)


def test_a_name_without_distribution_is_fitted_as_the_single_fit_fits_it():
    """The serial reference of fit_batch, given (name, the user's options), goes through the
    pipeline: both declared distributions tried, GGX kept, the same numbers as the single fit."""
    data = [_ggx_data(s) for s in (1, 2)]
    serial = fit_serial(data, ("roughplastic", {}), rng_seed=4, loss="chi2")
    for meas, batch in zip(data, serial):
        single, _, _, ranking, _ = fit_measurements(meas, model="roughplastic", seed=4, loss="chi2")
        assert single.model.options["distribution"] == "ggx"
        assert {r.options["distribution"] for r in ranking} == {"ggx", "beckmann"}
        assert batch.model.options == single.model.options
        np.testing.assert_allclose(batch.x, single.x, rtol=1e-9, atol=1e-12)
        assert batch.chi2 == pytest.approx(single.chi2, rel=1e-9)


def test_the_fit_document_of_a_notebook_fit_is_the_pipelines():
    meas = _ggx_data(3)
    result, doc, _ = fit_dataset(meas, model="roughplastic", options={"distribution": "ggx"}, seed=2)
    again, _, _, _, _ = fit_measurements(meas, model="roughplastic", options={"distribution": "ggx"}, seed=2)
    np.testing.assert_array_equal(result.x, again.x)
    assert doc["model"]["options"]["distribution"] == "ggx"


@pytest.mark.slow
def test_cli_batch_and_cli_single_fit_agree(tmp_path):
    """On a simulated capture of the demo's GGX roughplastic: `gonio fit --batch` on a local
    Dask cluster writes the model, options and parameters `gonio fit` writes."""
    from gonio.bench.dataset.export import export
    from gonio.bench.samples import load_sample
    from gonio.cli.capture import capture_sim
    from gonio.cli.main import main

    capture_sim(tmp_path / "session", sample=load_sample(None), plan="quick", seed=5, progress=False)
    dataset = export(tmp_path / "session")
    assert main(["fit", str(dataset), "--model", "roughplastic", "--out", str(tmp_path / "single.json"),
                 "--seed", "3"]) == 0
    assert main(["fit", "--batch", str(dataset), "--model", "roughplastic", "--out", str(tmp_path / "batch"),
                 "--workers", "1", "--seed", "3"]) == 0
    single = json.loads((tmp_path / "single.json").read_text())
    (batch_file,) = (tmp_path / "batch").glob("*.fit.json")
    batch = json.loads(batch_file.read_text())
    assert single["model"]["options"]["distribution"] == "ggx"
    assert batch["model"] == single["model"]
    for name, p in single["parameters"].items():
        assert batch["parameters"][name]["value"] == pytest.approx(p["value"], rel=1e-6, abs=1e-9), name
