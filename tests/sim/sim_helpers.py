"""Helpers shared by the tests of gonio.sim."""

DIFFUSE = {"mitsuba": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.5, 0.2]}}}


def exchange(port, pairs, end=b"\r\n"):
    """Send each command; assert the exact bytes that come back (all of them)."""
    for cmd, expected in pairs:
        port.write(cmd + end)
        got = port.read(port.in_waiting)
        assert got == expected, (cmd, got, expected)


def open_zaber(srv):
    """zaber-motion's Connection to a served instrument's Zaber chain, its devices detected
    without the device database."""
    from zaber_motion.ascii import Connection

    c = Connection.open_serial_port(srv.devices["zaber"])
    c.detect_devices(identify_devices=False)
    return c
