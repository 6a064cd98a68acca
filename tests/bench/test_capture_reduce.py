"""A point's reduction at full size: the regions as one run of columns per row, and the region
statistics accumulated inside the HDR merge's row blocks (both against the plain computations)."""

import numpy as np

from gonio.bench.plan import markers as _markers
from gonio.bench.plan import kinematics
from gonio.bench.plan import plans
from gonio.bench.settings import default_settings, merge_settings


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


def _bracket(rate, rng, h=37, w=53, times=(0.001, 0.004, 0.016), power=0.01):
    """Exposures of a scene of ``rate`` (3, h, w) DN / (s W) on a 14-bit sensor with the noise
    model's shot and read noise (gain 2 e/DN, read noise 3 e), its two greens averaged, clipped
    at full scale; a dark frame per exposure (10 DN/s)."""
    from gonio.bench.measure.hdr import Exposure
    from gonio.bench.drivers.camera import RawFrame

    full = 16383 - 512

    def shot(mean):
        return np.round((rng.poisson(np.maximum(mean, 0) * 2.0) + rng.normal(0, 3.0, mean.shape)) / 2.0)

    out = []
    for t in times:
        mean = rate * t * power + 10.0 * t
        dn, g2 = np.minimum(shot(mean), full), np.minimum(shot(mean[1]), full)
        sig, peak = dn.copy(), dn.copy()
        sig[1], peak[1] = 0.5 * (dn[1] + g2), np.maximum(dn[1], g2)
        dark = shot(np.full((3, h, w), 10.0 * t))
        n_raw = np.array([1.0, 2.0, 1.0])
        out.append(Exposure(t, power, RawFrame(sig.astype(np.float32), peak.astype(np.float32), n_raw, 512.0, 16383.0),
                            RawFrame(dark.astype(np.float32), None, n_raw, 512.0, 16383.0)))
    return out


def _odd_masks(rng, h, w, rows_per_block):
    """Regions of odd shapes: a random scatter, a disc cut by the frame's edge, single pixels on
    the rows either side of every block edge, a diagonal, one pixel, none, the whole frame."""
    i, j = np.mgrid[:h, :w]
    edges = np.zeros((h, w), bool)
    for r in range(rows_per_block, h, rows_per_block):
        edges[r - 1, (r * 7) % w] = edges[r, (r * 11) % w] = True
    one = np.zeros((h, w), bool)
    one[h // 2, w // 3] = True
    return {"scatter": rng.random((h, w)) < 0.3, "disc": (i - 3) ** 2 + (j - w + 4) ** 2 < 15 ** 2,
            "block edges": edges, "diagonal": i == j, "one pixel": one, "none": np.zeros((h, w), bool),
            "all": np.ones((h, w), bool)}


def test_fused_region_stats_are_the_two_pass_ones(monkeypatch):
    """A point's region statistics accumulated inside the merge's row blocks (each block's sums,
    combined per Chan, Golub & LeVeque 1983) equal `region_stats` over the merged, flat-fielded
    planes: the same counts and saturated counts, means and standard errors to float64 rounding
    (|difference| <= 1e-12 of the values' mean magnitude: summing at most 37 x 53 float32 values
    in float64, in two groupings, differs by at most ~n eps = 2e-13 of it; float32 rounding would
    be ~1e-7). On dim (radiance near 0, negative values), mid and saturated scenes (red saturated
    in every exposure in places: NaN, left out), with and without a flat field and a
    non-linearity, in one thread and two, with blocks of 3 rows and masks of odd shapes there."""
    from gonio.bench.measure import hdr as _hdr
    from gonio.bench.measure.hdr import NoiseModel, merge
    from gonio.bench.measure.point import merged_region_stats, region_stats

    rng = np.random.default_rng(17)
    h, w = 37, 53
    monkeypatch.setattr(_hdr, "_BLOCK", 3 * w)               # 3 rows a block: 13 blocks, the last of 1 row
    masks = _odd_masks(rng, h, w, 3)
    u = rng.random((1, h, w))
    scenes = {"dim": np.array([2e3, 1e3, 5e2])[:, None, None] * u,
              "mid": np.array([6e7, 3e7, 1e7])[:, None, None] * (0.5 + u),
              "saturated": np.array([2e9, 4e7, 1e7])[:, None, None] * (0.5 + u)}
    gain = (1.0 + 0.02 * rng.standard_normal((3, h, w))).astype(np.float32)
    noise = NoiseModel(2.0, 3.0)
    seen_nan = False
    for name, rate in scenes.items():
        exposures = _bracket(rate, rng, h, w)
        for flat, gamma, parallel in ((None, 0.0, 1 << 62), (gain, 0.0, 0), (gain, 0.01, 1 << 62)):
            monkeypatch.setattr(_hdr, "_PARALLEL", parallel)
            hdr = merge(exposures, noise, 0.9, gamma=gamma).flat_fielded(flat)
            fused = merged_region_stats(exposures, noise, list(masks.values()), 0.9, gamma, flat)
            for (what, mask), got in zip(masks.items(), fused):
                want = region_stats(hdr, mask)
                ctx = (name, what, flat is not None, gamma, parallel)
                assert np.array_equal(got["n"], want["n"]) and got["n_saturated"] == want["n_saturated"], ctx
                seen_nan |= want["n_saturated"] > 0 and want["n"].min() > 0
                scale = np.array([np.mean(np.abs(c[mask & np.isfinite(c)])) if want["n"][k] else 0.0
                                  for k, c in enumerate(hdr.radiance)])
                for q in ("mean", "se", "se_model"):
                    assert np.array_equal(np.isnan(got[q]), np.isnan(want[q])), (ctx, q)
                    tol = 1e-12 * (scale if q == "mean" else np.abs(np.nan_to_num(want[q])))
                    assert np.all(np.abs(np.nan_to_num(got[q] - want[q])) <= tol), (ctx, q, got[q], want[q])
    assert seen_nan                                          # the saturated scene left values out


def test_probe_levels_are_the_whole_frame_extremes(monkeypatch):
    """The probe's brightest raw value, brightest over its dark and darkest dark-subtracted value
    in the regions, taken a block of rows at a time, are those of the whole planes exactly (max
    and min round nothing), for regions of odd shapes: runs across block edges, one pixel, a run
    from the first value, one to the last; an empty region raises as before."""
    import pytest

    from gonio.bench.measure import point as _measure
    from gonio.bench.measure.point import _extreme, _runs, probe_levels

    rng = np.random.default_rng(23)
    h, w = 37, 53
    monkeypatch.setattr(_measure, "_PROBE_BLOCK", 3 * w)
    exposures = _bracket(np.array([2e9, 4e7, 1e3])[:, None, None] * rng.random((1, h, w)), rng, h, w)
    masks = dict(_odd_masks(rng, h, w, 3))
    ends = np.zeros((h, w), bool)
    ends[0, :5] = ends[-1, -4:] = ends[10:20, 40:] = True
    masks["ends"] = ends
    for k in range(60):                                      # short runs: their ends decide the extremes
        m = np.zeros((h, w), bool)
        for _ in range(3):
            r, c = rng.integers(h), rng.integers(w - 2)
            m[r, c:c + rng.integers(2, 9)] = True
        masks[f"short runs {k}"] = m
    for e in exposures:
        f, d = e.frame, e.dark
        for what, mask in masks.items():
            runs = _runs(mask)
            if not mask.any():
                with pytest.raises(ValueError):
                    probe_levels(f, d, runs)
                continue
            want = (_extreme(np.maximum, f.peak, runs), _extreme(np.maximum, f.peak - np.maximum(d.signal, 0), runs),
                    _extreme(np.minimum, f.signal - d.signal, runs))
            assert want == (f.peak[:, mask].max(), (f.peak - np.maximum(d.signal, 0))[:, mask].max(),
                            (f.signal - d.signal)[:, mask].min())
            assert probe_levels(f, d, runs) == want, what


def test_blocked_decode_is_the_tile_mean_and_max(monkeypatch):
    """`_raw._planes`, a block of rows at a time: each channel is the mean of its positions in the
    CFA tile minus their black levels, and its peak their maximum (computed here in float64 from
    the mosaic), exactly, for RGGB, GRBG and BGGR tiles with a black level per position, blocks
    of 3 rows, windows cut at block edges, clipped at the frame, of one row, and empty."""
    from gonio.bench.drivers import raw as _raw

    rng = np.random.default_rng(29)
    h, w = 37, 53
    monkeypatch.setattr(_raw, "_DECODE_BLOCK", 3 * w)
    img = rng.integers(0, 16384, (2 * h, 2 * w)).astype(np.uint16)
    blacks = np.array([[512.0, 510.0], [514.0, 508.0]])
    for pattern in ((0, 1, 1, 2), (1, 0, 2, 1), (2, 1, 1, 0)):
        chan = np.array(pattern).reshape(2, 2)
        for box in ((0, h, 0, w), (3, 34, 5, 50), (-4, h + 9, -1, 3), (h // 2, h // 2 + 1, 0, w), (5, 5, 0, w)):
            got = _raw._planes(img, chan, blacks, 16383.0, box, True, "x.dng")
            r0, r1, c0, c1 = max(0, box[0]), min(h, box[1]), max(0, box[2]), min(w, box[3])
            want = np.zeros((3, max(0, r1 - r0), max(0, c1 - c0)))
            top = np.full(want.shape, -np.inf)
            for dr in range(2):
                for dc in range(2):
                    k = chan[dr, dc]
                    v = img[2 * r0 + dr:2 * r1:2, 2 * c0 + dc:2 * c1:2].astype(float) - blacks[dr, dc]
                    want[k] += v / np.sum(chan == k)
                    top[k] = np.maximum(top[k], v)
            assert got.signal.dtype == np.float32 and np.array_equal(got.signal, want), (pattern, box)
            assert np.array_equal(got.peak, top) and np.array_equal(got.n_raw, [1, 2, 1])
            assert _raw._planes(img, chan, blacks, 16383.0, box, False, "x.dng").peak is None
