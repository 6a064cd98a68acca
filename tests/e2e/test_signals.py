"""Signals and exit status of `gonio capture` (issue 14).

SIGTERM (a service manager stopping the bench) and SIGHUP (the terminal closing) are handled
like Ctrl-C twice: stages stopped, LED off, the journal consistent, one line, resumable. The
exit status says what happened: 0 complete, 3 stopped and resumable, 2 refused, 1 failure.
"""

import os
import signal
import sqlite3
import subprocess

import pytest

sim = pytest.importorskip("gonio.sim")

from capture_process import ENV, GONIO, start_capture  # noqa: E402


def events(session):
    return sqlite3.connect(session / "journal.sqlite").execute("SELECT kind, text FROM events ORDER BY id").fetchall()


def resume_and_check(session):
    res = subprocess.run(GONIO + ["capture", "--resume", str(session), "--quiet"], capture_output=True, text=True,
                         timeout=300, env=ENV)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "30/30 points" in res.stdout
    rows = sqlite3.connect(session / "journal.sqlite").execute("SELECT idx FROM points ORDER BY idx").fetchall()
    assert [r[0] for r in rows] == list(range(30))                 # every point once
    assert not list((session / "raw").glob(".*"))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_sigterm_and_sighup_stop_like_ctrl_c_twice(tmp_path, sig):
    session = tmp_path / "s"
    proc, _ = start_capture(session)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    name = signal.Signals(sig).name
    assert proc.returncode == 3, (proc.returncode, err[-2000:])
    lines = [x for x in err.splitlines() if x.strip()]
    assert lines == [f"gonio: stopped: stopped by {name}; the stages were stopped, the LED switched off and the "
                     f"session is resumable with `gonio capture --resume {session}`"], err
    ev = events(session)
    stop = ev.index(("stop", f"stopped by {name}: stages stopped"))
    assert ("lamp", "LED off") in ev[stop:]
    resume_and_check(session)


def test_ctrl_c_once_exits_3_and_says_how_to_finish(tmp_path):
    session = tmp_path / "s"
    proc, _ = start_capture(session)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 3, (proc.returncode, err[-2000:])
    assert "stopped early: stopped by Ctrl-C" in out and f"gonio capture --resume {session}" in out
    assert "Traceback" not in err
    resume_and_check(session)


def test_exit_status_is_documented():
    for args in (["--help"], ["capture", "--help"]):
        proc = subprocess.run(GONIO + args, capture_output=True, text=True, env=ENV, timeout=60)
        assert proc.returncode == 0
        text = " ".join(proc.stdout.split())
        for needle in ("exit status:", "0 done", "1 failed", "2 refused", "3 stopped, resumable", "SIGTERM"):
            assert needle in text, (args, needle)
    readme = open(os.path.join(os.path.dirname(__file__), "..", "..", "README.md")).read()
    assert "exit status" in readme.lower() and "SIGTERM" in readme and "--rebuild-journal" in readme


def test_sigterm_during_a_move_stops_the_stages_and_switches_the_led_off(tmp_path):
    """In process against the simulator: the signal arrives while a stage moves."""
    from gonio.bench.plan import plans
    from gonio.bench.settings import default_settings
    from gonio.bench.session.capture import CaptureInterrupted, capture, resume

    S = default_settings()
    from gonio.sim.physics.clock import SimClock
    inst = sim.Instrument(S, seed=1, clock=SimClock("instant", jump_on_busy=False)).register(f"sigterm-{os.getpid()}")
    plan = plans.Plan("three", [[30, 0, 40, 180], [20, 0, 50, 90], [60, 0, 10, 0]])
    sent = []

    def sleep(dt):
        t = inst.clock.now()
        if not sent and inst.lamp.on and any(ax.busy(t) for ax in inst.axes):
            sent.append(max(ax.end_time(t) or 0.0 for ax in inst.axes))   # when the move would have ended
            os.kill(os.getpid(), signal.SIGTERM)
        inst.clock.advance(dt)
    try:
        with pytest.raises(CaptureInterrupted) as e:
            capture(tmp_path / "s", plan, S, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=1,
                    progress=False, sleep=sleep)
        assert sent, "no move was under way"
        assert "stopped by SIGTERM" in str(e.value) and "\n" not in str(e.value)
        assert not inst.lamp.on                                   # LED off
        now = inst.clock.now()
        ends = [ax.end_time(now) for ax in inst.axes]
        assert max((e for e in ends if e is not None), default=now) < sent[0]   # braking, not going on
        inst.clock.advance(30.0)
        assert not any(ax.busy(inst.clock.now()) for ax in inst.axes)   # stopped, not still on its way
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL        # handlers given back
        res = resume(tmp_path / "s", progress=False, sleep=inst.clock.advance)
        assert res.complete
    finally:
        inst.unregister()


def test_a_fault_mid_run_exits_3_and_a_refusal_exits_2(tmp_path, monkeypatch, capsys):
    """A stall while measuring leaves a resumable session: status 3, one line; bad input: 2."""
    from gonio.cli import main as cli
    from gonio.bench.session import simulated as session_runner     # where capture_sim builds its instrument

    real = session_runner.sim_instrument

    def stalling(settings, sample, seed, clock="instant", faults=None, name=None, **kw):
        return real(settings, sample, seed, clock, [{"kind": "stall", "port": "zaber", "at_command": [70]}], name, **kw)
    monkeypatch.setattr(session_runner, "sim_instrument", stalling)
    session = tmp_path / "s"
    rc = cli.main(["capture", "--sim", "--plan", "quick", "--out", str(session), "--quiet"])
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert rc == 3 and len(err) == 1, err
    assert err[0].startswith("gonio: stopped:") and "FS stalled" in err[0] and f"--resume {session}" in err[0]
    monkeypatch.setattr(session_runner, "sim_instrument", real)
    assert cli.main(["capture", "--resume", str(session), "--quiet", "--remeasure", "999"]) == 2
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert len(err) == 1 and err[0].startswith("gonio: error: --remeasure '999'"), err
    assert cli.main(["capture", "--resume", str(session), "--quiet"]) == 0
    assert "30/30 points" in capsys.readouterr().out


def test_sigterm_while_a_capture_or_resume_sets_up_stops_cleanly(tmp_path, monkeypatch):
    """A signal while the ports open (capture) or the session is checked (resume): one line, no
    half-done step; the resume's checks and repairs finish whole first."""
    from gonio.bench.session import integrity as _integrity
    from gonio.bench.plan import plans
    from gonio.bench.session import capture as capture_mod
    from gonio.bench.settings import default_settings
    from gonio.bench.session.capture import CaptureInterrupted, capture, resume

    S = default_settings()
    inst = sim.Instrument(S, seed=1).register(f"setup-{os.getpid()}")
    plan = plans.Plan("two", [[30, 0, 40, 180], [20, 0, 50, 90]])
    real_bench, real_repair = capture_mod.Bench, _integrity.repair

    class Bench(real_bench):
        def __init__(self, *a, **kw):
            os.kill(os.getpid(), signal.SIGTERM)
            super().__init__(*a, **kw)

    def repair(*a, **kw):
        os.kill(os.getpid(), signal.SIGTERM)
        return real_repair(*a, **kw)
    try:
        monkeypatch.setattr(capture_mod, "Bench", Bench)
        with pytest.raises(CaptureInterrupted, match="stopped by SIGTERM before the capture started; no session "
                                                     "was written"):
            capture(tmp_path / "s", plan, S, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=1,
                    progress=False, sleep=inst.clock.advance)
        assert not (tmp_path / "s" / "session.toml").exists()
        monkeypatch.setattr(capture_mod, "Bench", real_bench)
        assert capture(tmp_path / "s", plan, S, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=1,
                       progress=False, sleep=inst.clock.advance).complete
        monkeypatch.setattr(_integrity, "repair", repair)
        with pytest.raises(CaptureInterrupted, match="stopped by SIGTERM before measuring; the session is resumable"):
            resume(tmp_path / "s", progress=False, sleep=inst.clock.advance, remeasure="1")
        monkeypatch.setattr(_integrity, "repair", real_repair)
        res = resume(tmp_path / "s", progress=False, sleep=inst.clock.advance)
        assert res.complete and res.n_new == 1                 # the --remeasure was done whole before the stop
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    finally:
        inst.unregister()
