"""Operator commands a lab runs before a long capture: ``gonio devices``, ``home``, ``move``,
``jog`` and ``shot``.

Each talks to the instrument through the production drivers, so a ``sim://NAME/PORT`` URL, a
pseudo-terminal of ``gonio sim serve`` and /dev/ttyUSB0 are the same to it. Every input is
checked before a port is opened, and every target before anything moves: stage angles against
the ``[axes]`` limits and the lamp-in-front-of-the-camera zone, direction angles through
`kinematics.reachable` (horizon, lamp, limits, the squares in view), then against the limits
the controller itself reports. A move needs homed stages (``gonio home`` first). Bad input is
one line on stderr and exit status 2 (`cli.main`).
``gonio shot`` takes one bracketed exposure at a pose as a capture does for one point (a probe,
rungs that keep the regions unsaturated and bring the darkest to the noise floor's SNR, a dark
frame per exposure with the lamp off) and writes the DNG files, an HDR preview (PNG, regions
outlined) and ``shot.json`` (pose, exposures, monitor readings, regions and how they were
found, the devices' identification) into a new folder.
"""

from __future__ import annotations

import argparse
import functools
import math
from pathlib import Path

import numpy as np

from gonio.bench.session import operate as _operate
from gonio.bench.settings import AXES
from gonio.core.errors import GonioError

__all__ = ["parse_four", "register"]

MAX_JOG_DEG = 90.0


# --------------------------------------------------------------------------- argument types
def parse_four(names: str):
    """An argparse type: four finite numbers ``A,B,C,D`` (degrees) named ``names``."""
    def parse(text: str) -> tuple[float, ...]:
        parts = str(text).split(",")
        try:
            vals = tuple(float(p) for p in parts)
        except ValueError:
            vals = ()
        if len(vals) != 4 or not all(math.isfinite(v) for v in vals):
            raise argparse.ArgumentTypeError(f"{text[:40]!r} is not four numbers {names} in degrees "
                                             "(comma-separated, no spaces), e.g. 30,0,45,180")
        return vals
    return parse


def _baud(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = 0
    if not 300 <= v <= 4_000_000:
        raise argparse.ArgumentTypeError(f"baud rate {text[:20]!r}: give an integer such as 9600 or 115200")
    return v


def _jog_step(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and 0 < abs(v) <= MAX_JOG_DEG):
        raise argparse.ArgumentTypeError(f"{text[:20]!r}: give a step in degrees, non-zero, between "
                                         f"-{MAX_JOG_DEG:g} and {MAX_JOG_DEG:g} (use gonio move for larger moves)")
    return v


def _flux(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and 0 < v <= 1):
        raise argparse.ArgumentTypeError(f"{text[:20]!r}: give the LED flux as a fraction in (0, 1]")
    return v


def _url(text: str) -> str:
    if not text.strip() or len(text) > 1024 or any(ord(c) < 32 for c in text):
        raise argparse.ArgumentTypeError("give a serial port, a pyserial URL (sim://NAME/PORT) or a VISA resource")
    return text


def _settings(args):
    from gonio.bench.settings import load_settings

    return load_settings(args.settings)


def _one_line(func):
    """Environment errors one line; every GonioError message on one line."""
    @functools.wraps(func)
    def run(args):
        from gonio.core.preflight import environment_errors

        try:
            with environment_errors():
                return func(args)
        except GonioError as exc:
            text = " ".join(str(exc).split())
            if text != str(exc):
                raise GonioError(text) from None
            raise
    return run


# --------------------------------------------------------------------------- commands
@_one_line
def cmd_devices(args) -> int:
    from gonio.bench.drivers.probe import probe_ports
    from gonio.core.devices import PORTS

    urls = {p.name: getattr(args, p.option.lstrip("-").replace("-", "_"), None) for p in PORTS}
    if not any(urls.values()):
        probe_ports(urls, {}, args.baud)           # says which options name the ports
    print("\n".join(probe_ports(urls, _settings(args), args.baud)))
    return 0


@_one_line
def cmd_home(args) -> int:
    settings = _settings(args)
    chain, gonio = _operate.goniometer(args, settings)
    try:
        try:
            gonio.home()
        except KeyboardInterrupt:
            gonio.stop()
            raise
        print(f"homed: {_operate.where(gonio)}")
    finally:
        chain.close()
    return 0


@_one_line
def cmd_move(args) -> int:
    settings = _settings(args)
    stage = _operate.target_of(args, settings)
    chain, gonio = _operate.goniometer(args, settings)
    try:
        _operate.move(gonio, stage, args.port)
        print(f"moved: {_operate.where(gonio)}")
    finally:
        chain.close()
    return 0


@_one_line
def cmd_jog(args) -> int:
    settings = _settings(args)
    chain, gonio = _operate.goniometer(args, settings)
    try:
        _operate.require_homed(gonio, args.port)
        pos = gonio.positions()
        stage = np.array([pos[n] for n in AXES])
        stage[AXES.index(args.axis)] += args.by
        _operate.check_stage(stage, _jog_zone(settings, args.axis, pos["lamp"]), f"--axis {args.axis} --by {args.by:g}")
        _operate.move(gonio, stage, args.port)
        print(f"jogged {args.axis} by {args.by:+g} deg: {_operate.where(gonio)}")
    finally:
        chain.close()
    return 0


def _jog_zone(settings, axis: str, lamp_deg: float):
    """The settings a jog's target is checked against: the lamp-in-front-of-the-camera zone only
    where the jog moves the lamp from outside it. A jog of another axis leaves the lamp where it
    is (at home, lamp 0, inside the zone: jogging must still work there), and a lamp inside the
    zone may be jogged (out of it, or along it)."""
    block = float(settings["axes"].get("lamp_block_deg", 0.0))
    if axis == "lamp" and abs((lamp_deg + 180.0) % 360.0 - 180.0) >= block:
        return settings
    return {**settings, "axes": {**settings["axes"], "lamp_block_deg": 0.0}}


@_one_line
def cmd_shot(args) -> int:
    from gonio.bench.session.shot import take_shot

    settings = _settings(args)
    stage = _operate.target_of(args, settings)
    out = Path(args.out)
    from gonio.core.preflight import check_output_dir

    check_output_dir(out, "--out")
    if out.is_dir() and any(out.iterdir()):
        raise GonioError(f"--out {out} is not empty; give a new folder (a shot never overwrites files)")
    result = take_shot(args, settings, stage, out)
    print(result)
    return 0


# --------------------------------------------------------------------------- parser
def _common(p, port_required: bool = True) -> None:
    p.add_argument("--port", required=port_required, type=_url,
                   help="Zaber chain: serial port, pty or pyserial URL (e.g. /dev/ttyUSB0, sim://NAME/zaber)")
    p.add_argument("--baud", type=_baud, default=115200, help="baud rate (default 115200; 9600 on older devices)")
    p.add_argument("--settings", help="instrument settings TOML overriding gonio/bench/instrument.toml")


def _pose(p, required: bool) -> None:
    g = p.add_mutually_exclusive_group(required=required)
    g.add_argument("--stage", type=parse_four("YAW,TILT,AZIMUTH,LAMP"), metavar="YAW,TILT,AZIMUTH,LAMP",
                   help="stage angles, degrees")
    g.add_argument("--angles", type=parse_four("THETA_I,PHI_I,THETA_O,PHI_O"), metavar="THETA_I,PHI_I,THETA_O,PHI_O",
                   help="illumination and view directions in the sample frame, degrees")


def register(sub, bench_sub=None) -> None:
    """Add the operator commands to ``gonio``'s subparsers (and ``gonio bench capture`` to ``bench_sub``)."""
    d = sub.add_parser("devices", help="what is on each port, identified (Zaber ids, serials, firmware, axes; *IDN?)")
    _common(d, port_required=False)
    d.add_argument("--meter-port", type=_url, help="power meter: serial port, pyserial URL or VISA resource")
    d.add_argument("--monochromator-port", type=_url, help="Cornerstone monochromator: serial port or pyserial URL")
    d.add_argument("--camera", type=_url, help="camera: serial URL of a camera port, folder:PATH or gphoto2")
    d.set_defaults(func=cmd_devices)

    h = sub.add_parser("home", help="home every stage axis (clears WR/WH)")
    _common(h)
    h.set_defaults(func=cmd_home)

    m = sub.add_parser("move", help="move the stages to stage angles or to a geometry; limits checked first")
    _common(m)
    _pose(m, required=True)
    m.set_defaults(func=cmd_move)

    j = sub.add_parser("jog", help="move one axis by a few degrees; limits checked first")
    _common(j)
    j.add_argument("--axis", required=True, choices=AXES, help="the axis to move")
    j.add_argument("--by", required=True, type=_jog_step, metavar="DEG", help="step in degrees (|DEG| <= 90)")
    j.set_defaults(func=cmd_jog)

    s = sub.add_parser("shot", help="one bracketed exposure at a pose: DNG files, a PNG preview and shot.json")
    _common(s)
    s.add_argument("--meter-port", required=True, type=_url, help="power meter port, URL or VISA resource")
    s.add_argument("--camera", required=True, type=_url, help="camera: serial URL, folder:PATH or gphoto2")
    s.add_argument("--out", required=True, help="new (or empty) folder for the files")
    s.add_argument("--flux", type=_flux, help="LED flux as a fraction of lamp.flux.max (default [lamp] flux)")
    _pose(s, required=False)
    s.set_defaults(func=cmd_shot)

    if bench_sub is not None:
        bc = bench_sub.add_parser("capture", help="capture pipeline: per-point wall time against the motion + "
                                                  "exposure lower bound, default and full-size camera")
        bc.add_argument("--points", type=int, default=3, help="plan points per camera (1..20, default 3)")
        bc.add_argument("--full-size", default="24mp", metavar="SIZE",
                        help="the real camera's sensor: 24mp (6000x4000, 14-bit RGGB; the default) or WIDTHxHEIGHT")
        bc.add_argument("--skip-full", action="store_true", help="the default camera only")
        bc.set_defaults(func=_cmd_bench_capture)


def _cmd_bench_capture(args) -> int:
    from gonio.perf.capture import run_cli

    return _one_line(run_cli)(args)
