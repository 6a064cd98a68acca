"""An RGL file's samples and values do not depend on which loaded copy of it gonio reads.

Mitsuba 3.9.1's ``measured`` BSDF leaves ``m_reduction`` uninitialised for isotropic files and
mirrors its inputs when that garbage is >= 2, so two copies of one file could sample and
evaluate differently (vch: the normal-incidence samples turned by pi, f_r up to 19x apart),
which of the two depending on what the process had allocated before. gonio turns each pair so
that the mirroring is a no-op (``quarter_turns``). Here two copies that take the two paths are
found by a probe of the raw plugin, and gonio's results from both must agree to the bit.
Reads ../shared/data/rgl.
"""

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba")

RGL = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgl"
VCH = RGL / "vch_golden_yellow_rgb.bsdf"


def _mirrors(bsdf):
    """The raw plugin's path: the sign of one sample's x at normal incidence, (+0, +0, 1)."""
    import drjit as dr
    import mitsuba as mi

    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    bs, _ = bsdf.sample(mi.BSDFContext(), si, mi.Float(0.5), mi.Point2f(0.3, 0.7))
    return bool(bs.wo.x[0] > 0)


def _two_paths(path, keep):
    """Two loaded copies of ``path`` on which the raw plugin takes different paths (the heap
    moved between loads by small numpy allocations, all kept alive in ``keep``)."""
    from gonio.fitting.formats import RGLBRDF

    seen = {}
    for k in range(300):
        rgl = RGLBRDF(path)
        keep.append(rgl)
        seen.setdefault(_mirrors(rgl._bsdf), rgl)
        if len(seen) == 2:
            return seen[True], seen[False]
        keep.extend(np.zeros(k % 7 + 1) for _ in range(k % 5))
    pytest.skip("300 loaded copies all took one path: nothing to compare here")


@pytest.mark.skipif(not VCH.is_file(), reason="../shared/data/rgl is not here")
def test_every_loaded_copy_gives_the_same_samples_and_values(monkeypatch):
    import gonio.fitting.realdata as realdata

    keep = []
    a, b = _two_paths(VCH, keep)
    copies = iter([a, b])
    monkeypatch.setattr(realdata, "RGLBRDF", lambda path, variant=None: next(copies))
    ma = realdata.rgl_samples(VCH, n_side=8)
    mb = realdata.rgl_samples(VCH, n_side=8)
    for name in ("wi", "wo", "brdf", "weight", "cluster"):
        assert np.array_equal(getattr(ma, name), getattr(mb, name)), name
    assert np.array_equal(np.signbit(ma.wi), np.signbit(mb.wi))
    # any pair, any azimuth: RGLBRDF.eval agrees to the bit too
    rng = np.random.default_rng(7)
    t, p = rng.uniform(0.0, 1.4, (2, 400)), rng.uniform(-np.pi, np.pi, (2, 400))
    w = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)
    w[0, :5] = [[0.0, 0.0, 1.0], [0.3, 0.0, 0.95], [-0.3, 0.0, 0.95], [0.0, 0.3, 0.95], [0.0, -0.3, 0.95]]
    w[1, :5] = w[0, :5]
    w /= np.linalg.norm(w, axis=-1, keepdims=True)
    assert np.array_equal(a.eval(w[0], w[1]), b.eval(w[0], w[1]))
