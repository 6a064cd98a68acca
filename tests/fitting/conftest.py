"""Fixtures shared by the fitting tests."""

import pytest


@pytest.fixture(scope="session")
def uncalibrated(tmp_path_factory):
    """A quick capture of the default sample under the typical simulated errors, not
    calibrated: its budget holds the type-B angle inputs and the shared lines."""
    from gonio.bench.dataset.export import export
    from gonio.bench.samples import load_sample
    from gonio.bench.settings import default_settings
    from gonio.cli.capture import capture_sim

    folder = tmp_path_factory.mktemp("uncal") / "session"
    settings = default_settings()
    settings["errors"] = {"preset": "typical"}
    capture_sim(folder, sample=load_sample(None), plan="quick", seed=11, settings=settings, progress=False)
    return export(folder)
