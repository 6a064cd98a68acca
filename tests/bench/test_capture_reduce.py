"""A point's reduction at full size: the regions as one run of columns per row, and the region
statistics accumulated inside the HDR merge's row blocks (both against the plain computations)."""

import numpy as np

from gonio.bench import _markers, kinematics, plans
from gonio.bench._settings import default_settings, merge_settings


def _grid_masks(stage, settings, pose, margin_px, binning=2):
    """`_markers.posed_masks`' test on the whole grid, as it was computed before the row runs:
    the grid's holder-plane coordinates from the map's affinity, every super-pixel's extreme
    corner offsets added, the four edge inequalities of each square."""
    cam, hold = settings["camera"], settings["holder"]
    h, w = cam["height"] // binning, cam["width"] // binning

    def plane(r, c):
        xy = kinematics.image_to_local(stage, np.asarray(r, float), np.asarray(c, float), settings)
        return xy if pose is None else pose.to_holder(xy)

    o = plane(0.0, 0.0)
    d_row, d_col = (plane(1.0, 0.0) - o) * binning, (plane(0.0, 1.0) - o) * binning
    corners = np.array([plane(dr, dc) - o for dr in (-0.5, binning - 0.5) for dc in (-0.5, binning - 0.5)])
    lo, hi = corners.min(0), corners.max(0)
    i, j = np.arange(h, dtype=float), np.arange(w, dtype=float)
    x = (o[0] + d_row[0] * i)[:, None] + (d_col[0] * j)[None, :]
    y = (o[1] + d_row[1] * i)[:, None] + (d_col[1] * j)[None, :]
    half = hold["sample_half"] - margin_px * cam["pixel_size"]
    in_y = (y + hi[1] <= half) & (y + lo[1] >= -half)
    return tuple(in_y & (x + hi[0] <= cx + half) & (x + lo[0] >= cx - half)
                 for cx in (-hold["offset"], hold["offset"]))


def test_region_rows_are_the_grid_test_bit_for_bit():
    """Each region's row is one run of columns whose ends a bisection finds with the grid's own
    floating-point operations: the masks equal the whole grid's test exactly (no tie decided
    otherwise), at the margins `roi_masks_fast` uses (1 +- 1e-3 px) and at 0, on the quick plan's
    poses, on random poses with and without a holder offset, on poses where the pixel grid lines
    up with the squares' edges (yaw 0: ties), and on the full-size sensor."""
    base = default_settings()
    rng = np.random.default_rng(11)
    for w, h, n_random in ((64, 48, 25), (320, 240, 10), (6000, 4000, 0)):
        px = float(base["camera"]["pixel_size"]) * base["camera"]["width"] / w
        s = merge_settings(base, {"camera": {"width": w, "height": h, "pixel_size": px}})
        stages = list(kinematics.inverse(*plans.load_plan("quick").angles.T))[:1 if w > 1000 else 12]
        stages += [np.array([0.0, 0.0, 0.0, 45.0]), np.array([0.0, 0.0, 90.0, 45.0])][:1 if w > 1000 else None]
        stages += [np.array([rng.uniform(-80, 80), rng.uniform(-80, 80), rng.uniform(-180, 180), 90.0])
                   for _ in range(n_random)]
        for stage in stages:
            poses = (None, _markers.HolderPose(rng.uniform(-0.05, 0.05, 2), rng.uniform(-5, 5), 0.0, ()))
            for pose in poses[:1 if w > 1000 else None]:
                margins = (1.001, 0.999, 0.0)[:2 if w > 1000 else None]
                got = _markers._posed_masks(stage, s, pose, 2, margins)
                for m, masks in zip(margins, got):
                    want = _grid_masks(stage, s, pose, m)
                    assert all(np.array_equal(a, b) for a, b in zip(want, masks)), (w, stage, pose, m)
                    assert all(a.any() for a in want) or w < 100     # the regions are in view
