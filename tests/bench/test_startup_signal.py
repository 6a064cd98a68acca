"""SIGTERM while ``gonio`` starts (issue 40: the process ended silently): it says which signal
stopped it, exits non-zero (128 + the signal's number, or 3 where the capture's own handlers
had taken over) and leaves nothing half-written: no session, or (the capture had begun) a
resumable one."""

import os
import signal
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.timeout(120)


@pytest.mark.parametrize("delay", [0.8])
def test_sigterm_during_start_up_is_said_and_leaves_nothing(tmp_path, delay):
    out = tmp_path / "session"
    p = subprocess.Popen([sys.executable, "-m", "gonio.cli.main", "capture", "--sim", "--plan", "quick",
                          "--out", str(out), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(delay)                              # in the imports, or opening the simulated ports
    p.send_signal(signal.SIGTERM)
    stdout, stderr = p.communicate(timeout=60)
    assert p.returncode in (128 + signal.SIGTERM, 3), (p.returncode, stderr)
    assert "SIGTERM" in stderr and "Traceback" not in stderr, stderr
    assert len(stderr.strip().splitlines()) == 1, stderr
    if (out / "session.toml").exists():            # the capture had started: a resumable stop, said so
        assert p.returncode == 3 and f"--resume {out}" in stderr, stderr
        return
    left = [f for f in os.listdir(out) if f not in ("raw",)] if out.exists() else []
    assert left == [], left                        # nothing half-written


def test_a_stop_wrapped_by_what_it_interrupted_is_said_as_the_stop(monkeypatch, capsys):
    """SIGTERM inside a class's creation during an import (tifffile's ``cached_property``
    __set_name__, seen under load) reaches main as RuntimeError from the SignalStop (Python
    3.11 wraps it): it is said as the stop, exit 128 + 15, one line, no traceback. An error
    with no stop in its chain is not taken for one."""
    import gonio.cli.main as cli
    from gonio.bench.session.signals import SignalStop

    def wrapped(argv):
        try:
            raise SignalStop(signal.SIGTERM)
        except SignalStop as stop:
            raise RuntimeError("Error calling __set_name__ on 'cached_property' instance 'dims'") from stop

    monkeypatch.setattr(cli, "_main", wrapped)
    assert cli.main(["plans"]) == 128 + signal.SIGTERM
    err = capsys.readouterr().err.strip()
    assert "SIGTERM" in err and len(err.splitlines()) == 1 and "Traceback" not in err

    def plain(argv):
        raise RuntimeError("not a stop")

    def cleanup_failed(argv):               # a clean-up that fails while the stop is handled: its error
        try:
            raise SignalStop(signal.SIGTERM)
        finally:
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(cli, "_main", cleanup_failed)
    with pytest.raises(OSError, match="No space"):
        cli.main(["plans"])

    monkeypatch.setattr(cli, "_main", plain)
    with pytest.raises(RuntimeError, match="not a stop"):
        cli.main(["plans"])
