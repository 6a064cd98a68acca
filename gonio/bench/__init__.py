"""gonio.bench: the controller a lab operator runs, and the ``gonio`` command line.

Drivers talk to hardware only through pyserial's ``serial_for_url``, so ``sim://NAME/zaber``,
a pseudo-terminal and ``/dev/ttyUSB0`` are the same to them::

    from gonio.bench import load_plan, load_settings, capture, export
    settings = load_settings()                  # gonio/bench/instrument.toml (+ a user's overrides)
    plan = load_plan("standard")                # a preset, or a TOML/CSV file
    summary = capture("session/", plan, settings, "/dev/ttyUSB0", "/dev/ttyUSB1", "/dev/ttyUSB2")
    export("session/")                          # session/dataset.nc

The names below load their modules on first use, so ``gonio --help`` stays quick.
"""

from importlib import import_module

_WHERE = {
    "GonioError": "gonio.core.errors", "capture": "gonio.bench.session.capture", "resume": "gonio.bench.session.capture", "CaptureSummary": "gonio.bench.session.capture",
    "export": "gonio.bench.dataset.export", "to_dataset": "gonio.bench.dataset.export",
    "load_plan": "gonio.bench.plan.plans", "check_plan": "gonio.bench.plan.plans", "dry_run": "gonio.bench.plan.plans", "Plan": "gonio.bench.plan.plans",
    "load_settings": "gonio.bench.settings", "default_settings": "gonio.bench.settings",
    "forward": "gonio.bench.plan.kinematics", "inverse": "gonio.bench.plan.kinematics",
    "ZaberChain": "gonio.bench.drivers", "Goniometer": "gonio.bench.drivers", "LedSource": "gonio.bench.drivers", "emergency_stop": "gonio.bench.drivers",
    "PowerMeter": "gonio.bench.drivers", "SimCamera": "gonio.bench.drivers", "WatchedFolderCamera": "gonio.bench.drivers",
    "Gphoto2Camera": "gonio.bench.drivers", "decode_raw": "gonio.bench.drivers",
    "write_report": "gonio.bench.report",
}

__all__ = sorted(_WHERE)


def __getattr__(name):
    if name in _WHERE:
        return getattr(import_module(_WHERE[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
