"""``gonio devices``: what answers on each declared port (`gonio.core.devices`), in words.

One probe per port (:data:`PROBES`): the Zaber chain is discovered and each device identified
against the roles the settings give it, the meter answers ``*IDN?``, the camera says what it
is. Nothing moves and nothing is written.
"""

from __future__ import annotations

from typing import Callable, Mapping

from gonio.bench.drivers import identify as _identify
from gonio.bench.drivers.camera import open_camera
from gonio.bench.drivers.meter import PowerMeter
from gonio.bench.drivers.zaber import ZaberChain
from gonio.core.devices import PORTS
from gonio.core.errors import GonioError

__all__ = ["PROBES", "probe_ports"]


def _zaber(url: str, settings: Mapping, baud: int) -> list[str]:
    with ZaberChain(url, baud, 0.5, retries=1) as chain:
        found = _identify.discover(chain)
        if not found:
            raise GonioError(f"no Zaber device answered on {url}; check power, cable and --baud")
        roles = _identify.roles(settings)
        lines = [f"zaber {url}: {len(found)} device{'s' if len(found) != 1 else ''}"]
        lines += ["  " + _identify.describe_device(chain.identify(dev), roles.get(dev, "")) for dev in found]
        lines += [f"  device {dev}: did not answer, but the settings put the {roles[dev]} there"
                  for dev in sorted(set(roles) - set(found))]
    return lines


def _meter(url: str, settings: Mapping, baud: int) -> list[str]:
    with PowerMeter.from_settings(url, settings, baud, 1.0) as meter:
        return [f"meter {url}: {_identify.clean(meter.identify())}"]


def _camera(spec: str, settings: Mapping, baud: int) -> list[str]:
    cam = open_camera(spec, timeout=30.0)
    try:
        s = getattr(cam, "sensor", None)
        idn = _identify.camera_text(cam)
        return [f"camera {spec}: {idn}" + (f" ({s.width} x {s.height} pixels, {s.bits} bits, {s.cfa})"
                                           if s is not None else "")]
    finally:
        cam.close()


def _monochromator(url: str, settings: Mapping, baud: int) -> list[str]:
    from gonio.bench.drivers.monochromator import Monochromator

    mono = Monochromator(url, settings)
    try:
        return [f"monochromator {url}: {_identify.clean(mono.info)}, grating {mono.grating()}, "
                f"{mono.wavelength():g} nm"]
    finally:
        mono.close()


#: The probe of each declared port: ``probe(url, settings, baud) -> lines``.
PROBES: dict[str, Callable[[str, Mapping, int], list[str]]] = {"zaber": _zaber, "meter": _meter, "camera": _camera,
                                                               "monochromator": _monochromator}


def probe_ports(urls: Mapping[str, str | None], settings: Mapping, baud: int) -> list[str]:
    """The lines of every port given a URL in ``urls`` (port name -> URL or None), in the
    declared order; GonioError naming the options when none is given."""
    if not any(urls.get(p.name) for p in PORTS):
        raise GonioError("devices needs " + ", ".join(f"{p.option} for {p.carries}" for p in PORTS[:-1])
                         + f" or {PORTS[-1].option} for {PORTS[-1].carries}")
    lines: list[str] = []
    for p in PORTS:
        if urls.get(p.name):
            lines += PROBES[p.name](urls[p.name], settings, baud)
    return lines
