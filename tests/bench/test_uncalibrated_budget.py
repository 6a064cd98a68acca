"""A capture without calibration carries the instrument's uncorrected systematics as type-B
lines (issue 34; gonio/bench/measure/systematics.py, gonio/bench/dataset/budget.py).

Before: the budget held only type A and the certificate, and a glossy sample under the
typical simulator had z up to 24 (rms 5.9) against u_c. The coverage itself is checked in
tests/e2e/test_uncalibrated_coverage.py; here the lines, their sources and their sizes.
"""

import math

import numpy as np
import pytest

from gonio.sim.physics.errors import spectralon_factor
from gonio.bench import calibrate
from gonio.bench.dataset.budget import budget_variables
from gonio.bench.measure import systematics
from gonio.bench.settings import default_settings, merge_settings, validate_settings

N = 6


def rows():
    """Journal rows of a short in-plane scan: region statistics, stage angles, theta/phi."""
    out = []
    for k in range(N):
        yaw, lamp = 10.0 + 8 * k, 60.0 + 4 * k
        ang = calibrate.calibrated_angles({}, [yaw, 0.0, 0.0, lamp])[0]
        d = {}
        for name, mean in (("sample", 80.0 + 20 * k), ("reference", 150.0)):
            d.update({f"{name}_mean": [mean] * 3, f"{name}_se_model": [0.1] * 3, f"{name}_se": [0.1] * 3,
                      f"{name}_n": [200] * 3})
        d["exposures"] = [{"seconds": 40.0, "power": 1.0}]          # levels 0.2-0.4 of full scale
        out.append({"detail": d, "yaw": yaw, "tilt": 0.0, "azimuth": 0.0, "lamp": lamp, "finished": float(k),
                    "theta_i": ang[0], "phi_i": ang[1], "theta_o": ang[2], "phi_o": ang[3]})
    return out


def brdf():
    f = np.array([[(80.0 + 20 * k) / 150.0 * 0.99 / math.pi] * 3 for k in range(N)])
    return f, 1e-3 * f


def test_an_uncalibrated_session_carries_the_description_as_type_b():
    s = default_settings()
    f, u = brdf()
    v = budget_variables(rows(), s, f, u)
    for name in ("u_stray_light", "u_linearity"):
        assert v[name][2]["gum_type"] == "B"
        assert "[systematics]" in v[name][2]["source"] and "not calibrated" in v[name][2]["source"]
        assert np.all(np.abs(v[name][1]) > 0)
    # the linearity bound 0.003, rectangular: u = 0.003 / sqrt(3) x |level_s - level_r|; the stray
    # floor's bound 1e-4 as calibrate.u_stray_rel
    lev = np.array([[(80.0 + 20 * k) * 40.0 / 2 ** 14 - 150.0 * 40.0 / 2 ** 14] * 3 for k in range(N)])
    np.testing.assert_allclose(np.abs(v["u_linearity"][1]), f * 0.003 / math.sqrt(3) * np.abs(lev), rtol=1e-12)
    cos_i = np.cos(np.radians([r["theta_i"] for r in rows()]))[:, None]
    np.testing.assert_allclose(np.abs(v["u_stray_light"][1]),
                               f * calibrate.u_stray_rel(f * cos_i, 0.99 / math.pi * cos_i, 1e-4), rtol=1e-12)
    shared = v["angle_shift_shared"]
    assert "not calibrated" in shared[2]["source"]
    # inputs: yaw and tilt zero, two holder-tilt components, two wedge components, and one
    # lost-motion input per axis that moved in one direction (yaw, lamp)
    assert shared[1].shape[0] == 8
    assert "angle_shift_independent" in v
    # the yaw zero offset's input moves theta_o by its 0.1 deg (in-plane, phi 0)
    assert np.max(np.abs(shared[1][:, :, 2])) == pytest.approx(0.2, rel=0.02)       # the holder tilt's 0.2


def test_a_calibrated_session_keeps_its_calibration_lines():
    s = default_settings()
    s["alignment"] = {"yaw_zero_deg": 0.0, "tilt_zero_deg": 0.0, "holder_tilt_x_deg": 0.0, "holder_tilt_y_deg": 0.0,
                      "cov_deg2": (np.eye(4) * 1e-4).tolist(), "repeat_deg": 0.01}
    f, u = brdf()
    v = budget_variables(rows(), s, f, u)
    assert "u_stray_light" not in v and "u_linearity" not in v
    assert "gonio calibrate" in v["angle_shift_shared"][2]["source"]


def test_the_simulator_states_its_error_model():
    typical = systematics.for_session({**default_settings(), "errors": {"preset": "typical"}})
    assert typical["systematics"]["holder_tilt_deg"] == 0.2 and "typical" in typical["systematics"]["source"]
    assert typical["aperture"]["source_half_deg"] == 0.5
    # the reference's certificate factor is the simulator's Spectralon form
    from gonio.bench.measure.point import ReferenceModel

    ref = ReferenceModel(typical["reference"])
    ti, to = 55.0, 20.0
    true = spectralon_factor(math.radians(ti), math.radians(to), 1.0)
    assert ref.factor(ti, to) == pytest.approx(true, rel=1e-12)
    # the ideal instrument states zeros: leaving the table out let the capture's merge over the
    # defaults put instrument.toml's [systematics] back (an ideal capture carried a 0.2 deg tilt)
    ideal = systematics.for_session({**default_settings(), "errors": {"preset": "ideal"}})
    assert "aperture" not in ideal and "factor_a" not in ideal["reference"]
    sysm = validate_settings(merge_settings(default_settings(), ideal))["systematics"]
    assert "no systematic errors" in sysm["source"]
    assert not any(sysm["zero_deg"]) and not any(v for k, v in sysm.items()
                                                 if isinstance(v, (int, float)) and not isinstance(v, bool))
    # a calibrated session is left as it is
    cal = {**default_settings(), "errors": "typical", "alignment": {"yaw_zero_deg": 0.0}}
    assert systematics.for_session(cal) == cal


def test_an_ideal_capture_carries_no_systematics(tmp_path):
    """The error-free simulator's dataset has the noise's lines only: no angle shifts, no stray
    or non-linearity bound (before: instrument.toml's, through the capture's merge of defaults)."""
    import xarray as xr

    from gonio.bench.dataset.export import export
    from gonio.bench.session.simulated import capture_sim

    settings = {**default_settings(), "errors": {"preset": "ideal"}}
    sample = {"model": "roughplastic", "options": {"distribution": "ggx"},
              "params": {"diffuse_reflectance": [0.5, 0.35, 0.2], "alpha": 0.1, "int_ior": 1.5}}
    capture_sim(tmp_path / "s", sample=sample, plan="quick", seed=3, settings=settings, progress=False)
    with xr.open_dataset(export(tmp_path / "s")) as ds:
        lines = {v for v in ds.data_vars if v.startswith("u_") and "gum_type" in ds[v].attrs}
        assert not {"u_stray_light", "u_linearity"} & lines, lines
        shifts = ds["angle_shift_shared"].values if "angle_shift_shared" in ds else None
        assert shifts is None or not shifts.size or not shifts.any()
