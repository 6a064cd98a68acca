"""Instrument time (issue 38): a simulated capture journals each point's time and each run's
preparation by the simulator's clock, dataset.nc's ``instrument_time_s`` adds them up, and a
stop and a resume add up: the resumed run's time joins the time of the points already kept."""

from __future__ import annotations

import math
import os
import re
import signal

import numpy as np
import pytest

sim = pytest.importorskip("gonio.sim")

from benchfakes.cameras import InterruptingCamera

from gonio.bench.dataset.export import to_dataset
from gonio.bench.plan import plans
from gonio.bench.plan.ordering import cost_matrix
from gonio.bench.session.capture import CaptureInterrupted, capture, resume
from gonio.bench.session.journal import Journal, preparation_times
from gonio.bench.settings import default_settings

S = default_settings()
S["capture"]["flat_frames"] = 8             # a quick flat field: the preparation's time is what counts here
TWO = plans.Plan("two", [[30, 0, 40, 180], [45, 0, 20, 0]])
THREE = plans.Plan("three", [[30, 0, 40, 180], [45, 0, 20, 0], [20, 0, 30, 90]])


def _journalled(folder):
    """(rows in capture order, preparations) of a session's journal."""
    with Journal(folder / "journal.sqlite") as j:
        rows = sorted(j.points(), key=lambda r: r["finished"])
        return rows, preparation_times(j.events())


def test_a_simulated_capture_records_motion_settling_and_exposure(tmp_path):
    inst = sim.Instrument(S, seed=4).register("itime-capture")
    try:
        c0 = inst.clock.now()
        res = capture(tmp_path / "s", TWO, S, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=4,
                      progress=False, sleep=inst.clock.advance, sample_truth=inst.sample_spec)
        elapsed = inst.clock.now() - c0
    finally:
        inst.unregister()
    assert res.complete
    rows, preps = _journalled(tmp_path / "s")
    # each point: the move from the previous pose (homed: all axes at 0), the settle, its exposures;
    # what is left is the command lines (1 ms each) and the monitor readings, a few tens of ms
    pose = np.zeros(4)
    for r in rows:
        stage = np.array([r[k] for k in ("yaw", "tilt", "azimuth", "lamp")])
        motion = float(cost_matrix(pose[None], stage[None], S)[0, 0])
        exposure = sum(e["seconds"] for e in r["detail"]["exposures"])
        rest = r["detail"]["instrument_s"] - (motion + S["motion"]["settle_s"] + exposure)
        assert 0.0 <= rest < 0.05, (r["idx"], r["detail"]["instrument_s"], motion, exposure)
        assert motion > 1.0                          # the moves are most of it, not a rounding
        pose = stage
    assert len(preps) == 1 and preps[0][0] == 0 and preps[0][1] > 1.0     # homing, darks, flats, lamp on
    ds = to_dataset(tmp_path / "s")
    total = ds.attrs["instrument_time_s"]
    assert total == pytest.approx(preps[0][1] + sum(r["detail"]["instrument_s"] for r in rows), abs=1e-9)
    assert ds.attrs["instrument_time_preparation_s"] == pytest.approx(preps[0][1], abs=1e-12)
    by_idx = {r["idx"]: r["detail"]["instrument_s"] for r in rows}
    assert np.array_equal(ds["instrument_time"].values, [by_idx[i] for i in ds["plan_index"].values])
    assert ds["instrument_time"].attrs["units"] == "s" and "motion" in ds.attrs["instrument_time_comment"]
    # the simulator's clock ran for the capture: what is not counted is the few commands before
    # the preparation and after the last point (LED off)
    assert elapsed - 0.05 < total <= elapsed
    assert res.instrument_s == pytest.approx(total, abs=1e-9)


def _stop_twice_at_the_second_point():
    """A camera hook: Ctrl-C twice (stop now: the point in progress is lost) as the second
    measured point's first exposure starts."""
    seen: list[str] = []

    def hook(n, path):
        m = re.search(r"p(\d{5})_", os.fspath(path))
        if m and m.group(1) not in seen:
            seen.append(m.group(1))
            if len(seen) == 2:
                os.kill(os.getpid(), signal.SIGINT)
                os.kill(os.getpid(), signal.SIGINT)
    return hook


def test_a_stop_and_a_resume_add_up(tmp_path):
    folder = tmp_path / "s"
    inst = sim.Instrument(S, seed=5).register("itime-resume")
    try:
        cam = InterruptingCamera(inst.url("camera"), hook=_stop_twice_at_the_second_point())
        c0 = inst.clock.now()
        with pytest.raises(CaptureInterrupted):
            capture(folder, THREE, S, inst.url("zaber"), inst.url("meter"), cam, seed=5, progress=False,
                    sleep=inst.clock.advance, sample_truth=inst.sample_spec)
        first_run = inst.clock.now() - c0
        kept, preps = _journalled(folder)
        assert len(kept) == 1 and len(preps) == 1
        before = preps[0][1] + kept[0]["detail"]["instrument_s"]
        # the second point was cut short: its move and exposure are not in the kept time
        assert before < first_run - 1.0
        c1 = inst.clock.now()
        again = resume(folder, camera=inst.url("camera"), sleep=inst.clock.advance, progress=False)
        second_run = inst.clock.now() - c1
    finally:
        inst.unregister()
    assert again.complete and again.n_new == 2
    rows, preps = _journalled(folder)
    assert [p[0] for p in preps] == [0, 1]                 # the resume's preparation, after 1 kept point
    assert rows[0]["detail"]["instrument_s"] == kept[0]["detail"]["instrument_s"]   # kept as it was
    added = preps[1][1] + sum(r["detail"]["instrument_s"] for r in rows[1:])
    assert second_run - 0.05 < added <= second_run          # the resume's time, all of it
    assert again.instrument_s == pytest.approx(before + added, abs=1e-9)    # what the export writes (above)


def test_a_point_without_a_recorded_time_makes_the_total_nan_and_says_why():
    from gonio.bench.dataset import export as ex

    known = ex._instrument_time(np.array([1.5, 2.0]), [(0, 4.0), (1, 3.0)])
    assert known["instrument_time_s"] == 10.5 and known["instrument_time_preparation_s"] == 7.0
    assert "2 run(s)" in known["instrument_time_comment"] and "NaN" not in known["instrument_time_comment"]
    old = ex._instrument_time(np.array([1.5, ex._seconds(None)]), [(0, 4.0)])     # journalled before issue 38
    assert math.isnan(old["instrument_time_s"]) and old["instrument_time_preparation_s"] == 4.0
    assert "NaN: 1 point(s) were journalled by a gonio that did not record their time" in old["instrument_time_comment"]


def test_the_report_shows_the_instrument_time(tmp_path):
    from types import SimpleNamespace

    from gonio.bench.report import capture_section

    meas = SimpleNamespace(n_points=2, n_used=6, attrs={"instrument_time_s": 15.6135})
    rows = dict(capture_section(meas, tmp_path / "absent.nc")["rows"])
    assert rows["instrument time: motion, settling, exposures, preparation (s)"] == "15.61"
    assert not any("instrument" in k for k in dict(capture_section(
        SimpleNamespace(n_points=2, n_used=6, attrs={}), tmp_path / "absent.nc")["rows"]))   # an older dataset
