"""`gonio bench capture`, small: one point on the default camera, the simulator in real time."""

import math

from gonio.perf import capture as _capture_speed
from gonio.bench.session import run as _session
from gonio.bench.drivers import stages


def test_one_point_is_timed_and_the_pipeline_restored():
    originals = (_session.decode_raw, _session.merged_region_stats, _session._Session._reduce, _session._Session.run,
                 stages.Goniometer.move_to)
    lines = []
    (row,) = _capture_speed.run(n_points=1, full=None, out=lines.append)
    assert row["camera"] == "64x48" and row["points"] == 1
    assert all(math.isfinite(v) for v in row.values() if isinstance(v, float))
    # the bound is the stages' motion (a move from home, > 1 s at 20 deg/s) plus the exposures
    assert row["motion_s"] > 1.0 and row["exposure_s"] > 0
    assert row["bound_s"] == row["motion_s"] + row["exposure_s"]
    assert row["wall_s"] >= row["bound_s"] and row["ratio"] == row["projected_s"] / row["bound_s"]
    # wall table, CPU table, then each camera's verdict against the motion + exposure bound
    assert len(lines) == 7 and "64x48" in lines[2] and "64x48" in lines[5]
    assert lines[6].startswith("64x48:") and "target <= 1.1x" in lines[6] and "peak memory" in lines[6]
    # CPU: the critical path is part of the host's CPU; the phases ran; the idle bound is >= 1
    assert 0 < row["crit_cpu_s"] <= row["host_cpu_s"] and row["merge_cpu_s"] > 0 and row["decode_cpu_s"] > 0
    assert 0 <= row["lag_s"] < row["wall_s"] and (row["idle_ratio"] is None or row["idle_ratio"] >= 1.0)
    assert (_session.decode_raw, _session.merged_region_stats, _session._Session._reduce, _session._Session.run,
            stages.Goniometer.move_to) == originals
