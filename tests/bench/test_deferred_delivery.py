"""RAW files checked and committed by the point's reduction (the worker, while the stages move).

A point is journalled only once its files match the camera's SHA-256 and are fsynced and
renamed; a file spoilt after the stages left its point makes the run take that point again.
"""

import hashlib

import numpy as np
import pytest

sim = pytest.importorskip("gonio.sim")

from gonio.bench.plan import plans  # noqa: E402
from gonio.core.files import sha256_file  # noqa: E402
from gonio.bench.session.journal import Journal  # noqa: E402
from gonio.bench.settings import default_settings  # noqa: E402
from gonio.bench.session.capture import capture  # noqa: E402
from gonio.bench.drivers import BadDelivery, Delivery, SimCamera  # noqa: E402

S = default_settings()


def test_delivery_checks_then_commits(tmp_path):
    data = b"raw bytes" * 100
    good = tmp_path / ".tmp-a.dng"
    good.write_bytes(data)
    d = Delivery(tmp_path / "a.dng", hashlib.sha256(data).hexdigest(), good)
    assert not (tmp_path / "a.dng").exists()
    assert d.finish() == data and (tmp_path / "a.dng").read_bytes() == data and not good.exists()
    assert d.finish() is None                       # committed: nothing left to do
    bad = tmp_path / ".tmp-b.dng"
    bad.write_bytes(data[:-1])
    d = Delivery(tmp_path / "b.dng", hashlib.sha256(data).hexdigest(), bad)
    with pytest.raises(BadDelivery, match="does not match"):
        d.finish()
    assert not bad.exists() and not (tmp_path / "b.dng").exists()
    with pytest.raises(BadDelivery, match="vanished"):
        Delivery(tmp_path / "c.dng", "0" * 64, tmp_path / ".tmp-c.dng").finish()


def _flip(data: bytes) -> bytes:
    """One pixel byte changed near the end: still a DNG that decodes, no longer the camera's bytes."""
    i = len(data) - 100
    return data[:i] + bytes([data[i] ^ 0x01]) + data[i + 1:]


@pytest.mark.parametrize("spoil", ["flip", "truncate"])
def test_a_spoilt_file_is_taken_again(tmp_path, monkeypatch, spoil):
    """The first file (a probe) is spoilt after the camera's reply, as a failing disk might.
    Cut short, it does not decode and is taken again at once; with one byte changed it decodes,
    the reduction's check (the stages gone on) finds it and the point is measured again. Either
    way every journalled file is whole and the run completes."""
    spoilt = []
    real = SimCamera.expose_deferred

    def spoil_first(self, seconds, path):
        d = real(self, seconds, path)
        if not spoilt:
            spoilt.append(d.path.name)
            raw = d.tmp.read_bytes()
            d.tmp.write_bytes(_flip(raw) if spoil == "flip" else raw[:1000])
        return d

    monkeypatch.setattr(SimCamera, "expose_deferred", spoil_first)
    inst = sim.Instrument(S, seed=3).register(f"deferred-{spoil}")
    try:
        plan = plans.Plan("three", [[30, 0, 40, 180], [20, 0, 50, 90], [45, 0, 20, 0]])
        res = capture(tmp_path / "s", plan, S, inst.url("zaber"), inst.url("meter"), inst.url("camera"), seed=3,
                      progress=False, sleep=inst.clock.advance, sample_truth=inst.sample_spec)
    finally:
        inst.unregister()
    assert spoilt and res.complete and res.n_new == 3
    folder = tmp_path / "s"
    with Journal(folder / "journal.sqlite") as j:
        warnings = [t for _, k, t in j.events() if k == "warning"]
        rows = j.points()
    retaken = any(spoilt[0] in w and "taking it again" in w for w in warnings)
    assert retaken == (spoil == "flip")
    assert sorted(r["idx"] for r in rows) == [0, 1, 2]
    for r in rows:
        for e in r["detail"]["exposures"]:
            assert sha256_file(folder / e["file"]) == e["sha256"]
    assert not [p for p in (folder / "raw").iterdir() if p.name.startswith(".tmp-")]
    assert all(np.all(np.isfinite(r["brdf"])) for r in rows)
