"""gonio.bench.drivers: the bench's device layer, apart from the capture loop.

One module per device kind. Every device says what it is (``identify()``) and is read and set
through typed methods (``positions() -> dict[str, float]``, ``move_to``, ``power() -> float``,
``set_flux(fraction)``, ``expose(seconds, path) -> sha256``). The drivers that own a port
(`ZaberChain`, `PowerMeter`, the cameras) open it when made and close it with ``close()`` or
a ``with`` block; the stages and the LED are devices on the chain's port and close with it.

Modules: `serialport` (`SerialDevice`, the serial base), `zaber_protocol` (the Zaber ASCII
bytes, pure functions), `zaber` (`ZaberChain`, `emergency_stop`), `stages` (`Goniometer`),
`led` (`LedSource`), `meter` (`PowerMeter`, SCPI), `camera` (`SimCamera`,
`WatchedFolderCamera`, `Gphoto2Camera`, RAW decoding), `identify` (what is on each port).
The capture loop (`gonio.bench.session.capture`) and the operator commands use the devices
only through these classes; the simulator (`gonio.sim`) speaks the same bytes at the far end.
"""

# Layout as ophyd-async's devices and lewis's device/interface split. identify() gives a
# Zaber device's ids as a dict, an instrument's *IDN? as text.
# serialport: serial_for_url opens the port, so sim://NAME/..., a pty and /dev/ttyUSB0 are
# the same; one-line port errors. zaber_protocol: lrc, format_command, parse_reply, Reply, the
# flag and rejection meanings. zaber: the daisy chain on one port (message ids, retries,
# continued replies, alerts, broadcast). stages: the rotary axes in degrees (limits,
# shortest-way moves, homing). led: the lamp on the chain. meter: the SCPI source monitor
# (pyserial or VISA). identify: Zaber device ids and *IDN?, journalled once per run.

# The names below load their modules on first use (PEP 562), so `gonio estop` reaches the stages
# through zaber.py alone: the camera's RAW decoding (numpy, rawpy, tifffile) is not imported on
# that path (issue 40: the emergency stop must not wait for imports).
from importlib import import_module as _import_module

_WHERE = {
    **dict.fromkeys(("BadDelivery", "Delivery", "Gphoto2Camera", "RawFrame", "SimCamera", "WatchedFolderCamera",
                     "camera_from_spec", "decode_raw", "deliver", "open_camera", "read_verified"), "camera"),
    "LedSource": "led", "PowerMeter": "meter", "is_visa_resource": "meter", "SerialDevice": "serialport",
    "Goniometer": "stages", "MoveError": "stages", "shortest_equivalent": "stages",
    "ZaberChain": "zaber", "emergency_stop": "zaber",
    **dict.fromkeys(("FLAG_MEANINGS", "REJECT_MEANINGS", "Reply", "format_command", "lrc", "parse_reply"),
                    "zaber_protocol"),
}


def __getattr__(name):
    if name in _WHERE:
        value = getattr(_import_module(f"{__name__}.{_WHERE[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "BadDelivery", "Delivery", "FLAG_MEANINGS", "REJECT_MEANINGS", "Gphoto2Camera", "Goniometer", "LedSource", "MoveError",
    "PowerMeter", "RawFrame", "Reply", "SerialDevice", "SimCamera", "WatchedFolderCamera", "ZaberChain",
    "camera_from_spec", "decode_raw", "deliver", "emergency_stop", "open_camera", "format_command", "is_visa_resource", "lrc", "parse_reply",
    "read_verified", "shortest_equivalent",
]
