"""A fit function wrapped to keep every result it returns, and the check that a fit's time,
evaluations and CPU seconds are all of those runs' (FitResult counts every run it made)."""

import pytest


def recording(fn, runs: list):
    """``fn`` that appends each result it returns to ``runs``."""
    def counted(*a, **k):
        runs.append(fn(*a, **k))
        return runs[-1]
    return counted


def assert_counts_every_run(result, runs) -> None:
    """``result``'s time_s, n_evals and cpu_s are the sums over ``runs`` (to rounding)."""
    assert result.time_s == pytest.approx(sum(r.time_s for r in runs), rel=1e-12)
    assert result.n_evals == sum(r.n_evals for r in runs)
    assert result.cpu_s == pytest.approx(sum(r.cpu_s for r in runs), rel=1e-12)
