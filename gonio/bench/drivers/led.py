"""The LED source: a Zaber-protocol lamp controller on the stages' chain (device 2 by default)."""

from __future__ import annotations

import math

from gonio.core.errors import DeviceError, GonioError
from gonio.bench.drivers.zaber import ZaberChain

__all__ = ["LedSource"]


class LedSource:
    """The LED source, a Zaber-protocol device (device 2 by default), driven as zaber-motion's
    Illuminator API drives it (observed with zaber-motion 10.3 on the wire):

    * a channel is an axis: ``/2 1 lamp on``, ``/2 1 get lamp.flux.max``,
      ``/2 1 set lamp.flux F`` with ``F = fraction * lamp.flux.max``;
    * ``off`` is ``/2 0 lamp off``, every channel (the safe stop, as ``Illuminator.turn_off``).

    Parameters
    ----------
    chain : ZaberChain
    device : int
        Address of the LED controller.
    channel : int
        The channel (axis) the LED is on, 1..n.
    """

    def __init__(self, chain: ZaberChain, device: int = 2, channel: int = 1):
        if not (isinstance(channel, int) and 1 <= channel <= 9):
            raise GonioError(f"lamp channel {channel!r} is invalid; fix [lamp] channel (1..9) in the settings")
        self.chain = chain
        self.device = device
        self.channel = channel
        self._flux_max: float | None = None

    def identify(self) -> dict:
        """The identification of the LED controller (`ZaberChain.identify`)."""
        return self.chain.identify(self.device)

    def on(self) -> None:
        """Switch the channel on (``/D C lamp on``)."""
        self.chain.request(self.device, self.channel, "lamp on")

    def off(self) -> None:
        """Switch every channel off (``/D 0 lamp off``)."""
        self.chain.request(self.device, 0, "lamp off")

    def flux_max(self) -> float:
        """``lamp.flux.max`` of the channel (read once)."""
        if self._flux_max is None:
            v = self.chain.get(self.device, self.channel, "lamp.flux.max")
            if len(v) != 1 or not (math.isfinite(v[0]) and v[0] > 0):
                raise DeviceError(f"Zaber device {self.device} channel {self.channel} reports lamp.flux.max "
                                  f"{v!r}; check that [lamp] device and channel name an LED")
            self._flux_max = v[0]
        return self._flux_max

    def set_flux(self, flux: float) -> None:
        """Set the flux as a fraction (0..1) of the channel's ``lamp.flux.max``."""
        if not (isinstance(flux, (int, float)) and math.isfinite(flux) and 0.0 <= flux <= 1.0):
            raise GonioError(f"lamp flux {flux!r} is outside [0, 1]; fix [lamp] flux in the settings")
        self.chain.set(self.device, self.channel, "lamp.flux", f"{flux * self.flux_max():.6g}")

    def temperature(self) -> float:
        """LED temperature (degrees Celsius)."""
        v = self.chain.get(self.device, self.channel, "lamp.temperature")
        if not v or not math.isfinite(v[0]):
            raise DeviceError(f"Zaber device {self.device} channel {self.channel} gives no lamp.temperature")
        return v[0]
