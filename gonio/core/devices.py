"""The rig's ports, declared once: what each carries, its protocol and how a user names it.

A port is one connection of the instrument: the Zaber chain (stages and LED source), the SCPI
power meter and the camera. The bench opens one driver per port (`gonio.bench.drivers.rig`),
the simulator serves one device per port (`gonio.sim.instrument`), the fault schedule, the
session record and the CLI name ports by these names. A new device (a monochromator) is one
more entry here plus its driver and its simulated twin.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["PortSpec", "PORTS", "PORT_NAMES", "port_spec"]


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
    """

    name: str
    carries: str
    protocol: str
    option: str


#: Every port of the rig, in the order the bench opens them (and closes them in reverse).
PORTS: tuple[PortSpec, ...] = (
    PortSpec("zaber", "the Zaber chain of the four rotary stages and the LED source", "Zaber ASCII", "--port"),
    PortSpec("meter", "the SCPI power meter that monitors the source", "SCPI-1999 over serial", "--meter-port"),
    PortSpec("camera", "the RAW camera", "gonio camera text protocol", "--camera"),
)

PORT_NAMES: tuple[str, ...] = tuple(p.name for p in PORTS)


def port_spec(name: str) -> PortSpec:
    """The declared port ``name``; ValueError naming the known ports otherwise."""
    for p in PORTS:
        if p.name == name:
            return p
    raise ValueError(f"unknown port {str(name)[:40]!r}; the rig's ports are {', '.join(PORT_NAMES)}")
