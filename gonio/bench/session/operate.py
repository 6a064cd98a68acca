"""What the operator commands share: target checks, homed-or-refuse, checked moves, where the
stages are, the camera from ``--camera`` (see `operator`)."""

from __future__ import annotations

import numpy as np

from gonio.bench.plan import kinematics
from gonio.bench.settings import AXES
from gonio.core.errors import GonioError

__all__ = ["check_stage", "goniometer", "move", "open_camera", "require_homed", "target_of", "where"]


def _wrap(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def check_stage(stage, settings, flag: str = "--stage") -> None:
    """Stage angles ``(yaw, tilt, azimuth, lamp)`` against the ``[axes]`` limits and the lamp zone."""
    axes = settings["axes"]
    for name, v in zip(AXES, stage):
        lo, hi = float(axes[name][2]), float(axes[name][3])
        if not lo - 1e-9 <= v <= hi + 1e-9:
            raise GonioError(f"{flag}: {name} = {v:g} deg is outside its limits [{lo:g}, {hi:g}] deg; "
                             "give an angle inside them")
    block = float(axes.get("lamp_block_deg", 0.0))
    if abs(_wrap(stage[3])) < block:
        raise GonioError(f"{flag}: lamp = {stage[3]:g} deg puts the lamp in front of the camera "
                         f"(|lamp| < {block:g} deg); give another lamp angle")


def target_of(args, settings) -> np.ndarray | None:
    """The stage angles (4,) of ``--stage`` or ``--angles``, checked; None if neither is given."""
    if getattr(args, "angles", None) is not None:
        ti, pi_, to, po = args.angles
        r = kinematics.reachable([ti], [pi_], [to], [po], settings)
        if not r.ok[0]:
            raise GonioError(f"--angles {ti:g},{pi_:g},{to:g},{po:g} cannot be reached: {r.reason[0]}; "
                             "give another geometry")
        return np.asarray(r.stage_deg[0], float)
    if getattr(args, "stage", None) is not None:
        stage = np.asarray(args.stage, float)
        check_stage(stage, settings)
        return stage
    return None


def goniometer(args, settings):
    from gonio.bench.drivers import Goniometer, ZaberChain       # a command's device: loaded when it runs

    chain = ZaberChain(args.port, args.baud, 1.0)
    try:
        gonio = Goniometer(chain, settings, poll_interval_s=0.05)
        gonio.connect()
    except BaseException:
        chain.close()
        raise
    return chain, gonio


def require_homed(gonio, port: str) -> None:
    flags = [f for f in gonio.flags() if f in ("WR", "WH")]
    if flags:
        raise GonioError(f"the stages are not homed ({' '.join(sorted(set(flags)))}); run `gonio home --port {port}` "
                         "first")


def move(gonio, stage, port: str) -> dict:
    """Move to ``stage`` (checked); a Ctrl-C during the move stops the stages."""
    require_homed(gonio, port)
    goal = dict(zip(AXES, (float(v) for v in stage)))
    for name, deg in goal.items():           # the controller's own limits, before anything moves
        a = gonio.axes[name]
        if not a.lo_deg - 1e-9 <= deg <= a.hi_deg + 1e-9:
            raise GonioError(f"{name} = {deg:g} deg is outside the limits the controller reports "
                             f"[{a.lo_deg:g}, {a.hi_deg:g}] deg; give an angle inside them")
    try:
        return gonio.move_to(goal)
    except KeyboardInterrupt:
        gonio.stop()
        raise


def where(gonio) -> str:
    pos = gonio.positions()
    stage = np.array([pos[n] for n in AXES])
    ang = kinematics.forward_angles(stage)
    return ("stages " + " ".join(f"{n} {pos[n]:.3f}" for n in AXES) + " deg; directions theta_i "
            f"{ang[0]:.2f} phi_i {ang[1]:.2f} theta_o {ang[2]:.2f} phi_o {ang[3]:.2f} deg")


def open_camera(spec: str):
    """A camera from ``--camera`` (:func:`gonio.bench.drivers.camera.open_camera`)."""
    from gonio.bench.drivers.camera import open_camera as _open

    return _open(spec, timeout=30.0)
