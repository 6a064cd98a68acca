"""The rig's ports, declared once: what each carries, its protocol and how a user names it.

A port is one connection of the instrument: the Zaber chain (stages and LED source), the SCPI
power meter and the camera. The bench opens one driver per port (`gonio.bench.drivers.rig`),
the simulator serves one device per port (`gonio.sim.instrument`), the fault schedule, the
session record and the CLI name ports by these names. A new device is one more entry here
plus its driver and its simulated twin. An ``optional`` port (the monochromator) is opened,
identified and recorded only where it is given a URL (the simulator serves it where the
settings hold its ``table``); a capture without it is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["PortSpec", "PORTS", "PORT_NAMES", "REQUIRED_PORTS", "OPTIONAL_PORTS", "port_spec"]


@dataclass(frozen=True)
class PortSpec:
    """One port of the rig.

    Attributes
    ----------
    name : str
        The port's name in ``sim://NAME/PORT`` URLs, session.toml's ``[ports]``, fault
        schedules and ``--port NAME=URL``.
    carries : str
        What is on it, for messages.
    protocol : str
        Its wire protocol (docs/interfaces.md; ../notes/protocols.md).
    option : str
        The CLI option that gives its URL.
    optional : bool
        Whether a capture may go without it (the bench opens it only when given a URL).
    table : str
        The settings table that declares the device on the rig ("" for the required ports).
    """

    name: str
    carries: str
    protocol: str
    option: str
    optional: bool = False
    table: str = ""


#: Every port of the rig, in the order the bench opens them (and closes them in reverse).
PORTS: tuple[PortSpec, ...] = (
    PortSpec("zaber", "the Zaber chain of the four rotary stages and the LED source", "Zaber ASCII", "--port"),
    PortSpec("meter", "the SCPI power meter that monitors the source", "SCPI-1999 over serial", "--meter-port"),
    PortSpec("camera", "the RAW camera", "gonio camera text protocol", "--camera"),
    PortSpec("monochromator", "the Cornerstone monochromator that sets the wavelength of a spectral capture",
             "Cornerstone RS-232 text (9600 8N1)", "--monochromator-port", optional=True, table="monochromator"),
)

PORT_NAMES: tuple[str, ...] = tuple(p.name for p in PORTS)
#: the ports every capture opens, in order (the Bench's positional URLs)
REQUIRED_PORTS: tuple[str, ...] = tuple(p.name for p in PORTS if not p.optional)
#: the ports a capture opens only when given a URL
OPTIONAL_PORTS: tuple[str, ...] = tuple(p.name for p in PORTS if p.optional)


def port_spec(name: str) -> PortSpec:
    """The declared port ``name``; ValueError naming the known ports otherwise."""
    for p in PORTS:
        if p.name == name:
            return p
    raise ValueError(f"unknown port {str(name)[:40]!r}; the rig's ports are {', '.join(PORT_NAMES)}")
