"""``gonio capture`` and ``gonio sim serve``: sessions on the simulated or the real instrument.

A simulated session runs the production drivers against :class:`gonio.sim.Instrument` through
``sim://NAME/PORT`` URLs (same bytes as hardware). Its ``session.toml`` records, under
``[meta]``, what rebuilds the simulator (seed, sample, reference), so ``--resume`` can bring
the same virtual instrument back after the capture process was killed: like a real bench
after a power cut, it comes back un-homed and the resume re-homes it.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from gonio.core.errors import GonioError

__all__ = ["capture_sim", "capture_cli", "resume_cli", "serve_cli", "sim_instrument", "with_errors_and_calibration",
           "EXIT_STOPPED"]

EXIT_STOPPED = 3          # the capture stopped before the end; `gonio capture --resume DIR` finishes it


def _settings(path):
    from gonio.bench.settings import load_settings

    return load_settings(path)


def _plan(spec):
    from gonio.bench.plan.plans import load_plan

    return load_plan(spec)


def _reference_for(settings) -> dict:
    return {"model": "diffuse", "params": {"reflectance": float(settings["reference"]["reflectance"])}}


def sim_instrument(settings, sample, seed, clock="instant", faults=None, name=None):
    """A registered simulated instrument matching the bench's settings."""
    import gonio.sim

    try:
        inst = gonio.sim.Instrument(settings, sample=sample, reference=_reference_for(settings), seed=seed,
                                    clock=clock, faults=faults)
    except (ValueError, KeyError, OSError) as exc:
        raise GonioError(f"cannot build the simulated instrument: {exc}") from None
    return inst.register(name or f"gonio-{os.getpid()}-{id(inst):x}")


def capture_sim(session: Path, *, sample: dict, plan, seed: int, settings=None, progress=True, demo=False,
                faults=None):
    """Capture ``plan`` of a virtual ``sample`` on the simulated instrument (instant clock)."""
    from gonio.bench.session.capture import capture

    settings = settings if isinstance(settings, dict) else _settings(settings)
    plan = plan if hasattr(plan, "angles") else _plan(plan)
    inst = sim_instrument(settings, sample, seed, faults=faults)
    try:
        return capture(session, plan, settings, inst.url("zaber"), inst.url("meter"), inst.url("camera"),
                       seed=seed, progress=progress, sample_truth=sample, sleep=inst.clock.advance,
                       meta={"sim": True, "demo": bool(demo), "sim_name": inst.name,
                             "sample": json.dumps(sample, sort_keys=True)})
    finally:
        inst.unregister()


def _print_summary(summary):
    """Print what the run did; return the exit status (0 complete, 3 stopped and resumable)."""
    lines = [f"session {summary.session_dir}: {summary.n_done}/{summary.n_points} points "
             f"({summary.n_new} new) in {summary.wall_s:.1f} s wall"]
    if summary.move_naive_s:
        lines.append(f"stage moves: plan order {summary.move_naive_s:.0f} s, ordered {summary.move_ordered_s:.0f} s, "
                     f"lower bound {summary.move_bound_s:.0f} s")
    if summary.reciprocity:
        lines.append(f"reciprocity: {len(summary.reciprocity)} pairs, median relative difference "
                     f"{summary.reciprocity_error:.2e}")
    if summary.stopped:
        lines.append(f"stopped early: {summary.stopped}; finish with `gonio capture --resume {summary.session_dir}`")
    elif not summary.complete:
        lines.append(f"incomplete: finish with `gonio capture --resume {summary.session_dir}`")
    print("\n".join(lines), flush=True)
    return 0 if summary.complete else EXIT_STOPPED


def with_errors_and_calibration(settings_d: dict, *, sim: bool, seed: int, errors, calibration) -> dict:
    """``--errors PRESET`` into ``[errors]`` (simulator only), ``--calibration CAL.toml`` merged
    (gonio/bench/calibrate); a calibration of the simulator made for another seed or error model is
    refused (the virtual instrument's errors come from them)."""
    if errors is not None:
        if not sim:
            raise GonioError("--errors sets the simulated instrument's errors; use it with --sim")
        old = settings_d.get("errors")
        settings_d = {**settings_d, "errors": {**(old if isinstance(old, dict) else {}), "preset": errors}}
    if sim and settings_d.get("errors") is not None:
        import gonio.sim

        try:
            gonio.sim.error_model(settings_d["errors"])
        except ValueError as exc:
            raise GonioError(f"settings: {exc}") from None
    if calibration is None:
        return settings_d
    from gonio.bench.calibrate import merge_calibration, read_calibration

    cal = read_calibration(Path(calibration))
    made = cal["calibration"]
    if bool(made.get("sim")) != bool(sim):
        raise GonioError(f"{calibration} calibrated {'the simulated' if made.get('sim') else 'a real'} instrument; "
                         f"use it with {'--sim' if made.get('sim') else 'the hardware ports'}")
    if sim:
        import gonio.sim

        if int(made.get("seed", -1)) != int(seed):
            raise GonioError(f"{calibration} calibrated the simulated instrument of seed {made.get('seed')}; capture "
                             f"with --seed {made.get('seed')} (its errors come from the seed) or calibrate again")
        if made.get("errors") != gonio.sim.error_model(settings_d.get("errors")).to_dict():
            raise GonioError(f"{calibration} calibrated another error model ([calibration.errors] preset "
                             f"{(made.get('errors') or {}).get('preset')!r}); give the same --errors / [errors]")
    return merge_calibration(settings_d, cal)


def capture_cli(out: Path, *, sim, sample, plan, seed, settings, port, meter_port, camera, dry_run, progress,
                errors=None, calibration=None):
    from gonio.bench.samples import load_sample
    from gonio.bench.plan.plans import dry_run as plan_dry_run

    settings_d = settings if isinstance(settings, dict) else _settings(settings)
    settings_d = with_errors_and_calibration(settings_d, sim=sim, seed=seed, errors=errors, calibration=calibration)
    plan_obj = _plan(plan)
    if dry_run:
        print(plan_dry_run(plan_obj, settings_d).summary())
        return 0
    if sim:
        if port or meter_port:
            raise GonioError("--sim and --port/--meter-port exclude each other: pick the simulated or the real instrument")
        summary = capture_sim(out, sample=load_sample(sample), plan=plan_obj, seed=seed, settings=settings_d,
                              progress=progress)
    else:
        from gonio.bench.session.capture import capture

        if sample:
            raise GonioError("--sample names the virtual sample of --sim; on hardware, mount the sample")
        if not meter_port or not camera:
            raise GonioError("a hardware capture needs --port, --meter-port and --camera")
        summary = capture(out, plan_obj, settings_d, port, meter_port, _camera(camera), seed=seed, progress=progress)
    return _print_summary(summary)


def _camera(spec: str):
    """``--camera`` as capture and calibrate take it (read in one place: the driver's)."""
    from gonio.bench.drivers.camera import camera_from_spec

    return camera_from_spec(spec)


def _note(line: str) -> None:
    sys.stderr.write(f"gonio: {line}\n")
    sys.stderr.flush()


def resume_cli(session: Path, *, port, meter_port, camera, progress, rebuild_journal=False, remeasure=None,
               restore_session=False):
    """``gonio capture --resume``; returns the exit status."""
    from gonio.bench.session import integrity as _integrity
    from gonio.bench.session.capture import resume

    if restore_session:
        from gonio.bench.session.journal import SessionLock

        if not session.is_dir():
            raise GonioError(f"{session} is not a gonio session folder; give the folder a capture wrote")
        with SessionLock(session):
            print(_integrity.restore_session(session))
        return 0
    data, doc, why = _integrity.load_session(session)
    # refuse what differs or is damaged before any simulator is built (the resume checks again)
    if rebuild_journal:
        if doc is None:
            raise GonioError(f"{session / 'session.toml'} is not valid TOML ({why}); the journal cannot be "
                             "rebuilt without it")
        _integrity.check_doc(doc, session)
    else:
        try:
            _integrity.open_journal(session, data, doc, why, write=False).close()
        except _integrity.NothingMeasured:
            pass                                 # a capture stopped before its journal: the resume starts it
    meta = doc.get("meta") if isinstance(doc.get("meta"), dict) else {}
    kw = dict(progress=progress, rebuild_journal=rebuild_journal, remeasure=remeasure, notify=_note)
    if meta.get("sim") and not port:
        settings = doc["settings"]
        try:
            sample = json.loads(meta["sample"])
        except (KeyError, TypeError, ValueError):
            raise GonioError(f"{session / 'session.toml'}: [meta] sample is missing or not JSON; "
                             "the simulated instrument cannot be rebuilt") from None
        inst = sim_instrument(settings, sample, int(doc["session"]["seed"]), name=meta.get("sim_name"))
        try:
            summary = resume(session, inst.url("zaber"), inst.url("meter"), inst.url("camera"),
                             sleep=inst.clock.advance, **kw)
        finally:
            inst.unregister()
    else:
        summary = resume(session, port, meter_port, _camera(camera) if camera else None, **kw)
    return _print_summary(summary)


def serve_cli(*, sample, seed, settings, clock, faults):
    import gonio.sim

    from gonio.bench.samples import load_sample

    settings_d = _settings(settings)
    schedule = None
    if faults:
        path = Path(faults)
        if not path.exists():
            raise GonioError(f"fault schedule {path} does not exist")
        try:
            schedule = gonio.sim.FaultSchedule.from_toml(path)
        except (ValueError, KeyError) as exc:
            raise GonioError(f"fault schedule {path}: {exc}") from None
    clock_spec = {"instant": "instant", "realtime": "real", "real": "real"}.get(clock)
    if clock_spec is None:
        try:
            clock_spec = f"scaled:{float(clock)}"
        except ValueError:
            raise GonioError(f"--clock {clock!r}: use instant, realtime or a time scale factor such as 10") from None
    print("gonio sim serve: Ctrl-C stops; connect with `gonio capture --port ZABER --meter-port METER --camera CAMERA`",
          flush=True)
    try:
        gonio.sim.serve(settings_d, sample=load_sample(sample), reference=_reference_for(settings_d), seed=seed,
                        clock=clock_spec, faults=schedule, block=True)
    except KeyboardInterrupt:
        pass
