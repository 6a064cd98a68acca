"""The bench's devices opened together, one driver per declared port (`gonio.core.devices`):
the Zaber chain (stages and LED), the power meter and the camera of one capture, and the
monochromator where one is given (an optional port), closed together on failure
(`gonio.bench.drivers` holds the drivers; :data:`DRIVERS` maps a port to the function that
opens its driver)."""

from __future__ import annotations

import time
from typing import Callable, Mapping

from gonio.bench.drivers import Goniometer, LedSource, PowerMeter, SimCamera, ZaberChain
from gonio.core.devices import OPTIONAL_PORTS, PORT_NAMES, REQUIRED_PORTS
from gonio.core.errors import GonioError

__all__ = ["Bench", "DRIVERS", "clock_of"]


def clock_of(sleep: Callable[[float], None]) -> Callable[[], float]:
    """The clock a bench's waits run on: the ``now`` of the object whose method ``sleep`` is
    (a simulated clock's ``advance``), else ``time.monotonic`` (the rig's own time)."""
    now = getattr(getattr(sleep, "__self__", None), "now", None)
    return now if callable(now) and getattr(sleep, "__name__", "") == "advance" else time.monotonic


def _open_camera(camera, timeout: float):
    if isinstance(camera, str):
        return SimCamera(camera, timeout=timeout)
    if not hasattr(camera, "expose"):
        raise GonioError(f"camera {camera!r} is neither a URL nor a camera object; give a camera URL")
    return camera


def _open_zaber(bench: "Bench", url, kw: Mapping):
    bench.chain = bench.opened(ZaberChain(url, kw["baudrate"], kw["timeout"], on_warning=kw["on_warning"]))
    bench.gonio = Goniometer(bench.chain, bench.settings, poll_interval_s=kw["poll_interval_s"], sleep=bench.sleep,
                             alerts=kw["alerts"])
    bench.led = LedSource(bench.chain, int(bench.settings.get("lamp", {}).get("device", 2)))


def _open_meter(bench: "Bench", url, kw: Mapping):
    bench.meter = bench.opened(PowerMeter.from_settings(url, bench.settings, kw["baudrate"], kw["timeout"]))


def _open_camera_port(bench: "Bench", camera, kw: Mapping):
    bench.camera = bench.opened(_open_camera(camera, 30.0))


def _open_monochromator(bench: "Bench", url, kw: Mapping):
    from gonio.bench.drivers.monochromator import Monochromator

    if not isinstance(url, str):
        raise GonioError(f"monochromator {url!r:.40} is not a URL; give its serial port")
    bench.monochromator = bench.opened(Monochromator(url, bench.settings, timeout=kw["timeout"]))


#: How the bench opens the driver of each declared port: ``open(bench, url, options)`` sets the
#: bench's attributes for it and hands each connection it opens to ``bench.opened`` (closed by
#: ``close``, in reverse order, even when a later step fails).
DRIVERS: dict[str, Callable] = {"zaber": _open_zaber, "meter": _open_meter, "camera": _open_camera_port,
                                "monochromator": _open_monochromator}


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
    clock : callable, optional
        The instrument's clock, seconds (`clock_of`: ``time.monotonic`` on hardware, the
        simulated clock's ``now`` where ``sleep`` is its ``advance``); what a session's
        instrument time is read from.
    alerts : bool
        Wait for the stages' moves by their alerts (`Goniometer`'s ``alerts``), polling only
        where a device rejects them.
    monochromator : str, optional
        The monochromator's serial URL (an optional port): opened as ``bench.monochromator``
        (`gonio.bench.drivers.monochromator.Monochromator`); None without one.
    """

    def __init__(self, settings: Mapping, zaber_url: str, meter_url: str, camera, *,
                 sleep: Callable[[float], None] = time.sleep, poll_interval_s: float = 0.05,
                 timeout: float = 1.0, baudrate: int = 115200, on_warning=None, alerts: bool = True,
                 clock: Callable[[], float] | None = None, monochromator: str | None = None):
        self.settings = settings
        self._sleep = sleep
        self.clock: Callable[[], float] = clock if clock is not None else clock_of(sleep)
        self.checkpoint: Callable[[], None] = lambda: None    # a run's safe point: may raise StopNow
        self.chain = self.meter = self.camera = self.monochromator = None
        self._opened: list = []
        urls = dict(zip(REQUIRED_PORTS, (zaber_url, meter_url, camera)), monochromator=monochromator)
        kw = {"baudrate": baudrate, "timeout": timeout, "on_warning": on_warning, "poll_interval_s": poll_interval_s,
              "alerts": alerts}
        try:
            for name in PORT_NAMES:
                if urls.get(name) is not None or name not in OPTIONAL_PORTS:
                    DRIVERS[name](self, urls[name], kw)
        except BaseException:
            self.close()
            raise

    @classmethod
    def from_ports(cls, settings: Mapping, ports: Mapping[str, object], **kw) -> "Bench":
        """The bench of ``ports``, a mapping of every declared port's name to its URL (the camera
        may be a camera object; an optional port may be left out); ValueError naming what is
        missing or unknown."""
        missing = [p for p in REQUIRED_PORTS if p not in ports]
        unknown = sorted(set(ports) - set(PORT_NAMES))
        if missing or unknown:
            raise ValueError(f"the bench needs a URL for each of {', '.join(REQUIRED_PORTS)}"
                             + (f"; missing {', '.join(missing)}" if missing else "")
                             + (f"; unknown {', '.join(map(str, unknown))}" if unknown else ""))
        return cls(settings, *(ports[p] for p in REQUIRED_PORTS), **kw,
                   **{p: ports[p] for p in OPTIONAL_PORTS if ports.get(p) is not None})

    def sleep(self, seconds: float) -> None:
        """Wait (a stage poll, a settle, a pause): a safe point to stop at."""
        self.checkpoint()
        self._sleep(seconds)
        self.checkpoint()

    def opened(self, connection):
        """Record ``connection`` for :meth:`close`; returns it."""
        self._opened.append(connection)
        return connection

    def close(self) -> None:
        for dev in reversed(self._opened):
            try:
                dev.close()
            except Exception:
                pass
