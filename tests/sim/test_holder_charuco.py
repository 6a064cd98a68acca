"""The holder's ChArUco board: rendered by the simulator, found by the bench.

The simulated holder carries OpenCV's ChArUco board (``example_board``: 10 x 8 squares of
0.125, DICT_4X4_50 markers of 0.1) under the sample and reference squares; the holder is moved
by a known shift and turn (``sim_pose``, the simulator's truth) and the bench's pose, found from
the board's corners (``CharucoDetector``, ``matchImagePoints``, then the camera's own
orthographic map to the sample plane), follows it.

Tolerances: shift within half a pixel, turn within 0.1 deg. The corners are chessboard saddle
points refined to sub-pixel precision and 11 to 18 of them are fitted at these poses (measured
errors at most 0.14 pixel and 0.04 deg); a turn of 0.1 deg moves the board's outer corners, half
a holder unit from its centre, by 0.36 pixel, so the two bounds are of one size. The ArUco
markers' bounds (tests/bench/test_operator.py) are a pixel and 0.3 deg.
"""

import numpy as np
import pytest

import gonio.sim as gs
from gonio.bench.plan import markers as _markers
from gonio.bench.plan import kinematics
from gonio.bench.settings import default_settings, merge_settings
from gonio.core.errors import GonioError

AXES = ("yaw", "tilt", "azimuth", "lamp")
CAMERA = {"width": 600, "height": 450, "pixel_size": 0.0024}
STAGES = [(0.0, 0.0, 0.0, 40.0), (20.0, 10.0, 30.0, 60.0)]
MOVED = (0.04, -0.03, 3.0)


def _settings(**holder):
    s = merge_settings(default_settings(), {"camera": CAMERA})
    s["holder"] = {**s["holder"], "markers": _markers.example_board(), **holder}
    return s


def _green_superpixels(img):
    g = img[..., 1]
    return 0.25 * (g[0::2, 0::2] + g[0::2, 1::2] + g[1::2, 0::2] + g[1::2, 1::2])


@pytest.fixture(scope="module")
def frames():
    """{(stage, sim_pose): green super-pixel image} for both stages, holder in place and moved."""
    out = {}
    for pose in ((0.0, 0.0, 0.0), MOVED):
        inst = gs.Instrument(_settings(sim_pose=list(pose)), seed=1)
        for stage in STAGES:
            inst.set_pose(**dict(zip(AXES, stage)))
            out[stage, pose] = _green_superpixels(inst.radiance())
    return out


@pytest.mark.parametrize("stage", STAGES)
def test_pose_and_regions_follow_the_moved_holder(frames, stage):
    bench = _settings()
    px = CAMERA["pixel_size"]
    truth = _markers.HolderPose(np.array(MOVED[:2]), MOVED[2], 0.0, ())
    ts, tr = _markers.posed_masks(np.array(stage), bench, truth, margin_px=0.0)
    for pose in ((0.0, 0.0, 0.0), MOVED):
        r = _markers.find_regions(frames[stage, pose], np.array(stage), bench)
        assert r.source == "markers", r.why
        assert len(r.pose.ids) >= 8
        assert np.allclose(r.pose.shift, pose[:2], atol=0.5 * px)
        assert r.pose.angle_deg == pytest.approx(pose[2], abs=0.1)
    # the moved holder's regions lie inside its squares; the geometry's do not
    assert r.sample.sum() > 1000 and r.reference.sum() > 1000
    assert not (r.sample & ~ts).any() and not (r.reference & ~tr).any()
    gs_, gr = _markers.posed_masks(np.array(stage), bench, None)
    assert (gs_ & ~ts).sum() + (gr & ~tr).sum() > 100


def test_board_corners_map_to_the_holder(frames):
    """Corners found at normal incidence, holder in place, lie where the layout puts them."""
    stage = STAGES[0]
    bench = _settings()
    layout = _markers.layout_of(bench)
    holder, img = _markers.detect_board(frames[stage, (0.0, 0.0, 0.0)], layout)
    local = kinematics.image_to_local(stage, 2 * img[:, 1] + 0.5, 2 * img[:, 0] + 0.5, bench)
    assert len(holder) >= 12
    # every corner found is on a row boundary above or below the squares (0.375 = 3 squares)
    assert np.allclose(np.abs(holder[:, 1]), 0.375)
    assert np.abs(local - holder).max() < 0.5 * CAMERA["pixel_size"]


def test_board_out_of_view_falls_back_to_the_geometry():
    bench = _settings()
    flat = np.full((CAMERA["height"] // 2, CAMERA["width"] // 2), 0.05)
    r = _markers.find_regions(flat, np.array(STAGES[0]), bench)
    assert r.source == "geometry" and "board corners" in r.why
    sm, rm = kinematics.roi_masks(STAGES[0], bench)
    assert (r.sample == sm).all() and (r.reference == rm).all()


@pytest.mark.parametrize("bad", [
    {"board": [10, 8], "square": 0.1, "size": 0.12, "dictionary": "DICT_4X4_50"},       # markers larger than squares
    {"board": [10], "square": 0.1, "size": 0.08, "dictionary": "DICT_4X4_50"},
    {"board": [10, 8.5], "square": 0.1, "size": 0.08, "dictionary": "DICT_4X4_50"},
    {"board": [10, 8], "square": "0.1", "size": 0.08, "dictionary": "DICT_4X4_50"},
    {"board": [10, 8], "square": 0.1, "size": 0.08, "dictionary": "DICT_NOPE"},
    {"board": [10, 8], "square": 0.1, "size": 0.08, "dictionary": "DICT_4X4_50", "centre": [0, float("nan")]},
    {"board": [20, 20], "square": 0.1, "size": 0.08, "dictionary": "DICT_4X4_50"},       # 200 markers > 50
])
def test_malformed_board_is_one_line(bad):
    with pytest.raises(GonioError) as exc:
        _markers.layout_of(_settings(markers=bad))
    assert "\n" not in str(exc.value) and "[holder] markers" in str(exc.value)

