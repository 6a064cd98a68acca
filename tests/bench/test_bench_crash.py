"""Crash test: a capture in its own process against the simulator on pseudo-terminals, killed
with SIGKILL at seeded random moments and resumed each time.

The kill moments are counted in serial writes rather than wall time: the runner process sends
itself SIGKILL right after its N-th write (N drawn from a seeded generator), so the test is
reproducible and never sleeps. ``GONIO_CRASH_KILLS`` (default 20, the issue's figure) sets the
number of kills.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

sim = pytest.importorskip("gonio.sim")

from gonio.bench.plan import plans
from gonio.bench.session.journal import Journal, verify_files
from gonio.bench.settings import default_settings, merge_settings

S = merge_settings(default_settings(), {"motion": {"settle_s": 0.0}})
GLOSSY = {"model": "roughplastic", "params": {"diffuse_reflectance": [0.6, 0.4, 0.2], "alpha": 0.15}}
PLAN = plans.load_plan("quick")

RUNNER = r"""
import json, os, signal, sys
import serial
args = json.loads(sys.argv[1])
kill_after = args["kill_after"]
count = [0]
_open = serial.serial_for_url

def counting(*a, **kw):
    port = _open(*a, **kw)
    write = port.write
    def w(data):
        n = write(data)
        count[0] += 1
        if kill_after and count[0] >= kill_after:
            os.kill(os.getpid(), signal.SIGKILL)
        return n
    port.write = w
    return port
serial.serial_for_url = counting
from gonio.bench.session.capture import capture, resume
from gonio.bench.plan.plans import plan_from_dict
p = args["ports"]
if os.path.exists(os.path.join(args["folder"], "session.toml")):
    r = resume(args["folder"], progress=False, poll_interval_s=0.001)
else:
    r = capture(args["folder"], plan_from_dict(args["plan"]), args["settings"], p["zaber"], p["meter"], p["camera"],
                seed=args["seed"], progress=False, poll_interval_s=0.001)
print(json.dumps({"complete": r.complete, "writes": count[0]}))
"""


def run_once(folder, server, kill_after):
    args = {"folder": str(folder), "ports": server.paths, "plan": PLAN.to_dict(), "settings": S, "seed": 3,
            "kill_after": kill_after}
    return subprocess.run([sys.executable, "-c", RUNNER, json.dumps(args)], capture_output=True, text=True,
                          timeout=120)


@pytest.mark.slow
def test_sigkill_at_random_moments_then_resume(tmp_path):
    kills = int(os.environ.get("GONIO_CRASH_KILLS", "20"))
    server = sim.serve(S, sample=GLOSSY, seed=3, clock="instant", block=False, echo=None)
    try:
        ref = run_once(tmp_path / "ref", server, 0)
        assert ref.returncode == 0, ref.stderr[-2000:]
        total = json.loads(ref.stdout.splitlines()[-1])["writes"]
        setup = json.loads(run_once(tmp_path / "ref", server, 0).stdout.splitlines()[-1])["writes"]  # a resume's own writes
        rng = np.random.default_rng(20)
        folder = tmp_path / "s"
        killed = 0
        complete = False
        while killed < kills and not complete:
            reach = setup + 2 * (total - setup) // kills        # the kills spread over the whole session
            r = run_once(folder, server, int(rng.integers(1, reach)))
            if r.returncode == -9:
                killed += 1
            else:
                assert r.returncode == 0, r.stderr[-2000:]
                complete = json.loads(r.stdout.splitlines()[-1])["complete"]
        while not complete:                                     # then finish it
            r = run_once(folder, server, 0)
            assert r.returncode == 0, r.stderr[-2000:]
            complete = json.loads(r.stdout.splitlines()[-1])["complete"]
        assert killed == kills
    finally:
        server.stop()
    with Journal(folder / "journal.sqlite") as j:
        rows = j.points()
        assert [r["idx"] for r in rows] == list(range(len(PLAN)))    # every point exactly once
        assert verify_files(folder, j) == []                          # no corrupt file
    orphans = [p.name for p in folder.rglob("*") if p.name.startswith(".tmp-") or p.name.endswith(".part")]
    assert orphans == []
    with Journal(tmp_path / "ref" / "journal.sqlite") as j:
        ref_rows = j.points()
    # the uninterrupted run's values: the resumed points see other noise draws (the kills move
    # the simulated clock and the lamp drift), so they agree within the combined sigma; 4 sigma
    # over ~90 values is a false-alarm rate of 90 x 6.3e-5 = 0.6 % if every value were an
    # independent draw (the largest |difference| / sigma printed with -s, issue 12)
    z = []
    for a, b in zip(ref_rows, rows):
        fa, fb = np.array(a["brdf"]), np.array(b["brdf"])
        z.append(np.abs(fa - fb) / np.hypot(a["brdf_std"], b["brdf_std"]))
    z = np.concatenate(z)
    print(f"\nresumed vs uninterrupted: {z.size} values, largest |difference| / sigma {z.max():.2f}, "
          f"identical {np.mean(z == 0):.0%}")
    assert np.all(z < 4)
