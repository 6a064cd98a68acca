"""Extreme f_r in a dataset (issue 36): huge but finite values, +-1e300, the largest float and
denormals in brdf_srgb (and its 1-sigma) are refused in one line with exit status 2 before
anything is written, or fitted cleanly; never a traceback from the uncertainty budget."""

import shutil

import h5py
import numpy as np
import pytest

from gonio.cli import main as cli


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from gonio.bench.dataset.export import export
    from gonio.bench.samples import load_sample
    from gonio.cli.capture import capture_sim

    root = tmp_path_factory.mktemp("extreme")
    capture_sim(root / "session", sample=load_sample(None), plan="quick", seed=2, progress=False)
    return export(root / "session")


def _damaged(dataset, tmp_path, variables, change):
    path = tmp_path / "dataset.nc"
    shutil.copy(dataset, path)
    with h5py.File(path, "r+") as f:
        for name in variables:
            f[name][...] = change(f[name][...])
    return path


BOTH = ("brdf_srgb", "brdf_srgb_std")
REFUSED = [
    ("value 1e300", ("brdf_srgb",), lambda a: np.full_like(a, 1e300)),
    ("value -1e300", ("brdf_srgb",), lambda a: np.full_like(a, -1e300)),
    ("one value 1e300", ("brdf_srgb",), lambda a: np.where(np.arange(a.size).reshape(a.shape) == 7, 1e300, a)),
    ("both x 1e150", BOTH, lambda a: a * 1e150),          # the budget's reshape of nothing
    ("both x 1e200", BOTH, lambda a: a * 1e200),          # Cholesky of an overflowed covariance
    ("both 1e300", BOTH, lambda a: np.full_like(a, 1e300)),
    ("both largest float", BOTH, lambda a: np.full_like(a, np.finfo(np.float64).max)),
    ("sigma 1e300", ("brdf_srgb_std",), lambda a: np.full_like(a, 1e300)),
    ("both denormal", BOTH, lambda a: a * 1e-310),
    ("sigma denormal", ("brdf_srgb_std",), lambda a: np.full_like(a, 5e-324)),
]


@pytest.mark.parametrize("name, variables, change", REFUSED, ids=[r[0] for r in REFUSED])
def test_extreme_values_are_refused_before_anything_is_written(dataset, tmp_path, capsys, name, variables, change):
    path = _damaged(dataset, tmp_path, variables, change)
    out = tmp_path / "fit.json"
    assert cli.main(["fit", str(path), "--model", "diffuse", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "gonio: error:" in err, err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["dataset.nc"]


def test_denormal_values_with_sound_sigmas_fit_cleanly(dataset, tmp_path, capsys):
    path = _damaged(dataset, tmp_path, ("brdf_srgb",), lambda a: np.full_like(a, 5e-324))
    out = tmp_path / "fit.json"
    assert cli.main(["fit", str(path), "--model", "diffuse", "--out", str(out)]) == 0, capsys.readouterr().err
    assert out.exists()
