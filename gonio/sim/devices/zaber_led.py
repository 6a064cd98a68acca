"""Device 2 of the simulated chain: the LED source, its channels addressed as axes.

It answers what zaber-motion 10.3's Illuminator API sends (lamp on/off, lamp.status, lamp.flux,
lamp.flux.max, lamp.temperature); where the documents are silent its choices, and the
invented identification, are in the comment below."""

# As zaber-motion 10.3's Illuminator API drives it (observed on the wire): a channel is an axis;
# ``/2 1 lamp on``, ``/2 1 lamp off``, ``/2 1 get lamp.status``, ``/2 1 get lamp.flux.max``,
# ``/2 1 set lamp.flux F`` with ``F = fraction * lamp.flux.max``; ``/2 0 lamp off`` switches every
# channel off. One channel (``system.axiscount`` 1): the instrument's ``Lamp``. Chosen where the
# documents are silent (invented):
# - ``lamp.status``: 2 on, 1 off. zaber-motion 10.3's ``IlluminatorChannel.is_on()`` is true for 2
# only (observed: 0, 1, 3 and 4 all read as off); 1 for off is inferred, not published.
# - ``lamp.flux``: 3 decimals, units of ``lamp.flux.max`` (``Lamp.flux_max``, default 1.0); a value
# outside ``[0, lamp.flux.max]`` -> ``BADDATA``. ``lamp.temperature``: deg C, 1 decimal.
# - ``/2 0 lamp on`` switches every channel on; axis-0 ``get``/``set`` of a channel setting reads or
# sets every channel, as for the axis settings of a motion controller.
# - Identification: device id 30311, serial 92001, firmware 7.38 build 18426, peripheral id 58001:
# invented. The device is modelled on Zaber's X-LCA4 LED controller (zaber-motion's Illuminator
# drives it), whose device id only Zaber's device database gives; that database is not on this
# machine and no public source read offline names the id (issue 40), so zaber-motion's
# ``identify()`` of this device fails with its ``DeviceDbFailedException`` (no silent guess), and
# ``detect_devices(identify_devices=False)``, generic commands and the Illuminator API work.

from __future__ import annotations

import math

from gonio.sim.devices.zaber_common import Device, Reject

__all__ = ["LedDevice"]

LED_IDENT = {"deviceid": 30311, "system.serial": 92001, "version": "7.38",
             "version.build": 18426, "peripheralid": 58001}
_READ_ONLY = ("lamp.status", "lamp.flux.max", "lamp.temperature", "peripheralid", "peripheral.id")


class LedDevice(Device):
    """Device 2: the LED source."""

    def __init__(self, chain, number: int):
        super().__init__(chain, number, LED_IDENT)

    @property
    def lamp(self):
        return self.inst.lamp

    def axis_count(self) -> int:
        return 1

    def command(self, cmd) -> str:
        w = cmd.words
        op = w[0]
        if op in ("stop", "estop") and len(w) == 1:
            return "0"
        if op == "warnings":
            if w[1:] not in ([], ["clear"]):
                raise Reject("BADCOMMAND")
            return "00"
        if op == "lamp":
            if len(w) != 2 or w[1] not in ("on", "off"):
                raise Reject("BADDATA" if len(w) == 2 else "BADCOMMAND")
            self.lamp.switch(self.now(), w[1] == "on")     # one channel: axis 0 or 1 alike
            return "0"
        raise Reject("BADCOMMAND")

    def get_axis(self, key: str, axis: int) -> str:
        lamp = self.lamp
        if key == "lamp.flux":
            return f"{lamp.flux * lamp.flux_max:.3f}"
        if key == "lamp.flux.max":
            return f"{lamp.flux_max:.3f}"
        if key == "lamp.temperature":
            return f"{lamp.temperature(self.now()):.1f}"
        if key == "lamp.status":
            return "2" if lamp.on else "1"
        return super().get_axis(key, axis)

    def set_axis(self, key: str, value: str, axes: list) -> None:
        if key != "lamp.flux":
            raise Reject("BADCOMMAND")
        try:
            f = float(value)
        except ValueError:
            raise Reject("BADDATA") from None
        fmax = self.lamp.flux_max
        if not (math.isfinite(f) and 0.0 <= f <= fmax * (1 + 1e-9)):
            raise Reject("BADDATA")
        self.lamp.set_flux(self.now(), min(1.0, f / fmax))
