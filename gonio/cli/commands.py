"""What each ``gonio`` command does, as calls into the library (gonio/cli/main.py builds the
parser and maps each subcommand here). A command's user errors are GonioError (one line, exit
2); ``env`` turns environment errors (disk full, read-only, a broken pipe) into the same."""

from __future__ import annotations

import functools
import json
import math
import signal
import sys
from pathlib import Path

from gonio.cli.helptext import say
from gonio.cli.progress import Steps
from gonio.core.errors import GonioError

__all__ = ["env", "broken_pipe"]


def _steps(args, title: str) -> Steps:
    """The progress display of a long step: a bar on a terminal, nothing in a pipe or with --quiet."""
    return Steps(title, enabled=not getattr(args, "quiet", False))


def env(func):
    """Environment errors (disk full, read-only, binary garbage) inside a command: one line, exit 2."""
    @functools.wraps(func)
    def run(args):
        from gonio.core.preflight import environment_errors

        if getattr(args, "out", None) is not None and not str(args.out).strip():
            raise GonioError("--out is empty; give a path")
        with environment_errors():
            try:
                return func(args)
            except BrokenPipeError:         # `gonio plans | head`: the reader has what it wanted
                return broken_pipe()
    return run


def broken_pipe() -> int:
    """stdout's reader went away: stop quietly (no second error when Python flushes at exit),
    with the status of a process SIGPIPE ended."""
    import os

    try:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    return 141


@env
def cmd_demo(args):
    from gonio.cli.demo import run_demo

    run_demo(out=Path(args.out), seed=args.seed, plan=args.plan, posterior=args.posterior, quiet=args.quiet)


def _capture_progress(args) -> bool:
    """A capture's bar and status line: on a terminal only, unless --quiet."""
    from gonio.cli.progress import on_terminal

    return not args.quiet and on_terminal()


def cmd_models(args):
    from gonio.cli.listing import models_lines

    print("\n".join(models_lines()))


def cmd_plans(args):
    from gonio.cli.listing import plans_lines

    print("\n".join(plans_lines()))


@env
def cmd_capture(args):
    from gonio.cli import capture as session_runner

    if args.resume:
        given = [f for f, v in (("--sample-id", args.sample_id), ("--sample-description", args.sample_description),
                                ("--operator", args.operator)) if v is not None]
        if given:
            raise GonioError(f"{given[0]} is recorded when a session starts; a resume keeps the session's own")
        return session_runner.resume_cli(Path(args.resume), port=args.port, meter_port=args.meter_port,
                                         camera=args.camera, progress=_capture_progress(args),
                                         monochromator=args.monochromator_port,
                                         rebuild_journal=args.rebuild_journal, remeasure=args.remeasure,
                                         restore_session=args.restore_session)
    for flag, given in (("--rebuild-journal", args.rebuild_journal), ("--remeasure", args.remeasure),
                        ("--restore-session", args.restore_session)):
        if given:
            raise GonioError(f"{flag} repairs an existing session: use it with --resume DIR")
    if args.out is None and not args.dry_run:       # a dry run writes nothing: no folder needed
        raise GonioError("capture needs --out DIR (a new session folder) or --resume DIR")
    if not args.sim and not args.port:
        raise GonioError("capture needs --sim (the simulated instrument) or --port URL --meter-port URL for hardware")
    from gonio.bench.settings import load_settings
    from gonio.cli.listing import sample_path

    # the settings file and the [session] options (sample id, description, operator), checked
    # before anything is written; session.toml records them with the other settings
    settings = load_settings(args.settings, _session_options(args))
    return session_runner.capture_cli(Path(args.out) if args.out is not None else None, sim=args.sim,
                                      sample=sample_path(args.sample), plan=args.plan, seed=args.seed,
                                      settings=settings, port=args.port, meter_port=args.meter_port, camera=args.camera,
                                      dry_run=args.dry_run, progress=_capture_progress(args),
                                      errors=args.errors, calibration=args.calibration, points=args.points,
                                      target_rel_u=args.target_rel_u, candidates=args.candidates,
                                      budget_minutes=args.budget_minutes, target_de00=args.target_de00,
                                      monochromator=args.monochromator_port, criterion=args.criterion)


@env
def cmd_verify(args):
    from gonio.cli.verify import verify_cli

    with _steps(args, "verify"):
        return verify_cli(args.session)


@env
def cmd_calibrate(args):
    from gonio.bench.calibrate import calibrate_cli
    from gonio.cli.capture import _camera

    camera = _camera(args.camera) if args.camera else None
    with _steps(args, "calibrate") as progress:
        return calibrate_cli(Path(args.out), sim=args.sim, settings=args.settings, errors=args.errors, seed=args.seed,
                             port=args.port, meter_port=args.meter_port, camera=camera, progress=progress, say=say)


@env
def cmd_export(args):
    from gonio.bench.dataset.export import export

    from gonio.bench.dataset.cf import parse_attributes

    try:
        attrs = parse_attributes(args.attr)
    except ValueError as exc:
        raise GonioError(str(exc)) from None
    with _steps(args, "export"):
        path = export(Path(args.session), chart=Path(args.colour_chart) if args.colour_chart else None, attrs=attrs)
    done, planned, complete = _export_counts(path)
    if complete is False or (complete is None and planned is not None and done is not None and done < planned):
        of = f"{done} of {planned} planned points" if planned is not None else f"{done} points, the plan not finished"
        say(f"wrote {path}: PARTIAL, {of} (the session stopped early; "
            f"`gonio capture --resume {args.session}` measures the rest, then export again)")
    else:
        print(f"wrote {path}" + (f" ({done} points)" if done is not None else ""))


def _export_counts(path):
    """(points in the dataset, points planned, complete) from its attributes; None where not recorded."""
    import xarray as xr

    try:
        with xr.open_dataset(path, engine="h5netcdf") as ds:
            done = int(ds.sizes.get("point", 0))
            if "wavelength" in ds.sizes and "plan_index" in ds:     # spectral: a point per (geometry, wavelength)
                done = int((ds["plan_index"].values >= 0).sum())
            plan = json.loads(ds.attrs.get("plan", "{}"))
            complete = ds.attrs.get("complete")
    except (OSError, ValueError, TypeError):
        return None, None, None
    planned = len(plan["points"]) if isinstance(plan, dict) and isinstance(plan.get("points"), list) else None
    return done, planned, (None if complete is None else bool(int(complete)))


@env
def cmd_fit(args):
    from gonio.cli.fit import fit_batch_cli, fit_cli

    # a scene fit never estimates: the flag that asks for it is refused there
    if args.estimate_angles and args.scene is not None:
        raise GonioError("--estimate-angles goes with a fit of dataset.nc files: leave out --scene")
    if args.batch:
        fit_batch_cli([Path(d) for d in args.dataset], model=args.model, options=args.option, out=Path(args.out),
                      seed=args.seed, loss=args.loss, scheduler=args.scheduler, workers=args.workers,
                      dashboard=args.dashboard, quiet=args.quiet, estimate_angles=args.estimate_angles)
        return
    if len(args.dataset) != 1:
        raise GonioError("give one dataset, or --batch to fit several (the fit files then go into --out DIR)")
    if args.scene is not None:
        from gonio.cli.scene import fit_scene_cli

        if args.posterior or args.colour_space != "srgb":
            raise GonioError("--scene fits a measured material in linear sRGB; leave out --posterior and --colour-space")
        fit_scene_cli(Path(args.dataset[0]), scene=args.scene, model=args.model, options=args.option,
                      out=Path(args.out), seed=args.seed, loss=args.loss, size=args.scene_size, spp=args.scene_spp,
                      k=args.scene_light_samples, threshold=args.threshold, time_limit=args.scene_time_limit,
                      quiet=args.quiet)
        return
    fit_cli(Path(args.dataset[0]), model=args.model, options=args.option, out=Path(args.out), seed=args.seed,
            loss=args.loss, posterior=args.posterior, colour_space=args.colour_space, quiet=args.quiet,
            estimate_angles=args.estimate_angles)


@env
def cmd_render(args):
    from gonio.cli.fit import render_cli

    render_cli(Path(args.fit), Path(args.dataset), Path(args.out), variant=args.variant, preview=args.preview,
               measured=args.measured, size=args.size, spp=args.spp, quiet=args.quiet)


@env
def cmd_convert(args):
    from gonio.cli.convert import convert_cli

    convert_cli(Path(args.source), Path(args.out), args.to, attrs=args.attr)


@env
def cmd_report(args):
    from gonio.core.preflight import check_output_file
    from gonio.bench.report import write_report

    folder = Path(args.folder)
    if folder.is_dir():     # (a missing folder gets write_report's own one line)
        check_output_file(Path(args.out) if args.out else folder / "report.html", "report file")
    with _steps(args, "report") as progress:
        path = write_report(folder, Path(args.out) if args.out else None, approver=args.approver,
                            approver_role=args.approver_role, progress=progress)
    print(f"wrote {path}")


def cmd_settings_show(args):
    from gonio.bench.settings import show_settings
    from gonio.cli.listing import settings_lines_with_units

    print("\n".join(settings_lines_with_units(show_settings(args.settings, _session_options(args)))))


def _session_options(args) -> dict:
    """``--sample-id``, ``--sample-description``, ``--operator`` as a ``[session]`` settings table."""
    return {"session": {"sample_id": getattr(args, "sample_id", None),
                        "sample_description": getattr(args, "sample_description", None),
                        "operator": getattr(args, "operator", None)}}


def _check_clock(spec: str) -> None:
    """``--clock``: instant, realtime/real, or a finite time scale factor > 0."""
    if str(spec).strip().lower() in ("instant", "realtime", "real"):
        return
    try:
        scale = float(spec)
    except ValueError:
        scale = math.nan
    if not (math.isfinite(scale) and 1e-6 <= scale <= 1e6):
        raise GonioError(f"--clock {spec!r}: use instant, realtime or a time scale factor between 1e-6 and 1e6 "
                         "such as 10")


@env
def cmd_sim_serve(args):
    from gonio.cli import capture as session_runner

    _check_clock(args.clock)
    # SIGTERM and SIGHUP end the server like Ctrl-C: ptys closed, its /tmp/gonio-sim-* folder removed

    def _stop(signum, frame):
        raise KeyboardInterrupt

    previous = {sig: signal.signal(sig, _stop) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        from gonio.cli.listing import sample_path

        session_runner.serve_cli(sample=sample_path(args.sample), seed=args.seed, settings=args.settings, clock=args.clock,
                                 faults=args.faults, camera_size=args.camera_size)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def cmd_estop(args):
    from gonio.cli import estop

    return estop.run(args.port, args.baud)
