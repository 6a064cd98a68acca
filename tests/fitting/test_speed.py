"""`gonio bench fit --quick` runs, prints its table and writes the CSV and the plot."""

import csv

import pytest

from gonio.fitting import speed as bench


@pytest.mark.slow
def test_quick_bench_writes_table_csv_and_plot(tmp_path, capsys):
    rows = bench.run(quick=True, out=tmp_path)
    text = capsys.readouterr().out
    assert "scipy-lsq" in text and "err/CRLB" in text
    assert {r["optimiser"] for r in rows} == set(bench.OPTIMISERS)
    with open(tmp_path / "fit_bench.csv") as fh:
        assert len(list(csv.DictReader(fh))) == len(rows)
    assert (tmp_path / "fit_bench.png").stat().st_size > 1000
    for r in rows:
        if r["optimiser"] == "gonio":
            assert 0.7 < r["chi2_dof"] < 1.4
            assert r["param_err_crlb"] < 3.0
