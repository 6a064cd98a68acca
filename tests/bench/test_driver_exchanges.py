"""gonio's Zaber driver against what real controllers send (scripted byte exchanges).

Reference formats, Zaber ASCII protocol manual: reply ``@DD A [ID] FLAG STATUS WARN DATA``,
info ``#DD A [ID] ...``, alert ``!DD A STATUS WARN [DATA]``, continuation: a packet whose data
ends in ``\\`` goes on in ``#DD A [ID] cont DATA`` (zaber-motion 10.3 joins the parts with one
space, so no space precedes the backslash); ``NA`` for an axis without the setting.
"""

import math

import pytest

from benchfakes import expect
from gonio.bench.settings import default_settings
from gonio.bench.drivers import Goniometer, LedSource, ZaberChain, emergency_stop, format_command, lrc, parse_reply
from gonio.bench.drivers.zaber_protocol import parse_continuation
from gonio.core.errors import CommunicationError, GonioError


def cmd(device, axis, msgid, text=""):
    return format_command(device, axis, text, msgid, checksum=True)


def sealed(lead, body):
    return f"{lead}{body}:{lrc(body.encode())}\r\n"


def test_continued_reply_is_joined():
    # the exchange of issue 17: get limit.max split after two values
    ex = expect("c1", [(cmd(1, 0, 0, "get limit.max"),
                        "@01 0 00 OK IDLE -- 190000 176000\\\r\n#01 0 00 cont 360000 350000\r\n")])
    with ZaberChain("expect://c1") as z:
        assert z.get(1, 0, "limit.max") == [190000.0, 176000.0, 360000.0, 350000.0]
    assert ex.done()


def test_continuation_over_three_packets_with_checksums_alerts_and_info_between():
    reply = (sealed("@", "01 0 00 OK IDLE -- 1 2\\") + "!01 3 IDLE NI\r\n" + sealed("#", "01 0 00 cont 3\\")
             + "#01 0 info: something else\r\n" + "#01 0 07 cont 99\r\n" + sealed("#", "01 0 00 cont 4"))
    ex = expect("c2", [(cmd(1, 0, 0, "get pos"), reply)])
    z = ZaberChain("expect://c2")
    assert z.get(1, 0, "pos") == [1.0, 2.0, 3.0, 4.0]        # id 07 and the info line were skipped
    assert ex.done()
    assert parse_continuation("#01 0 12 cont a b") == (1, 0, 12, "a b")
    assert parse_continuation("#02 1 cont x") == (2, 1, None, "x")
    for bad in ("#01 0 info", "@01 0 cont 1", "#01 x cont 1", f"#01 0 cont 1:{'00'}"):
        with pytest.raises(ValueError):
            parse_continuation(bad)


def test_broken_continuation_is_garbled_and_retried():
    ex = expect("c3", [(cmd(1, 0, 0, "get pos"), "@01 0 00 OK IDLE -- 1 2\\\r\n@01 0 00 OK IDLE -- 9\r\n"),
                       (cmd(1, 0, 1, "get pos"), "@01 0 01 OK IDLE -- 1 2 3 4\r\n")])
    z = ZaberChain("expect://c3")
    assert z.get(1, 0, "pos") == [1.0, 2.0, 3.0, 4.0] and z.retries_used == 1
    assert ex.done()


def test_endless_continuation_is_bounded():
    z = ZaberChain.__new__(ZaberChain)
    lines = iter([b"#01 0 00 cont 1\\\r\n"] * 200)
    z._readline = lambda: next(lines)
    from gonio.bench.drivers.zaber import _Garbled
    with pytest.raises(_Garbled, match="continued over 64 lines"):
        z._complete(parse_reply("@01 0 00 OK IDLE -- 0\\"))


def test_na_reads_as_nan_and_is_refused_by_name():
    assert [math.isnan(v) for v in parse_reply("@01 0 OK IDLE -- 1 NA 3 NA").values] == [False, True, False, True]
    with pytest.raises(CommunicationError, match="non-numeric data 'x1'"):
        parse_reply("@01 0 OK IDLE -- x1").values
    ex = expect("n1", [(cmd(1, 0, 0, "warnings"), "@01 0 00 OK IDLE -- 00\r\n"),
                       (cmd(1, 0, 1, "get limit.cycle.dist"), "@01 0 01 OK IDLE -- 720000 720000 NA 720000\r\n"),
                       (cmd(1, 0, 2, "get limit.min"), "@01 0 02 OK IDLE -- -190000 -176000 NA -350000\r\n"),
                       (cmd(1, 0, 3, "get limit.max"), "@01 0 03 OK IDLE -- 190000 176000 NA 350000\r\n")])
    with pytest.raises(GonioError) as e:
        Goniometer(ZaberChain("expect://n1"), default_settings()).connect()
    assert "axis 3 (azimuth) answers NA" in str(e.value) and "\n" not in str(e.value)
    assert ex.done()


def test_na_position_is_refused_by_name():
    ex = expect("n2", [(cmd(1, 0, 0, "warnings"), "@01 0 00 OK IDLE -- 00\r\n"),
                       (cmd(1, 0, 1, "get limit.cycle.dist"), "@01 0 01 OK IDLE -- 720000 720000 720000 720000\r\n"),
                       (cmd(1, 0, 2, "get limit.min"), "@01 0 02 OK IDLE -- -1 -1 -1 -1\r\n"),
                       (cmd(1, 0, 3, "get limit.max"), "@01 0 03 OK IDLE -- 1 1 1 1\r\n"),
                       (cmd(1, 0, 4, "get pos"), "@01 0 04 OK IDLE -- 0 NA 0 0\r\n")])
    g = Goniometer(ZaberChain("expect://n2"), default_settings())
    g.connect()
    with pytest.raises(CommunicationError, match=r"no position for axis 2 \(tilt\)"):
        g.positions()
    assert ex.done()


def test_alerts_between_a_command_and_its_reply():
    ex = expect("a1", [(cmd(1, 2, 0, "move abs 1000"), "!01 1 IDLE --\r\n!01 4 IDLE NI\r\n@01 2 00 OK BUSY -- 0\r\n"),
                       (cmd(1, 0, 1), "@01 0 01 OK IDLE -- 0\r\n!01 2 IDLE --\r\n")])
    z = ZaberChain("expect://a1")
    assert z.request(1, 2, "move abs 1000").busy
    assert not z.request(1, 0).busy
    assert ex.done()


def test_broadcast_counts_every_device_past_alerts_and_leaves_nothing():
    # the case of issue 17: an alert interleaved with two devices' replies, plus a late reply
    # to an earlier message id and one after the two
    reply = ("!01 2 IDLE NI\r\n@01 0 17 OK IDLE -- 0\r\n@01 0 00 OK IDLE NI 0\r\n!01 3 IDLE NI\r\n"
             "#01 0 00 info\r\n@02 0 00 OK IDLE -- 0\r\n!01 1 IDLE NI\r\n")
    ex = expect("b1", [(cmd(0, 0, 0, "estop"), reply), (cmd(1, 0, 1), "@01 0 01 OK IDLE NI 0\r\n")])
    z = ZaberChain("expect://b1", timeout=0.05)
    got = z.broadcast("estop", 2)
    assert [(r.device, r.msgid) for r in got] == [(1, 0), (2, 0)]
    assert z._port.in_waiting == 0
    assert z.request(1, 0, check=False).msgid == 1          # the next exchange is clean
    assert ex.done()


def test_broadcast_with_a_duplicate_device_counts_it_once():
    expect("b2", [(cmd(0, 0, 0, "estop"), "@01 0 00 OK IDLE -- 0\r\n@01 0 00 OK IDLE -- 0\r\n")])
    z = ZaberChain("expect://b2", timeout=0.05)
    assert [r.device for r in z.broadcast("estop", 2)] == [1]


def test_emergency_stop_counts_both_devices_with_alerts():
    ex = expect("e2", [(cmd(0, 0, 0, "estop"), "!01 2 IDLE NI\r\n@02 0 00 OK IDLE -- 0\r\n!01 1 IDLE NI\r\n"
                                               "@01 0 00 OK IDLE NI 0\r\n")])
    assert emergency_stop("expect://e2") == 2
    assert ex.done()


def test_led_as_zaber_motion_drives_it():
    # fraction 0.4 of lamp.flux.max 2.5 -> set lamp.flux 1 (zaber-motion 10.3 sends the same)
    ex = expect("l2", [(cmd(2, 3, 0, "lamp on"), "@02 3 00 OK IDLE -- 0\r\n"),
                       (cmd(2, 3, 1, "get lamp.flux.max"), "@02 3 01 OK IDLE -- 2.500\r\n"),
                       (cmd(2, 3, 2, "set lamp.flux 1"), "@02 3 02 OK IDLE -- 0\r\n"),
                       (cmd(2, 3, 3, "set lamp.flux 2.5"), "@02 3 03 OK IDLE -- 0\r\n"),
                       (cmd(2, 0, 4, "lamp off"), "@02 0 04 OK IDLE -- 0\r\n")])
    led = LedSource(ZaberChain("expect://l2"), channel=3)
    led.on()
    led.set_flux(0.4)
    led.set_flux(1.0)                     # lamp.flux.max is read once
    led.off()
    assert ex.done()
    for bad in (-0.1, 1.01, math.nan, math.inf, "0.5"):
        with pytest.raises(GonioError):
            led.set_flux(bad)
    for bad in (0, 10, -1, 1.5, "1"):
        with pytest.raises(GonioError):
            LedSource(led.chain, channel=bad)


def test_led_with_a_bad_flux_max_is_refused():
    from gonio.core.errors import DeviceError
    expect("l3", [(cmd(2, 1, 0, "get lamp.flux.max"), "@02 1 00 OK IDLE -- 0\r\n")])
    with pytest.raises(DeviceError, match="lamp.flux.max"):
        LedSource(ZaberChain("expect://l3")).set_flux(0.5)


# -- waiting for a move by its alerts (issue 17) ----------------------------------------------

#: ``enable_alerts`` reads the device's ``comm.alert`` first, to give it back on close (issue 40)
GET_ALERT = (cmd(1, 0, 0, "get comm.alert"), "@01 0 00 OK IDLE -- 0\r\n")


def test_a_move_is_waited_for_by_its_alerts_read_between_other_replies():
    """``set comm.alert 1``, then ``wait_idle``: one poll (BUSY), the alert of axis 3 read after
    it (past a late reply, an info line and device 2's alert), a poll (BUSY: axis 1 still
    moves), axis 1's alert, a poll (IDLE). An alert read before the first poll (here between
    the packets of ``get pos``) is older than its BUSY and ends nothing. No poll sleeps."""
    ex = expect("w1", [
        GET_ALERT, (cmd(1, 0, 1, "set comm.alert 1"), "@01 0 01 OK IDLE -- 0\r\n"),
        (cmd(1, 0, 2, "get pos"), "!01 2 IDLE --\r\n@01 0 02 OK BUSY -- 1 2 3 4\r\n"),
        (cmd(1, 0, 3), "@01 0 03 OK BUSY -- 0\r\n@01 0 17 OK IDLE -- 0\r\n#01 0 info\r\n!02 1 IDLE --\r\n"
                       + sealed("!", "01 3 IDLE --")),
        (cmd(1, 0, 4), "@01 0 04 OK BUSY -- 0\r\n!01 1 IDLE --\r\n"),
        (cmd(1, 0, 5), "@01 0 05 OK IDLE -- 0\r\n"),
    ])
    z = ZaberChain("expect://w1")
    assert z.enable_alerts(1) and z.alerting == {1}
    z.get(1, 0, "pos")
    slept = []
    assert z.wait_idle(1, timeout_s=5.0, poll_interval_s=0.05, sleep=slept.append).status == "IDLE"
    assert ex.done() and set(slept) == {0} and z.retries_used == 0


def test_a_lost_alert_falls_back_to_a_poll_and_a_cut_alert_is_completed():
    """No alert after a BUSY: the port is read in 0.1 s windows (a safe point, ``sleep(0)``,
    between them) and polled again once it was silent for its timeout. An alert cut by a
    window's end is completed by the next read, not taken for a garbled reply."""
    ex = expect("w2", [
        GET_ALERT, (cmd(1, 0, 1, "set comm.alert 1"), "@01 0 01 OK IDLE -- 0\r\n"),
        (cmd(1, 0, 2), "@01 0 02 OK BUSY -- 0\r\n!01 1 ID"),
        (cmd(1, 0, 3), "LE --\r\n@01 0 03 OK IDLE -- 0\r\n"),
    ])
    z = ZaberChain("expect://w2", timeout=0.5)
    z.enable_alerts(1)
    slept = []
    assert z.wait_idle(1, timeout_s=5.0, poll_interval_s=0.05, sleep=slept.append).status == "IDLE"
    assert ex.done() and z.retries_used == 0 and slept == [0] * 5   # 4 safe points between 5 windows, 1 before the poll


def test_alerts_rejected_or_a_stage_that_never_stops():
    """A device that rejects ``comm.alert`` is polled as before; with alerts on, a stage BUSY
    past the budget (silent windows counted, not wall time) is a `CommunicationError`."""
    expect("w3", [GET_ALERT, (cmd(1, 0, 1, "set comm.alert 1"), "@01 0 01 RJ IDLE -- BADCOMMAND\r\n"),
                  (cmd(1, 0, 2), "@01 0 02 OK BUSY -- 0\r\n"), (cmd(1, 0, 3), "@01 0 03 OK IDLE -- 0\r\n")])
    z = ZaberChain("expect://w3")
    slept = []
    assert not z.enable_alerts(1) and z.alerting == set()
    assert z.wait_idle(1, timeout_s=1.0, poll_interval_s=0.1, sleep=slept.append).status == "IDLE"
    assert slept == [0.1]
    expect("w4", [GET_ALERT, (cmd(1, 0, 1, "set comm.alert 1"), "@01 0 01 OK IDLE -- 0\r\n")]
           + [(cmd(1, 0, k), f"@01 0 {k:02d} OK BUSY -- 0\r\n!01 1 IDLE --\r\n") for k in range(2, 13)])
    z = ZaberChain("expect://w4", timeout=0.2)
    z.enable_alerts(1)
    with pytest.raises(CommunicationError, match="still moving after 0.5 s"):
        z.wait_idle(1, timeout_s=0.5, poll_interval_s=0.05, sleep=lambda s: None)   # 10 alerts: 10 polls' budget


def test_a_device_that_only_sends_other_lines_cannot_keep_the_wait_going():
    """BUSY, then only late replies (never this device's alert, never silence): each round of
    64 skipped lines ends in a poll, and the polls count against the budget."""
    junk = "@01 0 77 OK IDLE -- 0\r\n" * 70
    expect("w5", [GET_ALERT, (cmd(1, 0, 1, "set comm.alert 1"), "@01 0 01 OK IDLE -- 0\r\n")]
           + [(cmd(1, 0, k), f"@01 0 {k:02d} OK BUSY -- 0\r\n" + junk) for k in range(2, 13)])
    z = ZaberChain("expect://w5")
    z.enable_alerts(1)
    with pytest.raises(CommunicationError, match="still moving"):
        z.wait_idle(1, timeout_s=0.5, poll_interval_s=0.05, sleep=lambda s: None)


def test_close_gives_comm_alert_back():
    """Issue 40: ``close`` sets ``comm.alert`` back to what the device had before
    ``enable_alerts`` (0 here); a device that alerted already, or that rejected it, is left as it
    was; a reconnect gives nothing back (the devices keep their settings)."""
    ex = expect("a1", [GET_ALERT, (cmd(1, 0, 1, "set comm.alert 1"), "@01 0 01 OK IDLE -- 0\r\n"),
                       (cmd(2, 0, 2, "get comm.alert"), "@02 0 02 OK IDLE -- 1\r\n"),
                       (cmd(2, 0, 3, "set comm.alert 1"), "@02 0 03 OK IDLE -- 0\r\n"),
                       (cmd(1, 0, 4, "set comm.alert 0"), "!01 1 IDLE --\r\n@01 0 04 OK IDLE -- 0\r\n")])
    z = ZaberChain("expect://a1")
    assert z.enable_alerts(1) and z.enable_alerts(2)
    z.reconnect()
    z.close()
    assert ex.done() and z.alerting == {2}
