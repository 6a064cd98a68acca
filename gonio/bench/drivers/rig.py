"""The bench's devices opened together: the Zaber chain (stages and LED), the power meter and
the camera of one capture, closed together on failure (`gonio.bench.drivers` holds the drivers)."""

from __future__ import annotations

import time
from typing import Callable, Mapping

from gonio.bench.drivers import Goniometer, LedSource, PowerMeter, SimCamera, ZaberChain
from gonio.core.errors import GonioError

__all__ = ["Bench"]


def _open_camera(camera, timeout: float):
    if isinstance(camera, str):
        return SimCamera(camera, timeout=timeout)
    if not hasattr(camera, "expose"):
        raise GonioError(f"camera {camera!r} is neither a URL nor a camera object; give a camera URL")
    return camera


class Bench:
    """The instrument's drivers, opened together (closed together on failure).

    Parameters
    ----------
    settings : dict
    zaber_url, meter_url : str
        Serial URLs of the Zaber chain and of the power meter.
    camera : str or camera object
        A camera URL (`SimCamera`) or an object with ``expose(seconds, path)``.
    sleep : callable
        Called with seconds to wait (settling, polling); ``time.sleep`` on hardware; a
        simulated clock's ``advance`` in tests.
    alerts : bool
        Wait for the stages' moves by their alerts (`Goniometer`'s ``alerts``), polling only
        where a device rejects them.
    """

    def __init__(self, settings: Mapping, zaber_url: str, meter_url: str, camera, *,
                 sleep: Callable[[float], None] = time.sleep, poll_interval_s: float = 0.05,
                 timeout: float = 1.0, baudrate: int = 115200, on_warning=None, alerts: bool = True):
        self.settings = settings
        self._sleep = sleep
        self.checkpoint: Callable[[], None] = lambda: None    # a run's safe point: may raise StopNow
        self.chain = self.meter = self.camera = None
        try:
            self.chain = ZaberChain(zaber_url, baudrate, timeout, on_warning=on_warning)
            self.gonio = Goniometer(self.chain, settings, poll_interval_s=poll_interval_s, sleep=self.sleep,
                                    alerts=alerts)
            self.led = LedSource(self.chain, int(settings.get("lamp", {}).get("device", 2)))
            self.meter = PowerMeter(meter_url, baudrate, timeout)
            self.camera = _open_camera(camera, 30.0)
        except BaseException:
            self.close()
            raise

    def sleep(self, seconds: float) -> None:
        """Wait (a stage poll, a settle, a pause): a safe point to stop at."""
        self.checkpoint()
        self._sleep(seconds)
        self.checkpoint()

    def close(self) -> None:
        for dev in (self.camera, self.meter, self.chain):
            if dev is not None:
                try:
                    dev.close()
                except Exception:
                    pass
