"""zaber-motion 10.3 and zaber.serial 0.9 against `gonio sim serve`'s pseudo-terminals.

The clients are Zaber's own; the bytes they send are theirs (message ids and ``:CC``
checksums from zaber-motion, bare commands from zaber.serial). Reference behaviour: Zaber's
ASCII protocol manual (replies, alerts ``!DD A STATUS WARN``, continuation ``\\`` + ``cont``);
values are the simulator's (gonio/sim/devices/zaber_stage.py, gonio/sim/devices/zaber_led.py).
"""

import http.server
import threading
import time

import pytest


zm = pytest.importorskip("zaber_motion", reason="zaber-motion is not installed")
from zaber_motion import DeviceDbSourceType, Library, LogOutputMode  # noqa: E402
from zaber_motion.ascii import Connection  # noqa: E402
from zaber_motion.exceptions import DeviceDbFailedException  # noqa: E402
from zaber_motion.microscopy import Illuminator  # noqa: E402
from sim_helpers import open_zaber  # noqa: E402

pytestmark = pytest.mark.timeout(60)
Library.set_log_output(LogOutputMode.OFF)


def test_detect_and_identification_settings(served):
    srv = served()
    with Connection.open_serial_port(srv.devices["zaber"]) as c:
        devs = c.detect_devices(identify_devices=False)
        assert [d.device_address for d in devs] == [1, 2]
        d1, d2 = devs
        ask = lambda d, text, axis=0: d.generic_command(text, axis=axis).data   # noqa: E731
        assert (ask(d1, "get deviceid"), ask(d1, "get system.serial"), ask(d1, "get version"),
                ask(d1, "get version.build")) == ("30342", "91001", "7.38", "15708")
        assert ask(d1, "get system.axiscount") == "4" and ask(d1, "get comm.packet.size.max") == "80"
        assert ask(d1, "get resolution", 2) == "64" and ask(d1, "get peripheralid", 3) == "0"
        assert ask(d1, "get peripheral.id", 1) == "0"
        assert ask(d2, "get deviceid") == "30311" and ask(d2, "get peripheralid", 1) == "58001"


class _DbSpy(http.server.BaseHTTPRequestHandler):
    paths: list = []

    def do_GET(self):                    # noqa: N802 - http.server's name
        _DbSpy.paths.append(self.path)
        self.send_response(404)
        self.end_headers()

    def log_message(self, *args):
        pass


def _db_lookups(srv, device=1):
    """The device-database lookups zaber-motion makes to identify ``device`` (a local spy
    stands in for Zaber's web service, which answers nothing: identify() then fails)."""
    httpd = http.server.HTTPServer(("127.0.0.1", 0), _DbSpy)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    _DbSpy.paths = []
    Library.set_device_db_source(DeviceDbSourceType.WEB_SERVICE, f"http://127.0.0.1:{httpd.server_port}/db")
    try:
        with open_zaber(srv) as c:
            with pytest.raises(DeviceDbFailedException):
                c.get_device(device).identify()
    finally:
        Library.set_device_db_source(DeviceDbSourceType.WEB_SERVICE)
        httpd.shutdown()
    assert _DbSpy.paths, "zaber-motion never reached the device database"
    return _DbSpy.paths


def test_identify_asks_the_device_database_with_the_sims_ids(served):
    """identify() reads every identification setting, then looks the product up in Zaber's
    device database with the device id, firmware and each axis's peripheral id. The controller
    is an X-MCC4 (30342, firmware 7.38 build 15708: Zaber's own test data); an axis reports the
    rotary peripheral whose microstep grid its ``limit.cycle.dist`` is (46657: 2 304 000 per
    turn), else 0, no peripheral: zaber-motion then converts nothing rather than convert the
    wrong product's units (issue 40: the simulator reported 43211, Zaber's X-LHM linear stage).

    identify() cannot pass offline without Zaber's own data: the web service is
    ``GET https://api.zaber.io/device-db/v2/public/device/30342?fw=7.38.15708&peripheral-id=...``
    (the peripheral id once per axis); the offline source (``DeviceDbSourceType.FILE``) is
    Zaber's published SQLite file ``devices-public.sqlite`` (zaber-motion first reads its table
    ``SwWeb_SchemaVersion``), not on this machine nor in any package; the store
    (``enable_device_db_store``) only keeps answers fetched online before."""
    assert _db_lookups(served())[0] == "/db/device/30342?fw=7.38.15708" + "&peripheral-id=0" * 4
    rsw = served(settings={"axes": {"cycle_dist": 2_304_000}})
    assert _db_lookups(rsw)[0] == "/db/device/30342?fw=7.38.15708" + "&peripheral-id=46657" * 4


def test_identify_offline_sources_need_zabers_database(served, tmp_path):
    """The offline routes zaber-motion offers fail without Zaber's database file: a missing
    file, an empty one (no schema), and the store with the web service unreachable."""
    srv = served()
    empty = tmp_path / "empty.sqlite"
    empty.write_bytes(b"")
    attempts = [(lambda: Library.set_device_db_source(DeviceDbSourceType.FILE, str(tmp_path / "none.sqlite")),
                 "no such file"),
                (lambda: Library.set_device_db_source(DeviceDbSourceType.FILE, str(empty)), "SwWeb_SchemaVersion"),
                (lambda: (Library.set_device_db_source(DeviceDbSourceType.WEB_SERVICE, "http://127.0.0.1:9/db"),
                          Library.enable_device_db_store(str(tmp_path / "store"))), "online source")]
    try:
        with open_zaber(srv) as c:
            for setup, why in attempts:
                setup()
                with pytest.raises(DeviceDbFailedException, match=why):
                    c.get_device(1).identify()
    finally:
        Library.disable_device_db_store()
        Library.set_device_db_source(DeviceDbSourceType.WEB_SERVICE)


def test_axis_moves_settings_park_and_driver(served):
    srv = served()
    with open_zaber(srv) as c:
        d = c.get_device(1)
        ax = d.get_axis(2)
        d.all_axes.home()
        ax.move_absolute(36000)
        assert ax.get_position() == 36000
        assert ax.settings.get("maxspeed") == 65536         # native: 40000 microsteps/s * 1.6384
        ax.settings.set("maxspeed", 32768)
        assert ax.settings.get("maxspeed") == 32768
        ax.move_velocity(16384)
        assert ax.is_busy()
        ax.stop()
        assert not ax.is_busy() and ax.get_position() > 36000
        ax.park()
        assert ax.is_parked()
        ax.unpark()
        assert not ax.is_parked()
        ax.driver_disable()
        assert "FD" in ax.warnings.get_flags()
        ax.driver_enable()
        assert "FD" not in ax.warnings.get_flags()
        ax.move_relative(-1000)
        assert ax.get_position() == pytest.approx(srv.instrument.axes[1].position(srv.instrument.clock.now()))


def _timed_move(srv, ax, microsteps):
    clock = srv.instrument.clock
    t0 = clock.now()
    ax.move_relative(microsteps)                 # waits until idle (polls)
    return clock.now() - t0


def test_native_speed_unit_sets_the_motion_time(served):
    """maxspeed, accel and move vel read and written through zaber-motion in Zaber's native
    units (ASCII protocol manual: speed = data / 1.6384 microsteps/s, acceleration = data * 10 /
    1.6384 microsteps/s^2); the simulated stage then takes the trapezoid's time for a move,
    d / v + v / a (d >= v^2 / a). Tolerance 20 ms: the instant clock charges 1 ms per command
    line and zaber-motion sends a few per move (the move, its polls); a unit error of 1.6384 or
    10 would change the 72-degree move's 4.1 s by more than a second."""
    from zaber_motion import Units
    from zaber_motion.exceptions import DeviceNotIdentifiedException

    srv = served()
    with open_zaber(srv) as c:
        d = c.get_device(1)
        ax = d.get_axis(1)
        d.all_axes.home()
        cycle = ax.settings.get("limit.cycle.dist")
        v_native, a_native = ax.settings.get("maxspeed"), ax.settings.get("accel")
        v, a = v_native / 1.6384, a_native * 10 / 1.6384            # microsteps/s, microsteps/s^2
        assert v * 360 / cycle == pytest.approx(20.0) and a * 360 / cycle == pytest.approx(40.0, rel=1e-4)
        dist = round(72 * cycle / 360)
        assert _timed_move(srv, ax, dist) == pytest.approx(dist / v + v / a, abs=0.02)
        ax.settings.set("maxspeed", 32768)                          # 20000 microsteps/s = 10 deg/s
        ax.settings.set("accel", 8192)                              # 50000 microsteps/s^2
        assert _timed_move(srv, ax, -dist) == pytest.approx(dist / 20000 + 20000 / 50000, abs=0.02)
        ax.move_velocity(-8192)                                     # 5000 microsteps/s toward limit.min
        axis = srv.instrument.axes[0]
        t = srv.instrument.clock.now() + 0.5                        # past the 0.1 s ramp
        assert axis.velocity(t) == pytest.approx(-5000.0)
        ax.stop()
        # zaber-motion's own conversion needs the product's conversion table from Zaber's
        # device database (identify()), which is not reachable offline
        with pytest.raises(DeviceNotIdentifiedException):
            ax.settings.get("maxspeed", Units.ANGULAR_VELOCITY_DEGREES_PER_SECOND)


def test_continued_reply(served):
    srv = served()
    srv.instrument.zaber.packet_size_max = 40       # '@01 0 07 OK IDLE -- 190000 176000\' fits
    with open_zaber(srv) as c:
        assert c.get_device(1).generic_command("get limit.max").data == "190000 176000 360000 350000"


def test_illuminator_channel_api(served):
    srv = served(lamp={"flux_max": 2.5})
    lamp = srv.instrument.lamp
    with open_zaber(srv) as c:
        il = Illuminator(c.get_device(2))
        ch = il.get_channel(1)
        assert not ch.is_on()
        ch.on()
        assert ch.is_on() and lamp.on
        ch.set_intensity(0.4)                        # sends set lamp.flux 1 (0.4 * 2.5)
        assert lamp.flux == pytest.approx(0.4)
        assert ch.get_intensity() == pytest.approx(0.4)
        il.turn_off()                                # /2 0 lamp off
        assert not ch.is_on() and not lamp.on


def test_alerts(served):
    srv = served()
    with open_zaber(srv) as c:
        alerts = []
        c.alert.subscribe(alerts.append)
        ax = c.get_device(1).get_axis(2)
        c.get_device(1).all_axes.home()
        c.enable_alerts()
        ax.move_absolute(72000, wait_until_idle=False)
        ax.wait_until_idle()
        deadline = time.monotonic() + 5
        while not alerts and time.monotonic() < deadline:
            time.sleep(0.01)
        assert [(a.device_address, a.axis_number, a.status) for a in alerts] == [(1, 2, "IDLE")]
        c.disable_alerts()


zs = pytest.importorskip("zaber.serial", reason="zaber.serial is not installed")


def test_zaber_serial(served):
    srv = served()
    port = zs.AsciiSerial(srv.devices["zaber"], timeout=2)
    try:
        dev = zs.AsciiDevice(port, 1)
        assert dev.send("get deviceid").data == "30342"
        assert dev.home().reply_flag == "OK"
        dev.poll_until_idle()
        ax = dev.axis(3)
        ax.move_abs(-36000)
        assert ax.get_position() == -36000
        led = zs.AsciiDevice(port, 2).axis(1)
        assert led.send("lamp on").reply_flag == "OK"
        assert led.send("get lamp.status").data == "2"
        assert zs.AsciiDevice(port, 2).send("lamp off").reply_flag == "OK"
        assert led.send("get lamp.status").data == "1"
    finally:
        port.close()
