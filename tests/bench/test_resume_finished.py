"""Resuming a finished session (issue 40: it homed the stages, took dark frames and switched the
LED on before finding nothing to measure): it says the session is finished, and no device is
asked to move, expose or light."""

import pytest

import gonio.sim as gs
from gonio.bench.plan import plans
from gonio.bench.session.capture import capture, resume
from gonio.bench.settings import default_settings
from gonio.cli.main import main

pytestmark = pytest.mark.timeout(300)

S = default_settings()
TWO = plans.Plan("two", [[30, 0, 40, 180], [45, 0, 20, 0]])


def _recorded(inst):
    """Every command line the simulated devices receive from now on, by port."""
    got = {name: [] for name in inst.ports}
    for name, ep in inst.ports.items():
        handle = ep.server.handle

        def watched(text, *a, _h=handle, _n=name, **kw):
            got[_n].append(text)
            return _h(text, *a, **kw)
        ep.server.handle = watched
    return got


def test_resume_of_a_finished_session_moves_nothing(tmp_path):
    inst = gs.Instrument(S, seed=4).register("resume-finished")
    try:
        folder = tmp_path / "s"
        res = capture(folder, TWO, S, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=4,
                      progress=False, sleep=inst.clock.advance, sample_truth=inst.sample_spec)
        assert res.complete
        inst.power_cycle(1)                        # the bench was switched off: the stages lost their home
        got = _recorded(inst)
        notes = []
        res = resume(folder, sleep=inst.clock.advance, progress=False, notify=notes.append)
        assert res.complete and res.n_new == 0 and res.n_done == 2
        assert any("session is finished" in n for n in notes), notes
        moves = [c for c in got["zaber"] if any(w in c for w in ("home", "move", "lamp on"))]
        assert moves == [], moves
        shots = [c for c in got["camera"] if c.split()[0] in ("EXPOSE", "FLAT", "CHART")]
        assert shots == [] and not any(c.startswith("MEAS") for c in got["meter"]), got
    finally:
        inst.unregister()


@pytest.mark.long          # the CLI's wording; the in-process test above checks the note and the devices
def test_gonio_capture_resume_says_finished(tmp_path, capsys):
    plan = tmp_path / "two.csv"
    plan.write_text("theta_i,phi_i,theta_o,phi_o\n30,0,40,180\n45,0,20,0\n")
    folder = tmp_path / "sim"
    assert main(["capture", "--sim", "--plan", str(plan), "--out", str(folder), "--quiet", "--seed", "5"]) == 0
    capsys.readouterr()
    assert main(["capture", "--resume", str(folder), "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert "2/2 points (0 new)" in out, out
    assert "the session is finished" in err and "nothing was moved" in err, err
