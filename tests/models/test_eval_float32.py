"""The public ``Model.eval`` in float32 (issue 18): float32 directions run the float32 compiled
kernel and give float32 f_r, equal to the float64 reference on the same directions to float32
precision (``models_testutil.F32_RTOL``, and why); on both round-trip paths (the gathering one
for small batches, the packed-words one of ``_roundtrip.packed_kernel`` for large ones), for
every registered model, with the reference's hostile rows, odd sizes, blocks, threads and
any memory layout; mixed types promote to float64."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import gonio.models as gm
from gonio.models.engine import fast as _fast
from gonio.models.engine import roundtrip as _roundtrip

from models_testutil import assert_float32_agrees, random_hemisphere, random_params

pytestmark = [pytest.mark.skipif(not _fast.available(), reason="Dr.Jit LLVM backend unavailable"),
              pytest.mark.codegen]


@pytest.fixture(autouse=True)
def _copies_from_soa_min_pairs(monkeypatch):
    """Here :data:`_roundtrip.SOA_MIN_PAIRS` alone picks the path (``COPIES = "copies"``):
    1 forces the copies, 1 << 40 the gathers, whatever this machine's vector width."""
    monkeypatch.setattr(_roundtrip, "COPIES", "copies")


def _configs():
    for name in gm.names():
        cls = gm.get(name).__class__
        for values in itertools.product(*cls.OPTIONS.values()):
            yield name, dict(zip(cls.OPTIONS, values))


CONFIGS = list(_configs())
IDS = ["-".join([n] + [f"{k}={v}" for k, v in o.items()]) for n, o in CONFIGS]


def _pairs(rng, n):
    """float32 pairs with the hostile rows: NaN and inf components (f_r = 0), below the
    horizon, grazing (cos 1e-7: still above it in float32), normal, mirror."""
    wi, wo = random_hemisphere(rng, n), random_hemisphere(rng, n)
    g = [np.sin(np.pi / 2 - 1e-7), 0.0, np.cos(np.pi / 2 - 1e-7)]
    wi[:8] = [[np.nan, 0, 1], [0, 0, 1], [0.6, 0, -0.8], g, [0, np.inf, 1], [0, 0, 1], [0.6, 0, 0.8], [0, 0, -1]]
    wo[:8] = [[0, 0, 1], [0, 0, np.nan], [0, 0, 1], g, [0, 0, 1], [0, 0, 1], [-0.6, 0, 0.8], [0, 0, 1]]
    return wi.astype(np.float32), wo.astype(np.float32)


def _reference(m, wi, wo, p):
    """The float64 reference on the float32 directions (promoted). Row 1 (wo with a NaN z)
    is taken as 0 without asking the reference: roughplastic's raises an IndexError on it
    (issue 18's notes); every compiled path gives 0 there."""
    keep = np.arange(wi.shape[0]) != 1
    ref = np.zeros((wi.shape[0], 3))
    ref[keep] = m.eval_reference(wi[keep], wo[keep], p)
    return ref


@pytest.mark.parametrize("name,options", CONFIGS, ids=IDS)
def test_float32_eval_agrees_with_the_reference_on_both_paths(name, options, monkeypatch):
    """Every registered model (those without a kernel of their own through the reference or
    their layers): float32 out, the reference to F32_RTOL, 0 on the hostile rows; the
    packed path (odd N: one padding row) equals the gathering path bit for bit."""
    m = gm.get(name, **options)
    rng = np.random.default_rng(1818)
    wi, wo = _pairs(rng, 3001)
    for p in [m.defaults()] + [random_params(m, rng, alpha_range=(1e-3, 1.0)) for _ in range(2)]:
        ref = _reference(m, wi, wo, p)
        monkeypatch.setattr(_roundtrip, "SOA_MIN_PAIRS", 1 << 40)
        gathered = m.eval(wi, wo, p)
        monkeypatch.setattr(_roundtrip, "SOA_MIN_PAIRS", 1)
        packed = m.eval(wi, wo, p)
        for got in (gathered, packed):
            assert_float32_agrees(got, ref, wi)
            assert got.flags.c_contiguous and np.all(got[[0, 1, 2, 4, 7]] == 0)
        if m.structure.kernel is not None:
            np.testing.assert_array_equal(packed, gathered)
        # the float32 result is the float64 path's, rounded, to F32_RTOL: float64 stays as it was
        f64 = m.eval(wi.astype(np.float64), wo.astype(np.float64), p)
        assert f64.dtype == np.float64
        assert_float32_agrees(packed, f64, wi)


def test_layouts_blocks_threads_and_sizes(monkeypatch):
    """Strided, Fortran-ordered and 4-byte-aligned (not 8: the packed words are read
    unaligned) float32 inputs, blocks of 1000 pairs with an odd last block, copies on 3
    threads: bit for bit the contiguous evaluation; the inputs are never written."""
    m = gm.get("roughplastic", distribution="ggx")
    rng = np.random.default_rng(1819)
    wi, wo = _pairs(rng, 2501)
    p = random_params(m, rng)
    monkeypatch.setattr(_roundtrip, "SOA_MIN_PAIRS", 1)
    want = m.eval(wi, wo, p)
    wi0, wo0 = wi.copy(), wo.copy()
    monkeypatch.setattr(_roundtrip, "SOA_BLOCK", 1000)
    np.testing.assert_array_equal(m.eval(wi, wo, p), want)
    monkeypatch.setattr(_roundtrip, "_threads", lambda: 3)
    np.testing.assert_array_equal(m.eval(wi, wo, p), want)
    monkeypatch.setattr(_roundtrip, "SOA_BLOCK", 1 << 16)
    np.testing.assert_array_equal(m.eval(np.asfortranarray(wi), np.asfortranarray(wo), p), want)
    np.testing.assert_array_equal(m.eval(wi[::2], wo[::2], p), want[::2])
    raw = np.empty(3 * 2501 + 1, np.float32)
    off = raw[1:] if raw[1:].ctypes.data % 8 else raw[:-1]
    un = off.reshape(2501, 3)
    un[...] = wi
    assert un.ctypes.data % 8 == 4
    np.testing.assert_array_equal(m.eval(un, wo, p), want)
    np.testing.assert_array_equal(wi, wi0)
    np.testing.assert_array_equal(wo, wo0)
    for n in (1, 2, 3, 31, 32, 33):  # below and above compiled_min_pairs, one and two rows
        got = m.eval(wi[-n:], wo[-n:], p)
        assert got.dtype == np.float32 and got.shape == (n, 3)
        assert_float32_agrees(got, m.eval_reference(wi[-n:], wo[-n:], p), wi[-n:])


def test_dtype_rules_and_bad_input(monkeypatch):
    """The type follows the directions as numpy's arithmetic does: both float32 -> float32;
    float32 with float64, integers or lists -> float64 (the float64 path, bit for bit);
    backend="numpy" and GONIO_EVAL_BACKEND=numpy: the float64 reference rounded to float32.
    Bad input: a one-line ValueError before any work."""
    m = gm.get("roughconductor", distribution="ggx")
    rng = np.random.default_rng(1820)
    wi, wo = _pairs(rng, 500)
    p = random_params(m, rng)
    assert gm.eval_dtype(wi, wo) == np.float32 and gm.eval_dtype(wi, wo.astype(np.float64)) == np.float64
    assert gm.eval_dtype(wi.tolist(), wo) == np.float64
    f64 = m.eval(wi.astype(np.float64), wo.astype(np.float64), p)
    np.testing.assert_array_equal(m.eval(wi, wo.astype(np.float64), p), f64)
    np.testing.assert_array_equal(m.eval(wi.tolist(), wo, p), f64)
    assert m.eval(np.array([[0, 0, 1]]), np.array([[0, 0, 1]]), p).dtype == np.float64
    assert m.eval(wi.astype(np.float16), wo.astype(np.float16), p).dtype == np.float64
    ref32 = m.eval_reference(wi, wo, p).astype(np.float32)
    assert m.eval_reference(wi, wo, p).dtype == np.float64  # the reference stays float64
    np.testing.assert_array_equal(m.eval(wi, wo, p, backend="numpy"), ref32)
    monkeypatch.setenv("GONIO_EVAL_BACKEND", "numpy")
    np.testing.assert_array_equal(m.eval(wi, wo, p), ref32)
    monkeypatch.delenv("GONIO_EVAL_BACKEND")
    assert m.eval(wi[:0], wo[:0], p, backend="drjit").dtype == np.float32
    for bad_i, bad_o, match in ((wi[:, :2], wo[:, :2], "shape"), (wi, wo[:10], "same shape"),
                                (np.full((2, 3), "a"), wo[:2], "convert")):
        with pytest.raises(ValueError, match=match) as err:
            m.eval(bad_i, bad_o, p)
        assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="alpha"):
        m.eval(wi, wo, {"alpha": np.float32(np.nan)})
