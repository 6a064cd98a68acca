"""gonio.bench: the controller a lab operator runs, and the ``gonio`` command line.

Drivers talk to hardware only through pyserial's ``serial_for_url``, so ``sim://NAME/zaber``,
a pseudo-terminal and ``/dev/ttyUSB0`` are the same to them::

    from gonio.bench import load_plan, load_settings, capture, export
    settings = load_settings()                  # bench/instrument.toml (+ a user's overrides)
    plan = load_plan("standard")                # a preset, or a TOML/CSV file
    summary = capture("session/", plan, settings, "/dev/ttyUSB0", "/dev/ttyUSB1", "/dev/ttyUSB2")
    export("session/")                          # session/dataset.nc

The names below load their modules on first use, so ``gonio --help`` stays quick.
"""

from importlib import import_module

_WHERE = {
    "GonioError": ".errors", "capture": ".capture", "resume": ".capture", "CaptureSummary": ".capture",
    "export": ".export", "to_dataset": ".export",
    "load_plan": ".plans", "check_plan": ".plans", "dry_run": ".plans", "Plan": ".plans",
    "load_settings": "._settings", "default_settings": "._settings",
    "forward": ".kinematics", "inverse": ".kinematics",
    "ZaberChain": ".drivers", "Goniometer": ".drivers", "LedSource": ".drivers", "emergency_stop": ".drivers",
    "PowerMeter": ".drivers", "SimCamera": ".drivers", "WatchedFolderCamera": ".drivers",
    "Gphoto2Camera": ".drivers", "decode_raw": ".drivers",
    "write_report": ".report", "run_demo": ".demo",
}

__all__ = sorted(_WHERE)


def __getattr__(name):
    if name in _WHERE:
        return getattr(import_module(_WHERE[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
