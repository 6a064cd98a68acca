"""What is on each port, identified: Zaber devices (device id, serial, firmware, axes and their
peripheral ids), the power meter's ``*IDN?`` and the camera's.

A Zaber controller answers ``get deviceid``, ``get system.serial``, ``get version``,
``get version.build`` and ``get system.axiscount`` on axis 0 and ``get peripheralid`` per
axis (the settings zaber-motion's ``identify()`` reads); older firmware may reject one of
them (``RJ BADCOMMAND``), which is recorded as missing rather than failing. Whatever a device
sends is treated as hostile text: only printable ASCII is kept, at most 64 characters.

`record` puts the identification of a bench's devices in the session's journal (an
``identification`` event, JSON) once per run. A capture identifies the devices as soon as the
ports are open, before ``session.toml`` is written, and `session_devices` makes that its
``[devices]`` table (docs/interfaces.md section 5); every resume identifies them again, journals
what it ran on, and `differences` says what differs from the table (`hardware_note`).
"""

from __future__ import annotations

import json

from typing import Mapping

from gonio.core.errors import CommunicationError, GonioError

__all__ = ["camera_text", "clean", "describe_device", "differences", "discover", "hardware_note", "identify_bench",
           "record", "roles", "session_devices", "zaber_device"]

_MAX_TEXT = 64
_DEVICE_SETTINGS = (("deviceid", "device_id"), ("system.serial", "serial"), ("version", "firmware"),
                    ("version.build", "build"), ("system.axiscount", "axes"))
MAX_AXES = 16          # peripheral ids read per device at most (a hostile axis count cannot loop us)


def clean(text) -> str:
    """Printable ASCII of a device's answer, at most 64 characters."""
    s = "".join(ch for ch in str(text) if 32 <= ord(ch) < 127).strip()
    return s[:_MAX_TEXT] + ("..." if len(s) > _MAX_TEXT else "")


def discover(chain, max_devices: int = 99) -> list[int]:
    """Addresses of the devices that answer a broadcast ``get deviceid``, ascending."""
    replies = chain.broadcast("get deviceid", max_devices)
    return sorted({r.device for r in replies if 1 <= r.device <= 99})


def _ask(chain, device: int, axis: int, setting: str):
    """One identification setting as text; None where the device rejects it or sends nothing usable."""
    try:
        reply = chain.request(device, axis, f"get {setting}", check=False)
    except CommunicationError:
        return None
    if not reply.ok or not reply.data or reply.data.split()[0] == "NA":
        return None
    return clean(reply.data)


def zaber_device(chain, device: int) -> dict:
    """Identification of one Zaber device: device id, serial, firmware, build, axes, peripheral ids."""
    out = {"address": int(device)}
    for setting, key in _DEVICE_SETTINGS:
        out[key] = _ask(chain, device, 0, setting)
    try:
        n = int(out["axes"]) if out["axes"] is not None else 0
    except ValueError:
        n = 0
    out["axes"] = n
    out["peripheral_ids"] = [_ask(chain, device, a, "peripheralid") for a in range(1, min(n, MAX_AXES) + 1)]
    return out


def camera_text(camera) -> str:
    """A camera's ``identify()`` as clean text; its class name for a camera object without one."""
    ident = getattr(camera, "identify", None)
    return clean(ident()) if callable(ident) else type(camera).__name__


def describe_device(d: dict, role: str = "") -> str:
    """One line for ``gonio devices``."""
    def v(key):
        return d.get(key) if d.get(key) is not None else "?"
    fw = v("firmware") + (f" build {d['build']}" if d.get("build") else "")
    ids = " ".join(p if p is not None else "-" for p in d.get("peripheral_ids", []))
    axes = f"{d['axes']} " + ("axis" if d["axes"] == 1 else "axes")
    text = (f"device {d['address']}: device id {v('device_id')}, serial {v('serial')}, firmware {fw}, {axes}"
            + (f" (peripheral ids {ids})" if ids else ""))
    return text + (f"; {role}" if role else "")


def roles(settings) -> dict[int, str]:
    """What the settings put on each Zaber address: the stage axes and the LED source."""
    out: dict[int, list[str]] = {}
    for name in ("yaw", "tilt", "azimuth", "lamp"):
        dev, ax = settings["axes"][name][:2]
        out.setdefault(int(dev), []).append(f"{name} on axis {int(ax)}")
    led = int(settings.get("lamp", {}).get("device", 2))
    text = {d: "stages: " + ", ".join(v) for d, v in out.items()}
    text[led] = (text[led] + "; " if led in text else "") + "LED source"
    return text


def identify_bench(bench) -> dict:
    """The identification of a `capture.Bench`'s devices (the Zaber addresses its settings name)."""
    addresses = sorted({int(v[0]) for k, v in bench.settings["axes"].items() if isinstance(v, list)}
                       | {int(bench.led.device)})
    out = {"zaber_port": clean(bench.chain.port_url), "zaber": [bench.chain.identify(d) for d in addresses]}
    try:
        out["meter"] = clean(bench.meter.identify())
    except GonioError:
        out["meter"] = None
    out["meter_port"] = clean(bench.meter.port_url)
    out["camera"] = camera_text(bench.camera)
    mono = getattr(bench, "monochromator", None)
    if mono is not None:                          # an optional port: only where the bench opened it
        out["monochromator"] = clean(mono.info or mono.identify())
        out["monochromator_port"] = clean(mono.port_url)
    return out


def record(bench, journal, ident: Mapping | None = None) -> dict:
    """Journal the identification of every device of ``bench`` (an ``identification`` event):
    ``ident`` where the caller already took it (`identify_bench`), else asked now."""
    ident = identify_bench(bench) if ident is None else ident
    journal.event("identification", json.dumps(ident, sort_keys=True, allow_nan=False))
    return ident


_ZABER_FIELDS = (("device_id", "device id"), ("serial", "serial"), ("firmware", "firmware"), ("build", "build"),
                 ("axes", "axes"), ("peripheral_ids", "peripheral ids"))


def session_devices(ident: Mapping) -> dict:
    """The ``[devices]`` table of ``session.toml`` for an `identify_bench` result.

    ``zaber_port``, ``meter_port``, ``meter`` (``*IDN?``), ``camera``, ``monochromator_port`` and
    ``monochromator`` (``INFO?``, where the bench has one), and per Zaber address A a
    table ``[devices.zaber.A]``: ``address``, ``device_id``, ``serial``, ``firmware``, ``build``,
    ``axes``, ``peripheral_ids``. Every text is `clean`'d again (printable ASCII, at most 64
    characters: no newline or control character reaches the file, and the TOML writer escapes
    quotes and backslashes); what a device did not answer is left out (TOML has no null), a
    peripheral id it did not answer is ``""``.
    """
    out: dict = {}
    for key in ("zaber_port", "meter_port", "meter", "camera", "monochromator_port", "monochromator"):
        if ident.get(key) is not None:
            out[key] = clean(ident[key])
    zaber: dict = {}
    for d in ident.get("zaber") or []:
        address = int(d["address"])
        row: dict = {"address": address}
        for key in ("device_id", "serial", "firmware", "build"):
            if d.get(key) is not None:
                row[key] = clean(d[key])
        row["axes"] = int(d.get("axes") or 0)
        row["peripheral_ids"] = ["" if p is None else clean(p) for p in (d.get("peripheral_ids") or [])[:MAX_AXES]]
        zaber[str(address)] = row
    out["zaber"] = zaber
    return out


def _shown(v) -> str:
    if v is None:
        return "(none)"
    if isinstance(v, list):
        return "[" + " ".join(clean(x) or "-" for x in v[:MAX_AXES]) + "]"
    return clean(v) or '""'


def differences(recorded: Mapping, now: Mapping) -> list[str]:
    """What differs between ``session.toml``'s ``[devices]`` (``recorded``) and the devices
    identified now (a `session_devices` table): one clean phrase per difference, e.g.
    ``"Zaber device 1 serial 91001 -> 91099"``; [] on the same hardware. The ports are not
    compared (a device may come back on another port); ``recorded`` is read defensively (a
    field of the wrong type differs)."""
    out = []
    rz = recorded.get("zaber") if isinstance(recorded.get("zaber"), Mapping) else {}
    nz = now.get("zaber") if isinstance(now.get("zaber"), Mapping) else {}
    for a in sorted(set(rz) | set(nz), key=lambda k: (len(str(k)), str(k)))[:99]:
        r, n = rz.get(a), nz.get(a)
        if not isinstance(r, Mapping):
            out.append(f"Zaber device {clean(a)} is not in session.toml")
            continue
        if not isinstance(n, Mapping):
            out.append(f"Zaber device {clean(a)} (serial {_shown(r.get('serial'))}) did not answer")
            continue
        for key, label in _ZABER_FIELDS:
            if r.get(key) != n.get(key):
                out.append(f"Zaber device {clean(a)} {label} {_shown(r.get(key))} -> {_shown(n.get(key))}")
    for key, label in (("meter", "power meter *IDN?"), ("camera", "camera"), ("monochromator", "monochromator INFO?")):
        if recorded.get(key) != now.get(key):
            out.append(f"{label} {_shown(recorded.get(key))} -> {_shown(now.get(key))}")
    return out


def hardware_note(diffs: list[str]) -> str:
    """The one line a resume on other hardware says (console and journal)."""
    return ("this resume runs on other hardware than session.toml records: " + "; ".join(diffs[:12])
            + ("; ..." if len(diffs) > 12 else "")
            + " (session.toml keeps the original; this run's identification is journalled)")
