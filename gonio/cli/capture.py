"""``gonio capture`` and ``gonio sim serve``: sessions on the simulated or the real instrument.

A simulated session runs the production drivers against :class:`gonio.sim.Instrument` through
``sim://NAME/PORT`` URLs (same bytes as hardware). Its ``session.toml`` records, under
``[meta]``, what rebuilds the simulator (seed, sample, reference), so ``--resume`` can bring
the same virtual instrument back after the capture process was killed: like a real bench
after a power cut, it comes back un-homed and the resume re-homes it.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from gonio.bench.calibrate import with_errors_and_calibration  # noqa: F401  (the CLI's names)
from gonio.bench.session import simulated as _simulated
from gonio.bench.session.simulated import capture_sim, reference_for, sim_instrument  # noqa: F401  (the CLI's names)
from gonio.core.errors import GonioError

__all__ = ["capture_sim", "capture_cli", "resume_cli", "serve_cli", "serve_hints", "sim_instrument",
           "with_errors_and_calibration", "EXIT_STOPPED"]

EXIT_STOPPED = 3          # the capture stopped before the end; `gonio capture --resume DIR` finishes it


def _print_summary(summary):
    """Print what the run did; return the exit status (0 complete, 3 stopped and resumable)."""
    lines = [f"session {summary.session_dir}: {summary.n_done}/{summary.n_points} points "
             f"({summary.n_new} new) in {summary.wall_s:.1f} s wall, {summary.instrument_s:.1f} s instrument time "
             "(all runs)"]
    if summary.move_naive_s:
        lines.append(f"stage moves: plan order {summary.move_naive_s:.0f} s, ordered {summary.move_ordered_s:.0f} s, "
                     f"lower bound {summary.move_bound_s:.0f} s")
    if getattr(summary, "spectral", ""):
        lines.append(summary.spectral)
    if summary.reciprocity:
        lines.append(f"reciprocity: {len(summary.reciprocity)} pairs, median relative difference "
                     f"{summary.reciprocity_error:.2e}")
    if summary.plan_stop:
        lines.append(summary.plan_stop)
    if summary.stopped:
        lines.append(f"stopped early: {summary.stopped}; finish with `gonio capture --resume {summary.session_dir}`")
    elif not summary.complete:
        lines.append(f"incomplete: finish with `gonio capture --resume {summary.session_dir}`")
    from gonio.cli.helptext import say

    say("\n".join(lines))          # wrapped on a terminal only: a pipe gets a line a message
    return 0 if summary.complete else EXIT_STOPPED


def _load_settings(path):
    from gonio.bench.settings import load_settings

    return load_settings(path)


def _load_plan(spec):
    from gonio.bench.plan.plans import load_plan

    return load_plan(spec)


def capture_cli(out: Path, *, sim, sample, plan, seed, settings, port, meter_port, camera, dry_run, progress,
                errors=None, calibration=None, points=None, target_rel_u=None, candidates=None, budget_minutes=None,
                target_de00=None, monochromator=None, criterion=None):
    from gonio.bench.samples import load_sample
    from gonio.bench.plan.cli_options import cli_strategy
    from gonio.bench.plan.plans import dry_run as plan_dry_run

    try:
        plan, strategy = cli_strategy(plan, points=points, target_rel_u=target_rel_u, candidates=candidates, seed=seed,
                                      budget_minutes=budget_minutes, target_de00=target_de00, criterion=criterion)
    except ValueError as exc:
        raise GonioError(str(exc)) from None
    given = {"strategy": strategy} if strategy else {}
    settings_d = settings if isinstance(settings, dict) else _load_settings(settings)
    settings_d = with_errors_and_calibration(settings_d, sim=sim, seed=seed, errors=errors, calibration=calibration)
    plan_obj = _load_plan(plan)
    if dry_run:
        print(plan_dry_run(plan_obj, settings_d).summary())
        return 0
    if sim:
        if port or meter_port:
            raise GonioError("--sim and --port/--meter-port exclude each other: pick the simulated or the real instrument")
        summary = capture_sim(out, sample=load_sample(sample), plan=plan_obj, seed=seed, settings=settings_d,
                              progress=progress, **given)
    else:
        from gonio.bench.session.capture import capture

        if sample:
            raise GonioError("--sample names the virtual sample of --sim; on hardware, mount the sample")
        if not meter_port or not camera:
            raise GonioError("a hardware capture needs --port, --meter-port and --camera")
        summary = capture(out, plan_obj, settings_d, port, meter_port, _camera(camera), seed=seed, progress=progress,
                          monochromator=monochromator, **given)
    return _print_summary(summary)


def _camera(spec: str):
    """``--camera`` as capture and calibrate take it (read in one place: the driver's)."""
    from gonio.bench.drivers.camera import camera_from_spec

    return camera_from_spec(spec)


def _note(line: str) -> None:
    sys.stderr.write(f"gonio: {line}\n")
    sys.stderr.flush()


def resume_cli(session: Path, *, port, meter_port, camera, progress, rebuild_journal=False, remeasure=None,
               restore_session=False, monochromator=None):
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
        inst = _simulated.sim_instrument(settings, sample, int(doc["session"]["seed"]), name=meta.get("sim_name"),
                              camera_root=session)
        try:
            summary = resume(session, inst.url("zaber"), inst.url("meter"), inst.url("camera"),
                             sleep=inst.clock.advance, clock=inst.clock.now, **kw)
        finally:
            inst.unregister()
    else:
        summary = resume(session, port, meter_port, _camera(camera) if camera else None, monochromator=monochromator,
                         **kw)
    return _print_summary(summary)


def serve_cli(*, sample, seed, settings, clock, faults, camera_size=None):
    import gonio.sim

    from gonio.bench.samples import load_sample
    from gonio.sim.physics.sensor import camera_table

    settings_d = _load_settings(settings)
    spp = {}
    if camera_size:                          # a real camera's sensor (e.g. 24mp), the same field of view
        try:
            settings_d = {**settings_d, "camera": camera_table(camera_size, settings_d["camera"])}
        except ValueError as exc:
            raise GonioError(f"--camera-size: {exc}") from None
        if settings_d["camera"]["width"] * settings_d["camera"]["height"] > 1_000_000:
            spp = {"spp": 1}                 # edge anti-aliasing is moot at millions of pixels
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
    server = gonio.sim.serve(settings_d, sample=load_sample(sample), reference=reference_for(settings_d), seed=seed,
                             clock=clock_spec, faults=schedule, block=False, echo=None, **spp)
    try:
        for line in serve_hints(server.paths, server.devices):
            print(line, flush=True)
        while True:                          # serving in the server's thread until Ctrl-C or SIGTERM
            time.sleep(0.5)
    except KeyboardInterrupt:
        print("gonio sim serve: stopped; the ports are closed", flush=True)
    finally:
        server.stop()


def serve_hints(paths: dict, devices: dict) -> list[str]:
    """What ``gonio sim serve`` prints: each port's stable path and device (``NAME PATH -> DEVICE``,
    one line each), then the commands and client calls that reach them, with the real paths."""
    z, m, c = (paths[k] for k in ("zaber", "meter", "camera"))
    mono = f" --monochromator-port {paths['monochromator']}" if "monochromator" in paths else ""
    lines = [f"{name} {paths[name]} -> {devices[name]}" for name in paths]
    return lines + [
        "gonio sim serve: serving until Ctrl-C; the paths above stay valid while it runs. Connect with:",
        f"  gonio devices --port {z} --meter-port {m} --camera {c}{mono}",
        f"  gonio capture --port {z} --meter-port {m} --camera {c}{mono} --out my-session",
        f"  PyVISA (pyvisa-py): pyvisa.ResourceManager('@py').open_resource('ASRL{devices['meter']}::INSTR', "
        "read_termination='\\n', write_termination='\\n')",
        f"  zaber-motion: Connection.open_serial_port('{devices['zaber']}')",
    ]
