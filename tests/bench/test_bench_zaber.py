"""Zaber ASCII driver, byte for byte against expected exchanges (expect:// ports)."""

import pytest

from benchfakes import expect
from gonio.bench.settings import default_settings
from gonio.bench.drivers import (Goniometer, LedSource, ZaberChain, format_command, lrc, parse_reply,
                                 shortest_equivalent)
from gonio.core.errors import CommunicationError, FaultError, GonioError, RejectedError, UnreachableError


def cmd(device, axis, msgid, text=""):
    return format_command(device, axis, text, msgid, checksum=True)


def test_lrc_and_format():
    # LRC of "1 0 get pos": two's complement of the byte sum mod 256
    body = b"1 0 00 get pos"
    assert int(lrc(body), 16) == (-sum(body)) & 0xFF
    assert (sum(body) + int(lrc(body), 16)) % 256 == 0
    assert format_command(1, 2, "move abs 64000") == b"/1 2 move abs 64000\n"
    assert format_command(1, 0, "", 7) == b"/1 0 07\n"
    assert format_command(1, 0, "get pos", 3, checksum=True) == b"/1 0 03 get pos:" + lrc(b"1 0 03 get pos").encode() + b"\n"


def test_parse_reply_fields():
    r = parse_reply(b"@01 2 07 OK BUSY WR 12 34\r\n")
    assert (r.device, r.axis, r.msgid, r.flag, r.status, r.warning, r.data) == (1, 2, 7, "OK", "BUSY", "WR", "12 34")
    assert r.ok and r.busy and r.values == [12.0, 34.0]
    r = parse_reply("@02 0 RJ IDLE -- BADCOMMAND")
    assert r.msgid is None and r.flag == "RJ" and r.data == "BADCOMMAND"
    body = "01 0 05 OK IDLE -- 0"
    assert parse_reply(f"@{body}:{lrc(body.encode())}").msgid == 5
    with pytest.raises(ValueError):
        parse_reply(f"@{body}:00")                      # wrong checksum
    for bad in ("", "#01 0 info", "@01 0 XX IDLE -- 0", "@01 0 OK"):
        with pytest.raises(ValueError):
            parse_reply(bad)


def test_get_and_msgid_sequence():
    ex = expect("z1", [(cmd(1, 0, 0, "get pos"), "@01 0 00 OK IDLE -- 0 720 -1440 0\r\n"),
                       (cmd(1, 4, 1, "get maxspeed"), "#01 4 01 info line\r\n@01 4 01 OK IDLE -- 40000\r\n")])
    with ZaberChain("expect://z1") as z:
        assert z.get(1, 0, "pos") == [0.0, 720.0, -1440.0, 0.0]
        assert z.get(1, 4, "maxspeed") == [40000.0]
    assert ex.done()


def test_rejection_names_reason():
    expect("z2", [(cmd(1, 2, 0, "move abs 99999999"), "@01 2 00 RJ IDLE -- BADDATA\r\n")])
    z = ZaberChain("expect://z2")
    with pytest.raises(RejectedError) as e:
        z.request(1, 2, "move abs 99999999")
    assert e.value.reason == "BADDATA" and "out-of-range" in str(e.value) and "\n" not in str(e.value)


def test_fault_flag_raises_with_meaning():
    expect("z3", [(cmd(1, 0, 0), "@01 0 00 OK IDLE FS 0\r\n"),
                  (cmd(1, 0, 1, "warnings"), "@01 0 01 OK IDLE FS 02 FS WR\r\n")])
    z = ZaberChain("expect://z3")
    with pytest.raises(FaultError) as e:
        z.request(1, 0)
    assert e.value.flags == ("FS",) and "stalled and stopped" in str(e.value)


def test_warning_reported_once():
    seen = []
    expect("z4", [(cmd(1, 0, 0), "@01 0 00 OK IDLE WT 0\r\n"), (cmd(1, 0, 1), "@01 0 01 OK IDLE WT 0\r\n")])
    z = ZaberChain("expect://z4", on_warning=lambda d, f, m: seen.append((d, f, m)))
    z.request(1, 0)
    z.request(1, 0)
    assert seen == [(1, "WT", "controller hot")]


def test_busy_polling_until_idle_and_timeout():
    slept = []
    expect("z5", [(cmd(1, 0, 0), "@01 0 00 OK BUSY -- 0\r\n"), (cmd(1, 0, 1), "@01 0 01 OK BUSY -- 0\r\n"),
                  (cmd(1, 0, 2), "@01 0 02 OK IDLE -- 0\r\n")])
    z = ZaberChain("expect://z5")
    assert z.wait_idle(1, timeout_s=1.0, poll_interval_s=0.1, sleep=slept.append).status == "IDLE"
    assert slept == [0.1, 0.1]
    expect("z6", [(cmd(1, 0, k), f"@01 0 {k:02d} OK BUSY -- 0\r\n") for k in range(3)])
    with pytest.raises(CommunicationError, match="still moving"):
        ZaberChain("expect://z6").wait_idle(1, timeout_s=0.3, poll_interval_s=0.1, sleep=lambda s: None)


def test_retry_after_silence_garble_and_stale_reply():
    ex = expect("z7", [
        (cmd(1, 0, 0, "get pos"), None),                                   # lost
        (cmd(1, 0, 1, "get pos"), "@01 0 01 OK ID\x00E -- 5\r\n"),         # garbled
        (cmd(1, 0, 2, "get pos"), "@01 0 01 OK IDLE -- 4\r\n@01 0 02 OK IDLE -- 5\r\n"),  # late reply first
    ])
    z = ZaberChain("expect://z7", retries=2)
    assert z.get(1, 0, "pos") == [5.0]
    assert ex.done() and ex.opened == 1


def test_reconnect_then_give_up():
    ex = expect("z8", [(cmd(1, 0, k, "get pos"), None) for k in range(2)]
                + [(cmd(1, 0, 2, "get pos"), "@01 0 02 OK IDLE -- 7\r\n")])
    z = ZaberChain("expect://z8", retries=1)
    assert z.get(1, 0, "pos") == [7.0]
    assert ex.opened == 2 and ex.closed == 1 and z.reconnects == 1
    expect("z9", [(cmd(1, 0, k, "get pos"), None) for k in range(4)])
    with pytest.raises(CommunicationError) as e:
        ZaberChain("expect://z9", retries=1).get(1, 0, "pos")
    assert "reconnect" in str(e.value) and "\n" not in str(e.value)


def test_dead_port_is_one_line():
    with pytest.raises(CommunicationError) as e:
        ZaberChain("/dev/does-not-exist-gonio")
    assert "--port" in str(e.value) and "\n" not in str(e.value)


def test_shortest_equivalent():
    assert shortest_equivalent(170.0, -170.0, -180, 180) == 170.0      # cannot cross the limit
    assert shortest_equivalent(-170.0, 170.0, -360, 360) == 190.0      # full turn of travel: go the short way
    assert shortest_equivalent(10.0, 0.0, -95, 95) == 10.0


def _connect_script(flags="--"):
    cyc = "720000 720000 720000 720000"
    w = "00" if flags == "--" else f"01 {flags}"
    return [(cmd(1, 0, 0, "warnings"), f"@01 0 00 OK IDLE {flags} {w}\r\n"),
            (cmd(1, 0, 1, "get limit.cycle.dist"), f"@01 0 01 OK IDLE -- {cyc}\r\n"),
            (cmd(1, 0, 2, "get limit.min"), "@01 0 02 OK IDLE -- -190000 -176000 -360000 -350000\r\n"),
            (cmd(1, 0, 3, "get limit.max"), "@01 0 03 OK IDLE -- 190000 176000 360000 350000\r\n")]


def test_goniometer_move_in_degrees():
    s = default_settings()
    ex = expect("g1", _connect_script() + [
        (cmd(1, 0, 4, "get pos"), "@01 0 04 OK IDLE -- 0 0 0 0\r\n"),
        (cmd(1, 1, 5, "move abs 60000"), "@01 1 05 OK BUSY -- 0\r\n"),      # 30 deg
        (cmd(1, 2, 6, "move abs -20000"), "@01 2 06 OK BUSY -- 0\r\n"),     # -10 deg
        (cmd(1, 0, 7), "@01 0 07 OK BUSY -- 0\r\n"),
        (cmd(1, 0, 8), "@01 0 08 OK IDLE -- 0\r\n"),
        (cmd(1, 0, 9, "get pos"), "@01 0 09 OK IDLE -- 60000 -20000 0 0\r\n"),     # verified
        (cmd(1, 0, 10, "get pos"), "@01 0 10 OK IDLE -- 60000 -20000 0 0\r\n"),
    ])
    g = Goniometer(ZaberChain("expect://g1"), s, sleep=lambda t: None)
    assert g.connect() == []
    assert g.move_to({"yaw": 30.0, "tilt": -10.0}) == {"yaw": 30.0, "tilt": -10.0}
    assert g.positions() == {"yaw": 30.0, "tilt": -10.0, "azimuth": 0.0, "lamp": 0.0}
    assert g.deg_to_steps("lamp", 1.0) == 2000 and g.steps_to_deg("lamp", 2000) == 1.0
    assert ex.done()


def test_short_move_is_reported_with_flags():
    from gonio.bench.drivers import MoveError
    ex = expect("g4", _connect_script() + [
        (cmd(1, 0, 4, "get pos"), "@01 0 04 OK IDLE -- 0 0 0 0\r\n"),
        (cmd(1, 4, 5, "move abs 100000"), "@01 4 05 OK BUSY -- 0\r\n"),
        (cmd(1, 0, 6), "@01 0 06 OK IDLE WL 0\r\n"),
        (cmd(1, 0, 7, "get pos"), "@01 0 07 OK IDLE WL 0 0 0 40000\r\n"),
        (cmd(1, 0, 8, "warnings"), "@01 0 08 OK IDLE WL 01 WL\r\n"),
    ])
    g = Goniometer(ZaberChain("expect://g4"), default_settings(), sleep=lambda t: None)
    g.connect()
    with pytest.raises(MoveError) as e:
        g.move_to({"lamp": 50.0})
    assert "lamp at 20.000 deg instead of 50.000" in str(e.value) and "WL unexpected limit switch" in str(e.value)
    assert e.value.flags == ("WL",) and ex.done()


def test_again_is_sent_again():
    ex = expect("z10", [(cmd(1, 0, 0, "get pos"), "@01 0 00 RJ BUSY -- AGAIN\r\n"),
                        (cmd(1, 0, 1, "get pos"), "@01 0 01 OK IDLE -- 5\r\n")])
    assert ZaberChain("expect://z10").get(1, 0, "pos") == [5.0] and ex.done()


def test_soft_limits_checked_before_any_move():
    s = default_settings()
    ex = expect("g2", _connect_script() + [(cmd(1, 0, 4, "get pos"), "@01 0 04 OK IDLE -- 0 0 0 0\r\n")])
    g = Goniometer(ZaberChain("expect://g2"), s, sleep=lambda t: None)
    g.connect()
    with pytest.raises(UnreachableError, match="tilt"):
        g.move_to({"yaw": 10.0, "tilt": 89.0})                          # settings: tilt within +-88
    assert ex.done()                                                    # nothing was sent after get pos
    assert g.axes["tilt"].hi_deg == 88.0 and g.axes["lamp"].hi_deg == 175.0


def test_homing_and_flags():
    ex = expect("g3", _connect_script(flags="WR") + [
        (cmd(1, 0, 4, "warnings"), "@01 0 04 OK IDLE WR 02 WR WH\r\n"),
        (cmd(1, 0, 5, "home"), "@01 0 05 OK BUSY WR 0\r\n"),
        (cmd(1, 0, 6), "@01 0 06 OK IDLE -- 0\r\n"),
    ])
    g = Goniometer(ZaberChain("expect://g3"), default_settings(), sleep=lambda t: None)
    assert g.connect() == ["WR"]
    assert g.needs_homing()
    g.home()
    assert ex.done()


def test_connect_clears_latched_fault_or_refuses():
    ex = expect("g5", [(cmd(1, 0, 0, "warnings"), "@01 0 00 OK IDLE FS 01 FS\r\n"),
                       (cmd(1, 0, 1, "warnings clear"), "@01 0 01 OK IDLE FS 01 FS\r\n"),
                       (cmd(1, 0, 2, "warnings"), "@01 0 02 OK IDLE FS 01 FS\r\n")])
    with pytest.raises(FaultError, match="FS stalled and stopped"):
        Goniometer(ZaberChain("expect://g5"), default_settings()).connect(clear_faults=True)
    assert ex.done()


def test_led_commands():
    # issue 17: the channel is an axis and the flux a fraction of lamp.flux.max, as
    # zaber-motion's Illuminator sends it (was /2 0 lamp on, /2 0 set lamp.flux 0.8)
    ex = expect("l1", [(cmd(2, 1, 0, "lamp on"), "@02 1 00 OK IDLE -- 0\r\n"),
                       (cmd(2, 1, 1, "get lamp.flux.max"), "@02 1 01 OK IDLE -- 1.000\r\n"),
                       (cmd(2, 1, 2, "set lamp.flux 0.8"), "@02 1 02 OK IDLE -- 0\r\n"),
                       (cmd(2, 1, 3, "get lamp.temperature"), "@02 1 03 OK IDLE -- 31.5\r\n"),
                       (cmd(2, 0, 4, "lamp off"), "@02 0 04 OK IDLE -- 0\r\n")])
    led = LedSource(ZaberChain("expect://l1"))
    led.on()
    led.set_flux(0.8)
    assert led.temperature() == 31.5
    led.off()
    with pytest.raises(GonioError):
        led.set_flux(1.5)
    assert ex.done()


def test_broadcast_estop():
    from gonio.bench.session.capture import estop
    ex = expect("e1", [(cmd(0, 0, 0, "estop"), "@01 0 00 OK IDLE NI 0\r\n@02 0 00 OK IDLE -- 0\r\n")])
    assert estop("expect://e1") == 2
    assert ex.done()
