"""`gonio bench fit --quick` runs, prints its table and writes the CSV and the plot."""

import csv

import pytest

from gonio.perf import fit as bench


@pytest.mark.slow
def test_quick_bench_writes_table_csv_and_plot(tmp_path, capsys):
    rows = bench.run(quick=True, out=tmp_path)
    text = capsys.readouterr().out
    assert "scipy-lsq" in text and "err/CRLB" in text
    verdicts = bench.cell_verdicts(rows)  # one per cell, against a peer of equal error
    assert len(verdicts) == 2 and "fastest peer at equal error" in text
    for v in verdicts:
        assert v["best_peer"] is None or v["ratio"] == pytest.approx(v["gonio_s"] / v["peer_s"])
    assert {r["optimiser"] for r in rows} == set(bench.OPTIMISERS)
    with open(tmp_path / "fit_bench.csv") as fh:
        assert len(list(csv.DictReader(fh))) == len(rows)
    assert (tmp_path / "fit_bench.png").stat().st_size > 1000
    for r in rows:
        if r["optimiser"] == "gonio":
            assert 0.7 < r["chi2_dof"] < 1.4
            assert r["param_err_crlb"] < 3.0


@pytest.mark.slow
def test_dask_bench_prints_both_serial_baselines_and_matches_them(capsys):
    """bench_dask: serial on one Dr.Jit thread and on the default pool, and two plain
    processes at once (the machine's limit), in processes of their own; Dask on 1 and 2
    single-thread workers (loaders) and 2 with in-memory data (handed through files, and
    scattered through a client that connected by address); speed-ups against both serial
    baselines, which one the issue's 1.8x is measured against, and how much of the machine's
    limit Dask reaches. Every one-thread run equals the one-thread serial fits bit for bit.
    (A behaviour test: no timing is asserted.)

    It leaves Dask's default scheduler as it found it: its two clients, closed in the order
    they were opened, once left ``scheduler='dask.distributed'`` set with no client, and every
    later ``to_netcdf`` in the process failed ("Requested dask.distributed scheduler but no
    Client active": 14 errors in the suite's worker that ran this test). It leaves no process
    behind."""
    import multiprocessing

    import dask

    from gonio.perf.fit import bench_dask

    before = dask.config.get("scheduler", None)
    rows = bench_dask(cases=((4, 800),), repeat=1)
    assert dask.config.get("scheduler", None) == before
    assert not [p for p in multiprocessing.active_children() if p.name == "gonio-bench-plain"]
    text = capsys.readouterr().out
    assert "serial, 1 Dr.Jit thread" in text and "(default)" in text and "Dask, 2 workers x 1 thread" in text
    assert "measured against the serial loop on one Dr.Jit thread" in text and "The machine's limit" in text
    row = rows["4x800"]
    runs = [k for k in row if isinstance(row[k], dict)]
    assert len(runs) == 7 and "2 plain processes x 1 thread, no Dask" in runs
    for key in runs:
        assert row[key]["wall_s"] > 0 and row[key]["speedup_vs_serial_1_thread"] > 0
        if "(default)" not in key:
            assert row[key]["max_diff"] == 0.0, key
    assert row["goal_speedup"] > 0 and row["limit_speedup"] > 0


def test_scale_bench_reports_the_fits_own_peak_memory(capsys):
    """bench_scale prints the fit's time, its peak RSS against the data and the tracemalloc
    peak (small N here: the behaviour, not the 1e6-point figure)."""
    from gonio.perf.fit import bench_scale

    row = bench_scale(n=20_000)
    text = capsys.readouterr().out
    assert "peak RSS during the fit" in text and "tracemalloc" in text
    assert row["peak_rss_bytes"] >= row["rss_before_fit_bytes"] > 0
    assert row["traced_peak_bytes"] > 0 and row["data_bytes"] == 20_000 * (4 * 24 + 3)


def test_every_timed_run_starts_with_the_parameter_tables_uncached(monkeypatch):
    """Each optimiser's run in `gonio bench fit` starts with roughplastic's per-(alpha, eta)
    table caches empty. Without it a repeated run of a deterministic peer found every table
    its previous run had made: nlopt SLSQP at 1e3 points took 0.007 s CPU against 0.86 s cold
    (2026-12-02), and the verdicts read "peer ahead" in every roughplastic cell up to 1e4."""
    import numpy as np

    import gonio.models as gm
    from gonio.fitting import fit
    from gonio.models import fast
    from gonio.models.engine import jit_tables as _jit_tables
    from gonio.models.physics import rough_tables as _rough_tables

    name, options, truth = bench.MODELS[0]
    model = gm.get(name, **options)
    truth = {k: np.asarray(v, dtype=float) if isinstance(v, list) else v for k, v in truth.items()}
    meas, _ = bench.simulate_capture(model, truth, 100, np.random.default_rng(5), 0.01)
    caches = (_rough_tables.rough_tables, _rough_tables.rough_tables_interp, _jit_tables._cached_tables,
              _jit_tables._cached_table_derivs)
    bench._run_one("nlopt-slsqp", meas, model, 0, fit)
    assert sum(c.cache_info().currsize for c in caches) > 0  # the run filled them
    fast.clear_parameter_caches()
    assert [c.cache_info().currsize for c in caches] == [0, 0, 0, 0]
    seen, original = [], fast.clear_parameter_caches

    def spy():
        seen.append(sum(c.cache_info().currsize for c in caches))
        original()

    monkeypatch.setattr(fast, "clear_parameter_caches", spy)
    runs = ("gonio", "nlopt-slsqp", "scipy-lsq")  # both branches of _run_one (nlopt-mma: ~70 evaluations, ~40 ms a new table)
    for opt in runs:
        bench._run_one(opt, meas, model, 0, fit)
    # each run cleared caches that its predecessor had filled, before starting its own
    assert len(seen) == len(runs) and all(n > 0 for n in seen[1:])
