"""The compiled (Dr.Jit LLVM) path against the numpy reference, and the benchmark."""

from __future__ import annotations

import io
import itertools

import numpy as np
import pytest

import gonio.models as gm
from gonio.models.engine import fast as _fast

from models_testutil import assert_float32_agrees, random_hemisphere, random_params

pytestmark = [pytest.mark.skipif(not _fast.available(), reason="Dr.Jit LLVM backend unavailable"),
              pytest.mark.codegen]


def configs():
    """Every model that declares a compiled kernel (``structure.kernel``; the kernel is
    optional, issue 13: roughplastic2 has none of its own)."""
    for name in gm.names():
        cls = gm.get(name).__class__
        if gm.get(name).structure.kernel is None:
            continue
        for values in itertools.product(*cls.OPTIONS.values()):
            yield name, dict(zip(cls.OPTIONS, values))


CONFIGS = list(configs())
IDS = ["-".join([n] + [f"{k}={v}" for k, v in o.items()]) for n, o in CONFIGS]
#: the kernels that write their derivatives too (``structure.derivatives``; tabulated's
#: gives values only: its parameters act through tables built in numpy)
DERIV = [(n, o) for n, o in CONFIGS if gm.get(n, **o).structure.derivatives]
DERIV_IDS = [i for i, (n, o) in zip(IDS, CONFIGS) if (n, o) in DERIV]


def hard_pairs(rng):
    g = np.array([np.sin(np.pi / 2 - 1e-7), 0.0, np.cos(np.pi / 2 - 1e-7)])
    z = np.array([0.0, 0.0, 1.0])
    s = np.array([0.6, 0.0, 0.8])
    extra_i = np.array([g, z, s, s, [1.0, 0, 0], [0.6, 0, -0.8], [np.nan, 0, 1], -z])
    extra_o = np.array([g, z, s, [-0.6, 0, 0.8], s, s, z, z])
    wi = np.concatenate([random_hemisphere(rng, 3000), extra_i])
    wo = np.concatenate([random_hemisphere(rng, 3000), extra_o])
    return wi, wo


@pytest.mark.parametrize("name,options", CONFIGS, ids=IDS)
def test_matches_reference(name, options):
    m = gm.get(name, **options)
    rng = np.random.default_rng(5)
    wi, wo = hard_pairs(rng)
    # Beckmann roughplastic: Dr.Jit's erfinv differs from scipy's in the last digits
    # inside the transmittance quadrature (table differences ~1e-9, f_r ~1e-8)
    rtol = 1e-7 if (name == "roughplastic" and options["distribution"] == "beckmann") else 1e-10
    for p in [m.defaults()] + [random_params(m, rng, alpha_range=(1e-4, 1.0)) for _ in range(4)]:
        ref = m.eval_reference(wi, wo, p)
        got = _fast.eval(m, wi, wo, p)
        assert np.all(np.isfinite(got)) and np.all(got >= 0)
        np.testing.assert_allclose(got, ref, rtol=rtol, atol=1e-300)
    # float32 input: the float32 kernel (issue 18), the reference to float32 precision; the
    # same directions promoted: the float64 kernel, as above; N = 0 behaves as the reference
    w32 = wi[:100].astype(np.float32), wo[:100].astype(np.float32)
    assert_float32_agrees(_fast.eval(m, *w32, p), m.eval_reference(*w32, p), w32[0])
    np.testing.assert_allclose(_fast.eval(m, *(w.astype(np.float64) for w in w32), p), m.eval_reference(*w32, p), rtol=rtol)
    assert _fast.eval(m, np.zeros((0, 3)), np.zeros((0, 3)), p).shape == (0, 3)


@pytest.mark.parametrize("name", ["roughplastic", "diffuse"])
def test_public_eval_runs_the_compiled_kernel_above_its_crossover(name, monkeypatch):
    """``Model.eval`` (issue 18): from ``compiled_min_pairs`` pairs it is the compiled kernel
    (bit for bit ``fast.eval``), below it the reference (bit for bit ``eval_reference``);
    the replayed recording follows each new batch size (sizes taken in turns, a recording
    made at one size must not return another's length); ``backend`` and
    ``GONIO_EVAL_BACKEND=numpy`` choose the reference; a bad backend is refused."""
    m = gm.get(name)
    rng = np.random.default_rng(31)
    k = m.compiled_min_pairs
    p = random_params(m, rng)
    for n in (k, 3 * k + 5, k + 1, 2 * k, k - 1, 5000):
        wi, wo = random_hemisphere(rng, n), random_hemisphere(rng, n)
        wi[n // 2] = [np.nan, 0.0, 1.0]  # degenerate row: 0 on both paths
        ref = m.eval_reference(wi, wo, p)
        got = m.eval(wi, wo, p)
        assert got.shape == (n, 3) and got.dtype == np.float64 and np.all(got[n // 2] == 0)
        np.testing.assert_array_equal(got, _fast.eval(m, wi, wo, p) if n >= k else ref)
        # roughplastic's default is Beckmann: Dr.Jit's erfinv in its tables (see above)
        np.testing.assert_allclose(got, ref, rtol=1e-7 if name == "roughplastic" else 1e-12, atol=1e-300)
        np.testing.assert_array_equal(m.eval(wi, wo, p, backend="numpy"), ref)
    np.testing.assert_array_equal(m.eval(wi[:3], wo[:3], p, backend="drjit"), _fast.eval(m, wi[:3], wo[:3], p))
    monkeypatch.setenv("GONIO_EVAL_BACKEND", "numpy")
    np.testing.assert_array_equal(m.eval(wi, wo, p), ref)
    with pytest.raises(ValueError, match="backend"):
        m.eval(wi, wo, p, backend="cuda")


@pytest.mark.parametrize("name,options", DERIV, ids=DERIV_IDS)
def test_gradient_matches_finite_differences(name, options):
    """Reverse-mode gradient of sum(c * f_r) against central differences of the numpy
    reference (h = 1e-7 relative; roughplastic's tables have small jumps in alpha and
    eta where quadrature nodes cross a mask, so h must stay small)."""
    m = gm.get(name, **options)
    rng = np.random.default_rng(11)
    wi, wo = random_hemisphere(rng, 2000), random_hemisphere(rng, 2000)
    cot = rng.normal(size=(2000, 3))
    p = m.validate(random_params(m, rng, alpha_range=(0.05, 1.0)))
    # keep the finite differences inside the box
    p = {k: (np.clip(v, 0.05, None) if np.ndim(v) else max(v, 0.05)) if k != "sigma" else max(v, 0.1) for k, v in p.items()}
    p = m.validate(p)
    f, grad = _fast.value_and_grad(m, wi, wo, p, cot)
    np.testing.assert_allclose(f, m.eval_reference(wi, wo, p), rtol=1e-7)
    for par in m.parameters:
        chans = range(3) if par.per_channel else [None]
        for c in chans:
            x0 = p[par.name] if c is None else p[par.name][c]
            h = 1e-7 * max(abs(x0), 1e-3)
            q1, q2 = dict(p), dict(p)
            if c is None:
                q1[par.name], q2[par.name] = x0 + h, x0 - h
            else:
                q1[par.name], q2[par.name] = p[par.name].copy(), p[par.name].copy()
                q1[par.name][c] += h
                q2[par.name][c] -= h
            fd = (np.sum(cot * m.eval_reference(wi, wo, q1)) - np.sum(cot * m.eval_reference(wi, wo, q2))) / (2 * h)
            ad = grad[par.name] if c is None else grad[par.name][c]
            assert ad == pytest.approx(fd, rel=2e-4, abs=1e-6 * max(1.0, abs(fd))), (par.name, c)


def test_bench_runs():
    from gonio.perf import models as bench

    buf = io.StringIO()
    rows = bench.run(n=2000, repeat=1, cases=(("diffuse", {}), ("roughconductor", {"distribution": "ggx"})), file=buf)
    text = buf.getvalue()
    assert "roughconductor" in text and "Mevals/s" in text and "limit (memory bandwidth)" in text
    assert "ev32/mi" in text and "numpy round trip included" in text and "load average" in text
    # what each column includes is printed: Mitsuba resident (no round trip) and with its own
    assert "NO numpy round trip" in text and "mi+np" in text and "ev32/mnp" in text
    # and what the gradient reads: the prepared geometry, against both evaluations
    assert "grad/evp" in text and "prepared once per batch" in text
    assert len(rows) == 2
    for r in rows:
        assert all(r[k] > 0 for k in ("numpy", "drjit64", "eval32", "drjit32", "jac32"))
        assert r["limits"]["eval32"] == pytest.approx(r["limits"]["bandwidth"] / 36)
        assert r["jac_cost"] > 0 and r["grad_chi"] > 0 and r["grad_chi64"] > 0
        assert r["grad_cost_p"] > 0 and r["grad_cost_p64"] > 0
        if r["mitsuba"] is not None:
            assert r["mitsuba_np"] > 0 and r["eval32_np_ratio"] > 0 and r["eval_np_ratio"] > 0
        # the stated limit: the copy bandwidth over the bytes a pair moves (36 B float32, 72 B float64)
        assert r["limits"]["drjit32"] == pytest.approx(r["limits"]["bandwidth"] / 36)
        assert r["limits"]["eval"] == pytest.approx(r["limits"]["bandwidth64"] / 72)


def test_bench_states_issue_18s_goals():
    """The goals line reads this run's rows: the worst roughplastic row decides the public
    eval's verdict in each precision, the worst model the gradient's."""
    from gonio.perf import models as bench

    def row(model, ev32, ev64, e64, g32, g64):
        return {"model": model, "eval32_ratio": ev32, "eval_ratio": ev64, "eval64_ratio": e64,
                "grad_cost": g32, "grad_cost64": g64}

    buf = io.StringIO()
    bench._print_goals([row("roughplastic", 0.62, 0.36, 0.46, 2.4, 1.9), row("roughplastic", 0.67, 0.499, 0.5, 2.3, 1.8),
                        row("diffuse", 0.31, 0.17, 0.55, 2.25, 3.2)], buf)
    text = buf.getvalue()
    assert "float32 directions (Mitsuba's own precision) 0.620-0.670, met" in text
    assert "float64 directions 0.360-0.499, NOT met" in text and "alone reaches 0.460-0.500" in text
    assert "float64 at most 3.20, NOT met" in text
    buf = io.StringIO()
    bench._print_goals([row("diffuse", 0.31, 0.17, 0.55, 2.25, 2.3)], buf)   # no roughplastic: nothing said
    assert buf.getvalue() == ""


def test_bench_parameters_are_coloured():
    """The benchmark's parameters differ per channel (so no path can evaluate one channel
    for three) and stay inside the bounds."""
    from gonio.perf.models import coloured_params

    for name, options in DERIV:  # the benchmarked kinds (gonio/perf/models.py times jacobians too)
        m = gm.get(name, **options)
        p = coloured_params(m)
        for par in m.parameters:
            if par.per_channel and np.any(m.defaults()[par.name] > 0):
                assert len(set(np.round(p[par.name], 12))) == 3, (name, par.name)


# -- resident batches: float32 / float64 evaluation and the Jacobian -------------------------


@pytest.mark.parametrize("name,options", CONFIGS, ids=IDS)
def test_resident_float32_matches_reference(name, options):
    """float32 kernel on float32 directions against the float64 reference on the same
    (rounded) directions: relative error <= 2e-5 wherever f_r cos(theta_i) > 1e-6, the
    threshold of the Mitsuba agreement tests (measured: <= 7.5e-6, Beckmann conductors;
    float32 epsilon is 6e-8, the formulas take ~100 roundings)."""
    m = gm.get(name, **options)
    rng = np.random.default_rng(21)
    wi, wo = hard_pairs(rng)
    wi, wo = (w.astype(np.float32).astype(np.float64) for w in (wi, wo))
    dirs = _fast.Directions(wi, wo, np.float32)
    for p in [m.defaults()] + [random_params(m, rng, alpha_range=(1e-3, 1.0)) for _ in range(3)]:
        ref = m.eval_reference(wi, wo, p)
        got = _fast.eval_resident(m, dirs, p)
        assert got.dtype == np.float32 and got.shape == ref.shape
        assert np.all(np.isfinite(got)) and np.all(got >= 0)
        big = ref * np.clip(wi[:, 2:3], 0, None) > 1e-6
        np.testing.assert_allclose(got[big], ref[big], rtol=2e-5)
        assert np.all(got[ref == 0] == 0)


@pytest.mark.parametrize("name,options", CONFIGS, ids=IDS)
def test_resident_float64_equals_eval(name, options):
    """The resident float64 path is the same kernel as ``eval``; a new parameter value and a
    new batch size reuse the frozen kernel and still give the right answer."""
    m = gm.get(name, **options)
    rng = np.random.default_rng(22)
    for n in (37, 2000):
        wi, wo = random_hemisphere(rng, n), random_hemisphere(rng, n)
        dirs = _fast.Directions(wi, wo, np.float64)
        for p in [random_params(m, rng, alpha_range=(1e-3, 1.0)) for _ in range(3)]:
            np.testing.assert_allclose(_fast.eval_resident(m, dirs, p), _fast.eval(m, wi, wo, p), rtol=1e-12, atol=1e-300)


GEOMETRY = [(n, o) for n, o in CONFIGS if gm.get(n, **o).structure.geometry is not None]


@pytest.mark.parametrize("name,options", GEOMETRY, ids=["-".join([n] + [f"{k}={v}" for k, v in o.items()]) for n, o in GEOMETRY])
def test_prepared_geometry_equals_the_directions(name, options):
    """Where a model declares its parameter-independent geometry (issue 18), the resident
    paths read it prepared once per batch (``Directions.geometry``, kept: the same arrays
    at the next call) and give what the kernel on the directions gives: f_r, the Jacobian
    and the chi^2 sums to 1e-12 in float64 (the same formulas; only where the compiler
    fuses a multiply and an add across the boundary can the last bit differ), f_r in
    float32 against the float64 reference to 2e-5 (the bound of
    test_resident_float32_matches_reference, on the same hard pairs)."""
    m = gm.get(name, **options)
    rng = np.random.default_rng(24)
    wi, wo = hard_pairs(rng)
    wi, wo = (w.astype(np.float32).astype(np.float64) for w in (wi, wo))
    d64, d32 = _fast.Directions(wi, wo, np.float64), _fast.Directions(wi, wo, np.float32)
    g = d64.geometry(m)
    if g is None:
        pytest.skip("no prepared geometry for these options (the directions are read)")
    assert d64.geometry(m) is g and all(len(x) == len(wi) for x in g)
    for p in [m.defaults()] + [random_params(m, rng, alpha_range=(1e-3, 1.0)) for _ in range(2)]:
        p = m.validate(p)
        b = _fast.Bound(m, p, np.float64)
        direct, prepared = b.eval(d64), b.eval(d64, prepared=True)
        np.testing.assert_allclose(prepared, direct, rtol=1e-12, atol=1e-300)
        f, J = _fast.jacobian(m, d64, p)  # prepared
        np.testing.assert_allclose(f, direct, rtol=1e-12, atol=1e-300)
        P, _ = _fast._param_vars(m, p, d64.F, grad=False, dtables=True)
        f2, J2 = _fast._kernel(m, d64.wi, d64.wo, P, grad=True)  # on the directions
        for k in J:
            np.testing.assert_allclose(J[k], _fast._to_numpy(J2[k], len(wi)), rtol=1e-12,
                                       atol=1e-12 * np.max(np.abs(J[k])), err_msg=k)
        ref = m.eval_reference(wi, wo, p)
        got = _fast.Bound(m, p, np.float32).eval(d32, prepared=True)
        assert got.dtype == np.float32 and np.all(np.isfinite(got)) and np.all(got >= 0)
        big = ref * np.clip(wi[:, 2:3], 0, None) > 1e-6
        np.testing.assert_allclose(got[big], ref[big], rtol=2e-5)
        assert np.all(got[ref == 0] == 0)


@pytest.mark.parametrize("name,options", DERIV, ids=DERIV_IDS)
def test_jacobian_matches_ad_and_finite_differences(name, options):
    """Hand-written forward derivatives against (a) Dr.Jit's reverse-mode AD of the same
    model (``value_and_grad``) projected on random cotangents, to 1e-9, and (b) central
    differences of the numpy reference, element by element (h = 1e-6 relative)."""
    m = gm.get(name, **options)
    rng = np.random.default_rng(23)
    n = 1500
    wi, wo = random_hemisphere(rng, n), random_hemisphere(rng, n)
    dirs = _fast.Directions(wi, wo, np.float64)
    p = m.validate(random_params(m, rng, alpha_range=(0.05, 1.0)))
    p = m.validate({k: (np.clip(v, 0.05, None) if np.ndim(v) else max(v, 0.05)) if k != "sigma" else max(v, 0.1)
                    for k, v in p.items()})
    f, J = _fast.jacobian(m, dirs, p)
    rtol = 1e-7 if (name == "roughplastic" and options["distribution"] == "beckmann") else 1e-10  # see above
    np.testing.assert_allclose(f, m.eval_reference(wi, wo, p), rtol=rtol, atol=1e-300)
    # a coupled per-channel parameter (principled's base colour, through its luminance) adds
    # its cross-channel derivative's entry; every column is assembled by jacobian_column
    assert set(J) == {par.name for par in m.parameters} | {c.aux for c in m.structure.coupled}
    for _ in range(2):
        cot = rng.normal(size=(n, 3))
        _, grad = _fast.value_and_grad(m, wi, wo, p, cot)
        for par in m.parameters:
            want = grad[par.name]
            if par.per_channel:
                got = np.array([np.sum(cot * _fast.jacobian_column(m, J, par.name, c)) for c in range(3)])
            else:
                got = np.sum(cot * J[par.name])
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * np.max(np.abs(want)), err_msg=par.name)
    for par in m.parameters:
        for c in (range(3) if par.per_channel else [None]):
            x0 = p[par.name] if c is None else p[par.name][c]
            h = 1e-6 * max(abs(x0), 1e-2)
            q1, q2 = dict(p), dict(p)
            if c is None:
                q1[par.name], q2[par.name] = x0 + h, x0 - h
            else:
                q1[par.name], q2[par.name] = p[par.name].copy(), p[par.name].copy()
                q1[par.name][c] += h
                q2[par.name][c] -= h
            # every channel: a per-channel parameter's column is 0 in the other channels
            # unless the model declares it coupled
            fd = (m.eval_reference(wi, wo, q1) - m.eval_reference(wi, wo, q2)) / (2 * h)
            got = _fast.jacobian_column(m, J, par.name, -1 if c is None else c)
            scale = np.max(np.abs(fd))
            # roughplastic's tables have small steps in alpha and eta (quadrature nodes
            # crossing a mask): compare where the difference is smooth, i.e. almost everywhere
            bad = np.abs(got - fd) > 1e-4 * scale + 1e-5 * np.abs(fd)
            assert np.mean(bad) < 0.002, (par.name, c, np.max(np.abs(got - fd)) / scale)


def test_resident_bad_input_and_edges():
    m = gm.get("roughconductor")
    with pytest.raises(ValueError, match="dtype"):
        _fast.Directions(np.zeros((2, 3)), np.zeros((2, 3)), np.int32)
    with pytest.raises(ValueError, match="same shape"):
        _fast.Directions(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="shape"):
        _fast.Directions(np.zeros((2, 2)), np.zeros((2, 2)))
    empty = _fast.Directions(np.zeros((0, 3)), np.zeros((0, 3)))
    assert _fast.eval_resident(m, empty, {}).shape == (0, 3)
    f, J = _fast.jacobian(m, empty, {})
    assert f.shape == (0, 3) and all(v.shape == (0, 3) for v in J.values())
    # NaN directions are degenerate geometry: 0, and 0 derivatives, never NaN
    wi = np.array([[np.nan, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    wo = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    for dt in (np.float32, np.float64):
        d = _fast.Directions(wi, wo, dt)
        f, J = _fast.jacobian(m, d, {})
        assert np.all(f[[0, 2]] == 0) and f[1, 0] > 0
        assert all(np.all(np.isfinite(v)) and np.all(v[[0, 2]] == 0) for v in J.values())
    with pytest.raises(ValueError, match="alpha"):
        _fast.eval_resident(m, d, {"alpha": float("nan")})
    # a Bound model (parameters loaded once) evaluates any batch of its precision
    b = _fast.Bound(m, {"alpha": 0.3}, np.float64)
    np.testing.assert_array_equal(b.eval(d), _fast.eval_resident(m, d, {"alpha": 0.3}))
    with pytest.raises(ValueError, match="float32"):
        b.eval(_fast.Directions(wi, wo, np.float32))
    with pytest.raises(ValueError, match="alpha"):
        _fast.Bound(m, {"alpha": -1.0})


def test_chi2_grad_matches_jacobian():
    """chi2_grad's in-kernel reductions equal sum w (f - y)^2 and 2 sum w (f - y) J computed
    in numpy from ``jacobian`` (float64: 1e-12; float32: the chi^2 to 1e-5, the gradient to
    2e-3 of its largest component, the cancellation of a sum of 1e4 residual terms)."""
    rng = np.random.default_rng(31)
    n = 10_000
    wi, wo = random_hemisphere(rng, n), random_hemisphere(rng, n)
    for name, options in (("roughconductor", {"distribution": "beckmann"}), ("roughplastic", {"nonlinear": True}),
                          ("cooktorrance", {}), ("orennayar", {})):
        m = gm.get(name, **options)
        p = m.validate(random_params(m, rng, alpha_range=(0.05, 1.0)))
        f0 = m.eval_reference(wi, wo, p)
        y = f0 * (1 + 0.02 * rng.standard_normal(f0.shape))
        w = 1.0 / (0.02 * np.maximum(f0, 1e-3)) ** 2
        for dt, rtol, gtol in ((np.float64, 1e-12, 1e-10), (np.float32, 1e-5, 2e-3)):
            d = _fast.Directions(wi, wo, dt)
            f, J = _fast.jacobian(m, _fast.Directions(wi, wo, np.float64), p)
            chi2, grad = _fast.chi2_grad(m, d, p, d.channels(y), d.channels(w))
            assert chi2 == pytest.approx(np.sum(w * (f - y) ** 2), rel=rtol)
            for par in m.parameters:
                g = 2 * np.sum(w * (f - y) * J[par.name], axis=0)
                want = g if par.per_channel else g.sum()
                np.testing.assert_allclose(grad[par.name], want, rtol=gtol, atol=gtol * np.max(np.abs(want)))
    with pytest.raises(ValueError, match="y must have shape"):
        _fast.chi2_grad(m, d, p, np.zeros((3, 3)), np.ones((3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        _fast.chi2_grad(m, d, p, np.full((n, 3), np.nan), np.ones((n, 3)))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("n_terms", [1, 3, 5, 8, 11, 17, 36])
def test_reduced_sums_equal_float64_numpy(dtype, n_terms):
    """The in-kernel sums (``_reduced``: float64 packets of up to 16 terms into 16 slots per term,
    summed by ``_collect``) equal numpy's float64 sums of the same terms on 1e6 + 3 lanes
    (not a multiple of the slots or of a SIMD packet) of mixed sign and scale: within 1e-13
    of the sum of the absolute values (measured <= 1.5e-15 in float64, 0 to 1.5e-19 in
    float32, whose terms are exact in float64), for every packet layout (1 term: one
    packet of 2; 5: 8; 11: 16; 17: 16 + 2; 36: 2 x 16 + 4). Also through the frozen, replayed path (a
    second width)."""
    import drjit as dr

    rng = np.random.default_rng(n_terms)
    F = _fast.Directions(np.zeros((1, 3)) + [0, 0, 1], np.zeros((1, 3)) + [0, 0, 1], dtype).F
    for n in (1_000_003, 77):
        a = [(rng.standard_normal(n) * 10.0 ** (k % 5 - 2) + (k % 3)).astype(dtype) for k in range(n_terms)]
        run = dr.freeze(lambda *xs: _fast._reduced(list(xs)))
        target = run(*[F(x) for x in a])
        got = _fast._collect(target, dtype)
        assert got.shape[0] >= n_terms and np.all(got[n_terms:] == 0)
        ref = np.array([np.sum(x.astype(np.float64)) for x in a])
        scale = np.array([np.sum(np.abs(x.astype(np.float64))) for x in a])
        assert np.all(np.abs(got[:n_terms] - ref) <= 1e-13 * scale)


@pytest.mark.parametrize("dtype,rtol", [(np.float64, 1e-6), (np.float32, 2e-5)])
def test_conductor_fresnel_derivatives_near_k_zero(dtype, rtol):
    """dF/d eta and dF/dk of the kernel's conductor Fresnel where eta < sin(theta) and k -> 0
    (a^2 = (A + t1) / 2 cancels; F ~ 1 - C k there) against derivatives of the complex
    formula (Born & Wolf: r_s, r_p with n = eta + i k, numpy complex128 with a stable complex
    sqrt), by central differences with h = 1e-4 k (forward at k = 0: the one-sided
    derivative, since k >= 0); and F itself, as the derivative path computes it, to 1e-5
    in float32 and 1e-8 in float64 (measured 8.7e-7 and 1.4e-9). In float32 the
    derivative path takes a from the cancellation-free form (issue 18): with
    a = sqrt((A + t1) / 2), as before, F was off by up to 3.1e-4 and the derivatives by
    up to 2.7e-4 of max(1, max |dF|) (now 8.7e-7 and 2.5e-6); this test's float32 bound
    was 2e-3 then, 2e-5 now (the old code fails it: d/d eta at eta = 0.3, k = 1e-7).
    """
    import drjit as dr
    from drjit.llvm.ad import Float as F32
    from drjit.llvm.ad import Float64 as F64

    def fresnel(c, n):
        ct = np.sqrt(1 - (1 - c * c) / (n * n) + 0j)
        rs = (c - n * ct) / (c + n * ct)
        rp = (n * c - ct) / (n * c + ct)
        return 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)

    c = np.linspace(0.05, 0.95, 19)
    F = F64 if dtype == np.float64 else F32
    for eta in (0.3, 1.5):
        for k in (0.0, 1e-7, 1e-4, 0.5):
            f, d_eta, d_k = _fast._fresnel_conductor(dr, F(c), F(eta), F(k), grad=True)
            np.testing.assert_allclose(np.asarray(f, dtype=np.float64), fresnel(c, eta + 1j * k),
                                       rtol=1e-5 if dtype == np.float32 else 1e-8, err_msg=f"eta={eta} k={k} F")
            he, hk = 1e-6 * eta, 1e-4 * k if k > 0 else 1e-9
            fd_eta = (fresnel(c, (eta + he) + 1j * k) - fresnel(c, (eta - he) + 1j * k)) / (2 * he)
            if k > 0:
                fd_k = (fresnel(c, eta + 1j * (k + hk)) - fresnel(c, eta + 1j * (k - hk))) / (2 * hk)
            else:
                fd_k = (fresnel(c, eta + 1j * hk) - fresnel(c, eta + 0j)) / hk
            for got, want, what in ((d_eta, fd_eta, "eta"), (d_k, fd_k, "k")):
                got = np.asarray(got, dtype=np.float64)
                assert np.all(np.isfinite(got)), (eta, k, what)
                np.testing.assert_allclose(got, want, rtol=rtol, atol=rtol * max(1.0, np.max(np.abs(want))),
                                           err_msg=f"eta={eta} k={k} d/d{what}")


@pytest.mark.parametrize("alpha,eta", [(0.2, 1.3), (0.23, 1.62)])
def test_jacobian_with_interpolated_tables_matches_reverse_mode(alpha, eta):
    """roughplastic with ``exact_tables=False``, inside a grid cell (0.2, 1.3) and in one that
    falls back to the exact tables (0.23, 1.62: this case once interpolated a table paired
    twice, f_r off by 20 %): values equal the reference, and the Jacobian projected on random
    cotangents equals Dr.Jit's reverse mode through the same tables (``value_and_grad``)."""
    from gonio.models.physics.rough_tables import _interp

    m = gm.get("roughplastic", distribution="ggx", exact_tables=False)
    assert (_interp("ggx", alpha, eta) is None) == (alpha == 0.23)
    rng = np.random.default_rng(24)
    wi, wo = random_hemisphere(rng, 1000), random_hemisphere(rng, 1000)
    p = m.validate({"diffuse_reflectance": [0.6, 0.3, 0.2], "alpha": alpha, "int_ior": eta})
    np.testing.assert_allclose(_fast.eval_resident(m, _fast.Directions(wi, wo, np.float64), p), m.eval_reference(wi, wo, p),
                               rtol=1e-10)
    f, J = _fast.jacobian(m, _fast.Directions(wi, wo, np.float64), p)
    np.testing.assert_allclose(f, m.eval_reference(wi, wo, p), rtol=1e-10)
    cot = rng.normal(size=(1000, 3))
    _, grad = _fast.value_and_grad(m, wi, wo, p, cot)
    for par in m.parameters:
        proj = np.sum(cot * J[par.name], axis=0)
        got = proj if par.per_channel else proj.sum()
        np.testing.assert_allclose(got, grad[par.name], rtol=1e-9, err_msg=par.name)


def test_eval_at_many_sizes_keeps_bounded_recordings_and_says_nothing(capfd):
    """Model.eval at 40 new sizes: Dr.Jit records the frozen kernel again for many of them;
    at most fast.FREEZE_LIMIT recordings are kept, nothing is printed to the user (Dr.Jit
    warned from the 11th recording before), and every value equals the reference."""
    if not _fast.available():
        pytest.skip("Dr.Jit's LLVM backend is not available here")
    m = gm.get("roughconductor", distribution="ggx")
    rng = np.random.default_rng(402)
    p = random_params(m, rng)
    run = _fast._frozen_for(_fast._round_trip, m)
    for n in range(64, 64 + 40 * 97, 97):
        wi, wo = random_hemisphere(rng, n), random_hemisphere(rng, n)
        np.testing.assert_allclose(m.eval(wi, wo, p, backend="drjit"), m.eval_reference(wi, wo, p),
                                   rtol=1e-10, atol=1e-14)
    assert run.n_cached_recordings <= _fast.FREEZE_LIMIT
    out, err = capfd.readouterr()
    assert "frozen function" not in (out + err).lower(), err[-2000:]


def test_values_only_kernel_refuses_derivatives_and_the_fit_takes_the_models_own():
    """tabulated's kernel gives values only (``structure.derivatives = False``): its
    derivatives are refused, not returned as zeros (AD cannot see through its numpy tables),
    and the fit's evaluator runs the kernel for values and takes the Jacobian from the model's
    own exact numpy derivatives (``jacobian_host``: the chain rule through the tables, which
    test_tabulated holds to ``jacobian_reference``); a model with neither gets None (the fit
    differences)."""
    from gonio.fitting.likelihood.problem import Evaluator

    m = gm.get("tabulated")
    rng = np.random.default_rng(41)
    wi, wo = random_hemisphere(rng, 600), random_hemisphere(rng, 600)
    p = m.defaults()
    dirs = _fast.Directions(wi, wo, np.float64)
    with pytest.raises(NotImplementedError, match="values only"):
        _fast.jacobian(m, dirs, p)
    with pytest.raises(NotImplementedError, match="values only"):
        _fast.value_and_grad(m, wi, wo, p, np.ones((600, 3)))
    ev = Evaluator(m, wi, wo, 3)
    f, J = ev.jacobian(p)
    f_ref, J_ref = m.jacobian_host(wi, wo, p)
    assert ev.fast and np.array_equal(f, f_ref) and all(np.array_equal(J[k], J_ref[k]) for k in J_ref)
    np.testing.assert_allclose(ev(p), m.eval_reference(wi, wo, p), rtol=1e-10, atol=1e-300)
    slab = gm.get("roughslab")                  # numpy path, no derivatives of its own: differenced
    assert Evaluator(slab, wi, wo, 3).jacobian(slab.defaults()) is None
    assert np.array_equal(m.eval(wi, wo, p), m.eval_reference(wi, wo, p))  # model.eval: numpy at any size
