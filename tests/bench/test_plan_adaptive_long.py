"""The adaptive plan against the fixed plans on the simulated instrument (long): per sample and
plan, the simulated instrument time (`gonio.sim.physics.clock`) and the fit's error against the
truth (alpha; Ngan and log errors on `gonio.perf.real.dense_grid`). ``python
tests/bench/test_plan_adaptive_long.py [SAMPLE ...] [--plans adaptive:24,standard]`` prints the
table."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sim = pytest.importorskip("gonio.sim")

import gonio.models as gm
from gonio.bench.calibrate import with_errors_and_calibration
from gonio.bench.dataset.export import export
from gonio.bench.measure.systematics import for_session
from gonio.bench.plan import plans
from gonio.bench.samples import load_sample
from gonio.bench.session.capture import capture
from gonio.bench.settings import default_settings
from gonio.fitting import fit, load_dataset
from gonio.perf.real import dense_grid, measured_on_grid, metrics

SAMPLES = {
    "glossy": {"model": "roughplastic", "options": {"distribution": "ggx"},
               "params": {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": 0.08}},
    "matte": {"model": "roughplastic", "options": {"distribution": "ggx"},
              "params": {"diffuse_reflectance": [0.3, 0.5, 0.6], "alpha": 0.45}},
}
RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"


def run_one(sample: dict, plan: str, folder: Path, seed: int = 7, errors: str = "typical") -> dict:
    """Capture ``sample`` with ``plan`` (``adaptive:N`` or a preset) on a simulated instrument
    with the ``errors`` preset's systematic errors, export, fit roughplastic GGX; instrument
    time, points, alpha and the grid errors against the truth."""
    settings = with_errors_and_calibration(default_settings(), sim=True, seed=seed, errors=errors, calibration=None)
    settings = for_session(settings)
    kind, _, n = plan.partition(":")
    strategy = {"name": "adaptive", "points": int(n or 24), "seed": seed} if kind == "adaptive" else None
    pool = plans.load_plan("dense" if kind == "adaptive" else kind)
    inst = sim.Instrument(settings, sample=sample, seed=seed).register(f"cmp-{folder.name}")
    try:
        t0, w0 = inst.clock.now(), time.perf_counter()
        res = capture(folder, pool, settings, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=seed,
                      progress=False, sleep=inst.clock.advance, sample_truth=inst.sample_spec, strategy=strategy)
        inst_s, wall_s = inst.clock.now() - t0, time.perf_counter() - w0
    finally:
        inst.unregister()
    meas = load_dataset(export(folder))
    model = gm.get("roughplastic", distribution="ggx")
    r = fit(meas, model, rng=np.random.default_rng(0))
    wi, wo = dense_grid()
    if "bsdf_file" in sample:
        truth, alpha_true = measured_on_grid(sample["bsdf_file"], wi, wo), float("nan")
    else:
        truth_model = gm.get(sample["model"], **sample.get("options", {}))
        truth, alpha_true = truth_model.eval(wi, wo, sample["params"]), sample["params"]["alpha"]
    m = metrics(model.eval(wi, wo, r.params), truth, wi)
    k = r.space.names.index("alpha")
    return {"plan": plan, "points": res.n_done, "instrument_s": inst_s, "wall_s": wall_s,
            "alpha": float(r.x[k]), "u_alpha": float(r.std[k]), "alpha_err": float(r.x[k]) - alpha_true,
            "ngan": m["ngan"], "log": m["log"]}


def compare(samples: dict, plan_names, root: Path) -> list[dict]:
    rows = []
    for name, sample in samples.items():
        for plan in plan_names:
            row = {"sample": name, **run_one(sample, plan, root / f"{name}-{plan.replace(':', '')}")}
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


@pytest.fixture(scope="module")
def adaptive_and_standard(tmp_path_factory):
    return compare(SAMPLES, ["adaptive:24", "standard"], tmp_path_factory.mktemp("cmp"))


@pytest.mark.long
def test_adaptive_24_points_fit_as_well_as_the_standard_plan_in_less_instrument_time(adaptive_and_standard):
    rows = adaptive_and_standard
    for a, s in zip(rows[::2], rows[1::2]):
        assert a["points"] == 24 and a["instrument_s"] < s["instrument_s"]
        assert abs(a["alpha_err"]) < max(3 * a["u_alpha"], 0.05 * abs(a["alpha"]))
        assert a["ngan"] < 2 * s["ngan"] + 0.01


@pytest.mark.long
@pytest.mark.xfail(strict=True, reason="not met: 24 adaptive points take 0.59 of the standard plan's time")
def test_adaptive_24_points_take_half_the_standard_plans_instrument_time(adaptive_and_standard):
    # The target this file was written with, not met: the adaptive plan's later picks lie far apart
    # (docs/performance.md, "The long adaptive test's half-time target").
    rows = adaptive_and_standard
    assert all(a["instrument_s"] < 0.5 * s["instrument_s"] for a, s in zip(rows[::2], rows[1::2]))


if __name__ == "__main__":
    import tempfile

    args = sys.argv[1:]
    chosen = ["adaptive:24", "standard"]
    if "--plans" in args:
        i = args.index("--plans")
        chosen = args[i + 1].split(",")
        del args[i:i + 2]
    samples = {a: SAMPLES[a] if a in SAMPLES else load_sample(a) for a in args} or SAMPLES
    with tempfile.TemporaryDirectory() as d:
        compare({Path(k).stem: v for k, v in samples.items()}, chosen, Path(d))
