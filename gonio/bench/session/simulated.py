"""Sessions on the simulated instrument: the virtual instrument that matches the bench's
settings, and a capture on it. ``gonio capture --sim``, the demo and the tests all call these."""

from __future__ import annotations

import json
import os
from pathlib import Path

from gonio.core.errors import GonioError

__all__ = ["capture_sim", "sim_instrument", "reference_for"]


def _settings(path):
    from gonio.bench.settings import load_settings

    return load_settings(path)


def _plan(spec):
    from gonio.bench.plan.plans import load_plan

    return load_plan(spec)


def reference_for(settings) -> dict:
    return {"model": "diffuse", "params": {"reflectance": float(settings["reference"]["reflectance"])}}


def sim_instrument(settings, sample, seed, clock="instant", faults=None, name=None, camera_root=None):
    """A registered simulated instrument matching the bench's settings; ``camera_root``: the
    only folder its camera writes into (a session's folder)."""
    import gonio.sim

    try:
        inst = gonio.sim.Instrument(settings, sample=sample, reference=reference_for(settings), seed=seed,
                                    clock=clock, faults=faults)
    except (ValueError, KeyError, OSError) as exc:
        raise GonioError(f"cannot build the simulated instrument: {exc}") from None
    inst.camera.root = camera_root
    return inst.register(name or f"gonio-{os.getpid()}-{id(inst):x}")


def capture_sim(session: Path, *, sample: dict, plan, seed: int, settings=None, progress=True, demo=False,
                faults=None, strategy=None):
    """Capture ``plan`` of a virtual ``sample`` on the simulated instrument (instant clock);
    ``strategy``: session.toml's ``[strategy]`` table (`gonio.bench.plan.strategy`; default fixed).
    A spectral plan on settings without ``[monochromator]`` gets the default one (the simulated
    bench then has the Cornerstone twin)."""
    from gonio.bench.session.capture import capture

    from gonio.bench.measure.systematics import for_session

    settings = settings if isinstance(settings, dict) else _settings(settings)
    settings = for_session(settings)       # an uncalibrated capture states the error model's systematics
    plan = plan if hasattr(plan, "angles") else _plan(plan)
    if getattr(plan, "wavelength_nm", None) is not None and not settings.get("monochromator"):
        settings = {**settings, "monochromator": dict(settings.get("monochromator") or {})}   # the twin's defaults
    inst = sim_instrument(settings, sample, seed, faults=faults, camera_root=session)
    try:
        return capture(session, plan, settings, inst.url("zaber"), inst.url("meter"), inst.url("camera"),
                       seed=seed, progress=progress, sample_truth=sample, sleep=inst.clock.advance,
                       clock=inst.clock.now,
                       meta={"sim": True, "demo": bool(demo), "sim_name": inst.name,
                             "sample": json.dumps(sample, sort_keys=True)}, strategy=strategy,
                       monochromator=inst.url("monochromator") if inst.monochromator is not None else None)
    finally:
        inst.unregister()
