"""Datasets are checked when they are read (issue 14): known angle units only, directions above
the horizon, sigmas positive, finite and of a plausible size; one line and exit status 2."""

import os
import subprocess
import sys

import numpy as np
import pytest
import xarray as xr

from gonio.fitting import load_dataset
from gonio.fitting.measurements import DataError

N = 6


def write(path, *, units="degree", theta_i=None, std=None, brdf=None, drop_units=()):
    rng = np.random.default_rng(0)
    ti = np.array(theta_i if theta_i is not None else np.linspace(10, 60, N), float)
    f = np.array(brdf if brdf is not None else 0.1 + rng.random((N, 3)), float)
    s = np.array(std if std is not None else 0.01 * f, float)
    attrs = {"units": units}
    k = np.pi / 180 if units.lower().startswith("rad") else 1.0
    coords = {"point": np.arange(N), "channel": ["R", "G", "B"],
              "theta_i": ("point", ti, {} if "theta_i" in drop_units else attrs),
              "phi_i": ("point", np.zeros(N), attrs),
              "theta_o": ("point", k * np.linspace(20, 70, N), attrs),
              "phi_o": ("point", k * np.full(N, 180.0), attrs)}
    ds = xr.Dataset({"brdf": (("point", "channel"), f, {"units": "sr^-1"}),
                     "brdf_std": (("point", "channel"), s, {"units": "sr^-1"})}, coords=coords)
    ds.to_netcdf(path, engine="h5netcdf")
    return path


def refused(path, *needles):
    with pytest.raises(DataError) as e:
        load_dataset(path)
    msg = str(e.value)
    assert "\n" not in msg
    for n in needles:
        assert n in msg, msg
    return msg


@pytest.mark.parametrize("units, factor", [("degree", np.pi / 180), ("deg", np.pi / 180), ("Degrees", np.pi / 180),
                                           ("rad", 1.0), ("radian", 1.0), ("radians", 1.0)])
def test_known_units_are_read(tmp_path, units, factor):
    th = np.linspace(10, 60, N) if factor != 1.0 else np.radians(np.linspace(10, 60, N))
    meas = load_dataset(write(tmp_path / "d.nc", units=units, theta_i=th))
    assert np.allclose(meas.wi[:, 2], np.cos(np.radians(np.linspace(10, 60, N))))


def test_unknown_units_are_refused(tmp_path):
    refused(write(tmp_path / "d.nc", units="furlong"), "theta_i has units 'furlong'", "degree", "radian")
    refused(write(tmp_path / "e.nc", units="gradians"), "units 'gradians'")


def test_directions_below_the_horizon_are_refused(tmp_path):
    th = np.linspace(10, 60, N)
    th[2] = 120
    refused(write(tmp_path / "d.nc", theta_i=th), "theta_i = 120 deg at point 2 is below the horizon", "[0, 90]")
    th[2] = -5
    refused(write(tmp_path / "e.nc", theta_i=th), "theta_i = -5 deg at point 2")
    th = np.radians(np.linspace(10, 60, N))
    th[1] = 2.0                                            # 115 deg in radians
    refused(write(tmp_path / "f.nc", theta_i=th, units="rad"), "at point 1 is below the horizon")


@pytest.mark.parametrize("value, says", [(1e-300, "absurdly small"), (5e-324, "absurdly small"),
                                         (1e-12, "absurdly small"), (0.0, "not positive"), (-0.01, "not positive"),
                                         (np.inf, "NaN"), (np.nan, "NaN")])
def test_implausible_sigmas_are_refused(tmp_path, value, says):
    f = np.full((N, 3), 0.5)
    s = np.full((N, 3), 0.01)
    s[3, 1] = value
    refused(write(tmp_path / "d.nc", brdf=f, std=s), "point 3", says)


def test_a_zero_value_with_a_tiny_sigma_is_refused(tmp_path):
    f = np.full((N, 3), 0.5)
    f[0] = 0.0
    s = np.full((N, 3), 0.01)
    s[0] = 1e-300
    refused(write(tmp_path / "d.nc", brdf=f, std=s), "point 0", "absurdly small")
    s[0] = 1e-4                                            # a real zero measurement with a real sigma: fine
    assert load_dataset(write(tmp_path / "e.nc", brdf=f, std=s)).n_points == N


def test_fit_of_a_hostile_dataset_is_one_line_and_status_2(tmp_path):
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    f = np.full((N, 3), 0.5)
    s = np.full((N, 3), 0.01)
    s[2, 0] = 1e-300
    for path, needle in ((write(tmp_path / "a.nc", units="furlong"), "furlong"),
                         (write(tmp_path / "b.nc", theta_i=[10, 20, 120, 30, 40, 50]), "below the horizon"),
                         (write(tmp_path / "c.nc", brdf=f, std=s), "absurdly small")):
        proc = subprocess.run([sys.executable, "-m", "gonio.cli.main", "fit", str(path), "--model", "diffuse",
                               "--out", str(tmp_path / "fit.json")], capture_output=True, text=True, env=env,
                              timeout=300)
        lines = [x for x in proc.stderr.splitlines() if x.strip()]
        assert proc.returncode == 2 and len(lines) == 1 and needle in lines[0], (proc.returncode, proc.stderr)
        assert lines[0].startswith("gonio: error:") and not (tmp_path / "fit.json").exists()
