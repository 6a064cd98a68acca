"""`gonio fit`'s summary is the fit file's one uncertainty statement (issue 34): the rows of
gonio.fitting.display.uncertainty_rows under UNCERTAINTY_HEADER (flags included), z against
u_c, and a caption that says the 90 % interval is on u_c.

Before: the CLI built its own table (value rounded to u_c, "1-sigma (stat)", no k, no flags)
and its caption said "90 % interval = value +- 1.645 sigma".
"""

import io

from rich.console import Console

from gonio.cli.fit import print_fit
from gonio.fitting.display import UNCERTAINTY_HEADER, uncertainty_rows


def _doc():
    names = ["diffuse_reflectance[R]", "alpha", "int_ior"]
    values = [0.5498598, 0.0500123, 1.0]
    params = {n: {"value": v, "std": 1e-4, "u_combined": 3e-3, "U": 6e-3, "k": 2.0, "unit": "1", "method": "laplace",
                  "at_bound": n == "int_ior", "undetermined": False, "ci90": [v - 0.005, v + 0.005],
                  "flags": ["at_bound"] if n == "int_ior" else []} for n, v in zip(names, values)}
    return {"model": {"name": "roughplastic", "options": {"distribution": "ggx"}}, "parameters": params,
            "goodness": {"chi2_dof": 1.0, "dof": 90, "rmse_fr": 1e-4, "model_adequate": True, "warning": None},
            "constraints": {"energy": {"by_construction": True, "holds": True, "max_albedo": 0.6}},
            "optimiser": {"evaluations": 10, "time_s": 0.1},
            "uncertainty": {"k": 2, "components": {}, "parameters": {
                n: {"u_stat": 1e-4, "u_combined": 3e-3, "U": 6e-3, "k": 2, "budget": {"reference_certificate": 1.0}}
                for n in names}}}


def test_the_summary_is_uncertainty_rows_with_flags_and_z_on_u_c():
    console = Console(width=240, file=io.StringIO(), record=True, color_system=None)
    truth = {"model": "roughplastic", "options": {"distribution": "ggx"},
             "params": {"alpha": 0.05, "diffuse_reflectance": [0.55, 0.3, 0.12], "int_ior": 1.0}}
    doc = _doc()
    print_fit(doc, truth=truth, console=console)
    text = console.export_text()
    lines = text.splitlines()
    header = next(line for line in lines if line.strip().startswith("parameter"))
    for h in UNCERTAINTY_HEADER:
        assert h in header, h
    for row in uncertainty_rows(doc):
        line = next(line for line in lines if line.strip().startswith(row[0]))
        for cell in row[1:]:
            assert cell in line, (cell, line)
    assert "at bound" in text
    assert "90 % interval" in header and "value ± 1.645 u_c" in text and "sigma" not in text
    # z against u_c: (0.0500123 - 0.05) / 3e-3
    assert "+0.00" in next(line for line in lines if line.strip().startswith("alpha"))
    assert "-0.05" in next(line for line in lines if line.strip().startswith("diffuse_reflectance[R]"))
