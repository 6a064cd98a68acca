"""gonio.bench.drivers: the bench's device layer, apart from the capture loop.

One module per device kind, laid out as ophyd-async's devices and lewis's device/interface
split are. Every device says what it is (``identify()``: a Zaber device's ids as a dict, an
instrument's ``*IDN?`` as text) and is read and set through typed methods (``positions() ->
dict[str, float]``, ``move_to``, ``power() -> float``, ``set_flux(fraction)``,
``expose(seconds, path) -> sha256``). The drivers that own a port (`ZaberChain`, `PowerMeter`,
the cameras) open it when made and close it with ``close()`` or a ``with`` block; the stages
and the LED are devices on the chain's port and close with it.

* `serialport`: `SerialDevice`, the base of the serial drivers (``serial_for_url`` opens the
  port, so ``sim://NAME/...``, a pty and ``/dev/ttyUSB0`` are the same; one-line port errors).
* `zaber_protocol`: the Zaber ASCII bytes, pure functions (`lrc`, `format_command`,
  `parse_reply`, `Reply`, the flag and rejection meanings).
* `zaber`: `ZaberChain`, the daisy chain on one port (message ids, retries, continued replies,
  alerts, broadcast), and `emergency_stop`.
* `stages`: `Goniometer`, the rotary axes in degrees (limits, shortest-way moves, homing).
* `led`: `LedSource`, the lamp on the chain.
* `meter`: `PowerMeter`, the SCPI source monitor (pyserial or VISA).
* `camera`: `SimCamera`, `WatchedFolderCamera`, `Gphoto2Camera` and RAW decoding.
* `identify`: what is on each port (Zaber device ids, ``*IDN?``), journalled once per run.

The capture loop (`gonio.bench.capture`) and the operator commands use the devices only
through these classes; the simulator (`gonio.sim`) speaks the same bytes at the far end.
"""

from .camera import (BadDelivery, Delivery, Gphoto2Camera, RawFrame, SimCamera, WatchedFolderCamera, decode_raw, deliver,
                     read_verified)
from .led import LedSource
from .meter import PowerMeter, is_visa_resource
from .serialport import SerialDevice
from .stages import Goniometer, MoveError, shortest_equivalent
from .zaber import ZaberChain, emergency_stop
from .zaber_protocol import FLAG_MEANINGS, REJECT_MEANINGS, Reply, format_command, lrc, parse_reply

__all__ = [
    "BadDelivery", "Delivery", "FLAG_MEANINGS", "REJECT_MEANINGS", "Gphoto2Camera", "Goniometer", "LedSource", "MoveError",
    "PowerMeter", "RawFrame", "Reply", "SerialDevice", "SimCamera", "WatchedFolderCamera", "ZaberChain",
    "decode_raw", "deliver", "emergency_stop", "format_command", "is_visa_resource", "lrc", "parse_reply",
    "read_verified", "shortest_equivalent",
]
