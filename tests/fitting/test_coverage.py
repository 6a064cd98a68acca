"""Calibration of the uncertainty (issue 6, "the test that matters most"; sized in issue 12).

Seeded simulated captures of known samples (f_r from the model itself, Gaussian noise
sigma = rel f_r + floor, directions from the seeded rng): the Laplace 1-sigma interval must
contain the truth 68.3 % of the time and the emcee 90 % credible interval 90 % of the time,
for every parameter.

True coverage, measured outside the suite on 2026-12-01 (``calibrate_coverage.py``; seeds
from 100000, disjoint from the suite's; the per-capture hits are stored in
``data/coverage/``); binomial 1-sigma in brackets, then the coverage of intervals 20 %
narrower built from the same fits and chains:

    Laplace 1-sigma (nominal 0.683), 2000 captures each
      roughplastic ggx  rho R 0.687 (0.010)  G 0.685 (0.010)  B 0.701 (0.010)
                        alpha 0.686 (0.010)  int_ior 0.669 (0.011)        narrower 0.567-0.590
      orennayar         rho R 0.667 (0.011)  G 0.685 (0.010)  B 0.688 (0.010)
                        sigma 0.671 (0.011)                               narrower 0.556-0.584
    emcee 90 % (nominal 0.900)
      roughplastic ggx  rho R 0.902 (0.010)  G 0.877 (0.011)  B 0.910 (0.010)      900 captures
                        alpha 0.916 (0.009)  int_ior 0.902 (0.010)        narrower 0.789-0.823
      orennayar         rho R 0.888 (0.008)  G 0.895 (0.008)  B 0.887 (0.008)     1500 captures
                        sigma 0.892 (0.008)                               narrower 0.796-0.809

Every figure lies in the issue's [0.64, 0.72] (Laplace) and [0.87, 0.93] (emcee). The
in-suite run of 15e620e that failed (roughplastic emcee alpha 0.833 and int_ior 0.800 over
60 captures) was a fluctuation of a test whose per-parameter band (2.5 binomial sigma,
~1.2 % per parameter and tail) failed by chance in several per cent of runs.

The test (issue 12: "a correct method fails it by chance less than once in 1000 runs, a
posterior 20 % too narrow still fails it"). Two checks on the N in-suite captures:
(1) each parameter's number of hits within a binomial acceptance region whose tails are
each <= ALPHA_TAIL = 5e-5 for every true coverage within 2 sigma of the offline figure
(Bonferroni over P <= 5 parameters: <= 5e-4, whatever the dependence between them);
(2) the number of misses pooled over parameters and captures within the range of its exact
distribution (the n-fold convolution of the measured per-capture miss count, shifted by
2 sigma of the calibration) whose tails are <= ALPHA_POOLED = 5e-4 together. The whole
test's false-alarm rate is therefore <= 1e-3 (``test_false_alarm_rate_is_below_one_in_1000``).
The pooled count carries the power: resampling the offline captures, a posterior 20 % too
narrow passes the in-suite test with probability

    Laplace  roughplastic N = 300: 2.0e-4    orennayar N = 500: 4.3e-3
    emcee    roughplastic N = 150: 1.9e-2    orennayar N = 400: 4.4e-3

(``test_a_posterior_20_percent_too_narrow_fails`` holds each below POWER_MISS = 0.10).
The seeds are fixed, but the numbers a chain sees depend on the CPU's floating-point code
generation, so a run on another machine is a fresh draw: these rates, not one machine's
pass, are what make the test robust (``make test`` runs the Laplace test under two code generations).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

import gonio.models as gm
from gonio.fitting import fit, sample_posterior

from _simdata import simulate

# The Laplace coverage test runs again under a second code generation (issue 12): its fits see
# other numbers there. The emcee test runs once, under the native one: its false-alarm rate
# (<= 1e-3) and power are the method's, from the stored calibration, on any code generation, the
# compiled kernels its chains call are checked under both (tests/models: test_fast,
# test_mitsuba_agreement, test_eval_float32), and on a 2-core AVX2 machine its second run cost
# 3.5 of the suite's 14.6 minutes (2026-12-02). The false-alarm and power tests read only the
# stored calibration.
codegen = pytest.mark.codegen

ROUGHPLASTIC = (gm.get("roughplastic", distribution="ggx"),
                {"diffuse_reflectance": np.array([0.5, 0.35, 0.2]), "alpha": 0.2, "int_ior": 1.5})
ORENNAYAR = (gm.get("orennayar"), {"reflectance": np.array([0.5, 0.4, 0.3]), "sigma": 0.5})

# the simulated captures of each case (for Laplace and for emcee)
CASES = {
    "roughplastic": (*ROUGHPLASTIC, {"laplace": dict(n=300, rel=0.03), "emcee": dict(n=1000, rel=0.02)}),
    "orennayar": (*ORENNAYAR, {"laplace": dict(n=100, rel=0.03, specular_fraction=0.0),
                               "emcee": dict(n=40, rel=0.05, specular_fraction=0.0)}),
}

LAPLACE_P0 = float(stats.norm.cdf(1.0) - stats.norm.cdf(-1.0))  # 0.6827
EMCEE_P0 = 0.90
NARROW = 0.8  # "a posterior 20 % too narrow"
ALPHA_TAIL = 5e-5  # per parameter and tail: 2 x 5 x 5e-5 = 5e-4 for five parameters
ALPHA_POOLED = 5e-4  # the pooled count's two tails together; with the above, 1e-3 in all
POWER_MISS = 0.10  # a posterior 20 % too narrow may pass in at most 10 % of runs

# captures per in-suite test
N_LAPLACE = {"roughplastic": 300, "orennayar": 500}
N_EMCEE = {"roughplastic": 150, "orennayar": 400}

# the offline measurement (calibrate_coverage.py): per capture and parameter, did the
# interval (and the 20 % narrower one) contain the truth
CALIBRATION_DIR = Path(__file__).parent / "data" / "coverage"


def read_calibration(path) -> tuple[dict, np.ndarray]:
    """(document, hits) of a calibration file written by calibrate_coverage.py; hits
    (captures, 2, parameters): [:, 0] nominal intervals, [:, 1] intervals 20 % narrower."""
    d = json.loads(Path(path).read_text())
    hits = np.array([[[c == "1" for c in bits] for bits in d[key]] for key in ("nominal", "narrow")], dtype=bool)
    return d, hits.transpose(2, 0, 1)


def load_calibration(kind: str, case: str) -> tuple[list[str], np.ndarray]:
    """(names, hits) of the stored calibration run of one case (see read_calibration)."""
    d, hits = read_calibration(CALIBRATION_DIR / f"{kind}-{case}.json")
    return d["names"], hits


def _calibrated():
    table = {}
    for kind in ("laplace", "emcee"):
        for case in CASES:
            names, hits = load_calibration(kind, case)
            m = hits.shape[0]
            cov, narrow = hits.mean(axis=0)
            table[kind, case] = {nm: (float(c), float(np.sqrt(c * (1 - c) / m)), float(c8))
                                 for nm, c, c8 in zip(names, cov, narrow)}
    return table


CALIBRATED = _calibrated()  # (kind, case) -> {parameter: (coverage, its binomial sigma, 20 % narrower)}


def laplace_hits(model, truth, seed, *, n, rel, **sim):
    """One capture: does the Laplace 1-sigma interval contain the truth (per parameter),
    and would one 20 % narrower?"""
    meas = simulate(model, truth, np.random.default_rng([seed, 1]), n=n, rel=rel, **sim)
    r = fit(meas, model, rng=np.random.default_rng([seed, 2]))
    err = np.abs(r.x - r.space.from_params(truth))
    return r.space.names, np.stack([err <= r.std, err <= NARROW * r.std])


def emcee_hits(model, truth, seed, *, n, rel, **sim):
    """One capture: does the emcee 90 % interval contain the truth (per parameter), and
    would the interval of a posterior 20 % too narrow (shrunk about the median)?"""
    meas = simulate(model, truth, np.random.default_rng([seed, 1]), n=n, rel=rel, **sim)
    r = fit(meas, model, rng=np.random.default_rng([seed, 2]))
    post = sample_posterior(meas, r, rng=np.random.default_rng([seed, 3]), n_walkers=8, chunk=200, max_steps=1400,
                            tau_multiple=30)
    lo, hi = post.interval(90).T
    med = np.median(post.samples, axis=0)
    x_true = r.space.from_params(truth)
    nominal = (lo <= x_true) & (x_true <= hi)
    narrow = (med + NARROW * (lo - med) <= x_true) & (x_true <= med + NARROW * (hi - med))
    return r.space.names, np.stack([nominal, narrow]), float(np.max(post.tau)), bool(post.converged)


def acceptance(n: int, p_lo: float, p_hi: float | None = None, alpha_tail: float = ALPHA_TAIL) -> tuple[int, int]:
    """The accepted numbers of hits out of n, [lo, hi]: for every true coverage in
    [p_lo, p_hi] each tail outside has binomial probability <= alpha_tail."""
    p_hi = p_lo if p_hi is None else p_hi
    lo = int(stats.binom.ppf(alpha_tail, n, p_lo))
    while lo > 0 and stats.binom.cdf(lo - 1, n, p_lo) > alpha_tail:
        lo -= 1
    while lo + 1 <= n and stats.binom.cdf(lo, n, p_lo) <= alpha_tail:
        lo += 1
    hi = int(stats.binom.isf(alpha_tail, n, p_hi))
    while hi < n and stats.binom.sf(hi, n, p_hi) > alpha_tail:
        hi += 1
    while hi - 1 >= 0 and stats.binom.sf(hi - 1, n, p_hi) <= alpha_tail:
        hi -= 1
    return lo, hi


def region(kind: str, case: str, name: str, n: int) -> tuple[int, int]:
    """The in-suite acceptance region of one parameter: binomial tails <= ALPHA_TAIL for any
    true coverage within 2 sigma of the offline measurement (``CALIBRATED``)."""
    p, sd, _ = CALIBRATED[kind, case][name]
    return acceptance(n, max(p - 2 * sd, 0.0), min(p + 2 * sd, 1.0))


def pooled_region(kind: str, case: str, n: int) -> tuple[int, int]:
    """Accepted range of the pooled number of misses (every parameter of every capture).

    Per capture the number of parameters missed, T, has the distribution measured offline;
    over n independent captures the total is its n-fold convolution (exact, whatever the
    dependence between one capture's parameters). Each tail outside the range has
    probability <= ALPHA_POOLED / 2 under that distribution shifted by 2 sigma of the
    calibration's mean of T either way."""
    _, hits = load_calibration(kind, case)
    t = (~hits[:, 0]).sum(axis=1)
    pmf1 = np.bincount(t, minlength=hits.shape[2] + 1) / t.size
    pmf = np.array([1.0])
    for _ in range(n):
        pmf = np.convolve(pmf, pmf1)
    cdf = np.cumsum(pmf)
    lo = int(np.searchsorted(cdf, ALPHA_POOLED / 2, side="right"))  # P(M < lo) <= alpha / 2
    hi = int(np.searchsorted(cdf, 1.0 - ALPHA_POOLED / 2, side="left"))  # P(M > hi) <= alpha / 2
    shift = 2.0 * n * t.std() / np.sqrt(t.size)
    return max(0, int(np.floor(lo - shift))), int(np.ceil(hi + shift))


def resampled_pass_rates(kind: str, case: str, n: int, draws: int = 4000, seed: int = 12) -> tuple[float, float]:
    """How often the in-suite test of n captures passes, for gonio's intervals and for
    intervals 20 % narrower, estimated by drawing n captures (with replacement) from the
    offline measurement ``draws`` times: this keeps the dependence between parameters."""
    names, hits = load_calibration(kind, case)
    bounds = np.array([region(kind, case, nm, n) for nm in names])
    m_lo, m_hi = pooled_region(kind, case, n)
    rng = np.random.default_rng(seed)
    k = hits[rng.integers(0, hits.shape[0], size=(draws, n))].sum(axis=1)  # (draws, 2, P)
    misses = n * hits.shape[2] - k.sum(axis=-1)  # (draws, 2)
    ok = ((k >= bounds[:, 0]) & (k <= bounds[:, 1])).all(axis=-1) & (misses >= m_lo) & (misses <= m_hi)
    return float(ok[:, 0].mean()), float(ok[:, 1].mean())


def false_alarm(n: int, p_true, lo: int, hi: int) -> float:
    """Bonferroni bound on the probability that parameters of true coverage p_true (one
    value per parameter) fall outside [lo, hi] (arrays, one per parameter)."""
    p_true, lo, hi = np.broadcast_arrays(np.asarray(p_true, float), lo, hi)
    return float(min(1.0, (stats.binom.cdf(lo - 1, n, p_true) + stats.binom.sf(hi, n, p_true)).sum()))


def pass_probability(n: int, p_true: float, lo: int, hi: int) -> float:
    """Probability that one parameter of true coverage p_true lands inside [lo, hi]."""
    return float(stats.binom.cdf(hi, n, p_true) - stats.binom.cdf(lo - 1, n, p_true))


def _check(kind, case, names, hits):
    n = hits.shape[0]
    bounds = np.array([region(kind, case, nm, n) for nm in names])
    lo, hi = bounds[:, 0], bounds[:, 1]
    k_nominal = hits[:, 0].sum(axis=0)
    k_narrow = hits[:, 1].sum(axis=0)
    print(f"\n{kind} {case}: {n} captures;",
          {nm: f"{k}/{n} in [{a}, {b}]" for nm, k, a, b in zip(names, k_nominal, lo, hi)},
          "| 20 % narrower", {nm: f"{k}/{n}" for nm, k in zip(names, k_narrow)})
    inside = (k_nominal >= lo) & (k_nominal <= hi)
    assert inside.all(), {nm: f"{k}/{n} not in [{a}, {b}]" for nm, k, a, b, ok in zip(names, k_nominal, lo, hi, inside)
                          if not ok}
    m_lo, m_hi = pooled_region(kind, case, n)
    misses = int((~hits[:, 0]).sum())
    print(f"pooled misses {misses} in [{m_lo}, {m_hi}]; 20 % narrower: {int((~hits[:, 1]).sum())}")
    assert m_lo <= misses <= m_hi, (misses, m_lo, m_hi)


@pytest.mark.slow
@codegen
@pytest.mark.parametrize("case", ["roughplastic", "orennayar"])
def test_laplace_one_sigma_covers_68_percent(case):
    model, truth, settings = CASES[case]
    rows = [laplace_hits(model, truth, 1000 + s, **settings["laplace"]) for s in range(N_LAPLACE[case])]
    names = rows[0][0]
    _check("laplace", case, names, np.array([h for _, h in rows]))


@pytest.mark.long      # 50-57 s each: the suite's 10 minutes on 2 cores (make test-long runs it)
@pytest.mark.parametrize("case", ["roughplastic", "orennayar"])
def test_emcee_90_percent_intervals_cover_90_percent(case):
    model, truth, settings = CASES[case]
    rows = [emcee_hits(model, truth, 3000 + s, **settings["emcee"]) for s in range(N_EMCEE[case])]
    names = rows[0][0]
    conv = np.mean([c for *_, c in rows])
    print(f"\nemcee {case}: median tau {np.median([t for _, _, t, _ in rows]):.1f}, converged fraction {conv:.3f}")
    assert conv >= 0.9
    _check("emcee", case, names, np.array([h for _, h, _, _ in rows]))


def _sizes():
    return [(kind, case, (N_LAPLACE if kind == "laplace" else N_EMCEE)[case]) for kind, case in CALIBRATED]


@pytest.mark.parametrize("kind,case,n", _sizes(), ids=[f"{k}-{c}" for k, c, _ in _sizes()])
def test_false_alarm_rate_is_below_one_in_1000(kind, case, n):
    """Each region's tails are <= ALPHA_TAIL at the ends of the calibrated range and as
    narrow as that allows; the Bonferroni bound on failing the whole test by chance is
    < 1e-3 for every true coverage within 2 sigma of the offline measurement."""
    table = CALIBRATED[kind, case]
    for name, (p, sd, _) in table.items():
        lo, hi = region(kind, case, name, n)
        p_lo, p_hi = max(p - 2 * sd, 0.0), min(p + 2 * sd, 1.0)
        assert stats.binom.cdf(lo - 1, n, p_lo) <= ALPHA_TAIL < stats.binom.cdf(lo, n, p_lo)
        assert stats.binom.sf(hi, n, p_hi) <= ALPHA_TAIL < stats.binom.sf(hi - 1, n, p_hi)
    bounds = np.array([region(kind, case, nm, n) for nm in table])
    for shift in (-2, 0, 2):
        p_true = [p + shift * sd for p, sd, _ in table.values()]
        assert false_alarm(n, p_true, bounds[:, 0], bounds[:, 1]) < 1e-3 - ALPHA_POOLED, shift


@pytest.mark.parametrize("kind,case,n", _sizes(), ids=[f"{k}-{c}" for k, c, _ in _sizes()])
def test_a_posterior_20_percent_too_narrow_fails(kind, case, n):
    """Power: intervals 20 % narrower than gonio's (built from the same offline chains)
    would pass the in-suite test in fewer than POWER_MISS of its runs. Estimated by drawing
    the test's n captures from the offline measurement 4000 times (which keeps the
    dependence between parameters); also holds for the test's own nominal intervals that
    they pass in nearly all draws (the resampled false-alarm rate)."""
    passes, narrow_passes = resampled_pass_rates(kind, case, n)
    print(f"\n{kind} {case} n={n}: resampled pass rate {passes:.4f}; 20 % narrower passes {narrow_passes:.4f}")
    assert narrow_passes < POWER_MISS
    assert passes > 0.99
