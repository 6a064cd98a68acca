"""Spectral capture (issue 39): the monochromator as an optional declared port, opened,
identified and recorded only where a capture is given one; a capture without it is unchanged."""

from __future__ import annotations

import tomllib

import pytest

from gonio.bench.plan.plans import Plan
from gonio.bench.samples import DEMO_SAMPLE, check_sample
from gonio.bench.session.simulated import capture_sim
from gonio.bench.settings import default_settings
from gonio.core.devices import OPTIONAL_PORTS, REQUIRED_PORTS, port_spec

TWO = [[30, 0, 30, 180], [30, 0, 50, 180]]


def test_the_monochromator_is_an_optional_declared_port():
    assert REQUIRED_PORTS == ("zaber", "meter", "camera")
    assert OPTIONAL_PORTS == ("monochromator",)
    assert port_spec("monochromator").table == "monochromator"


@pytest.mark.parametrize("with_mono", [True, False])
def test_a_capture_records_the_monochromator_only_where_it_has_one(tmp_path, with_mono):
    st = default_settings()
    if with_mono:
        st["monochromator"] = {}
    s = capture_sim(tmp_path / "s", sample=check_sample(DEMO_SAMPLE), plan=Plan("two", TWO), seed=3, settings=st,
                    progress=False)
    assert s.complete and s.n_done == 2
    doc = tomllib.loads((tmp_path / "s" / "session.toml").read_text())
    if with_mono:
        # the twin's INFO? answer (gonio/sim/devices/monochromator.py)
        assert doc["devices"]["monochromator"] == "CORNERSTONE 260 VER 2.31 TWIN"
        assert doc["ports"]["monochromator"].endswith("/monochromator")
    else:
        assert "monochromator" not in doc["devices"] and "monochromator" not in doc["ports"]
