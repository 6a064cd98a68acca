"""`gonio bench fit --quick` runs, prints its table and writes the CSV and the plot."""

import csv

import pytest

from gonio.fitting import speed as bench


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
