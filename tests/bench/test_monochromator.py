"""The Cornerstone monochromator driver against its twin over a real pseudo-terminal.

Reference bytes: Newport's Cornerstone manuals (MCS260 appendix I 16.3-16.7; MCS260B 15.4-15.9).
Reference times: the twin's timing model (gonio/sim/devices/monochromator.py: GOWAVE 0.05 s +
|move| / (175 nm/s x 1200 / lines), GRAT 6 s, 0.8 s per filter position) plus 1 ms per
statement (the instant clock's latency).
"""

import math

import pytest
import serial

import gonio.sim as gs
from gonio.bench.drivers.monochromator import Monochromator
from gonio.core.errors import CommunicationError, DeviceError, GonioError
from gonio.sim.devices.monochromator import MonochromatorHost
from gonio.sim.pty_server import PtyServer

LATENCY = 1e-3          # simulated seconds per statement (SimClock's default latency)


@pytest.fixture
def twin(tmp_path, request):
    """(host, pty path) of a monochromator twin; ``@pytest.mark.parametrize("twin", [{...}], indirect=True)``
    passes `MonochromatorHost` options."""
    host = MonochromatorHost(**getattr(request, "param", {}))
    with PtyServer(host, str(tmp_path / "ports")).start() as srv:
        yield host, srv.paths["monochromator"]


#: a lost answer after a move is waited for timeout + move_timeout_s: short here, 30 s by default
QUICK = {"monochromator": {"move_timeout_s": 0.1}}


def _open(path, **kw):
    return Monochromator(path, kw.pop("settings", None), timeout=kw.pop("timeout", 0.2), **kw)


def _one_line(exc) -> str:
    text = str(exc.value)
    assert "\n" not in text and text
    return text


def test_bytes_match_the_manuals(twin):
    host, path = twin
    port = serial.Serial(path, 9600, timeout=1.0)

    def said(statement: bytes, expected: bytes) -> None:
        port.write(statement)
        assert port.read(len(expected)) == expected

    said(b"GOWAVE 500\r\n", b"GOWAVE 500\r\n")                # MCS260B 15.4, RS-232 echo on
    said(b"WAVE?\r\n", b"WAVE?\r\n500.00\r\n")                # MCS260B 15.4 (its unit read 500.01)
    said(b"WAVE?\n", b"WAVE?\n500.00\r\n")                    # MCS260 16.3: WAVE?[lf]500[cr][lf]
    said(b"gowave 587.1\r\n", b"gowave 587.1\r\n")            # MCS260B 15.8: any case, echoed as sent
    said(b"STB?\r\n", b"STB?\r\n00\r\n")                      # MCS260 16.7: 00 no error
    said(b"GOWAVE 1500\r\n", b"GOWAVE 1500\r\n")              # beyond grating 1's 1400 nm
    said(b"STB?\r\n", b"STB?\r\n20\r\n")                      # 20: error condition, then cleared
    said(b"ERROR?\r\n", b"ERROR?\r\n3\r\n")                   # 3: destination not allowed
    said(b"ERROR?\r\n", b"ERROR?\r\n0\r\n")                   # read resets it
    said(b"HANDSHAKE 1\r\n", b"HANDSHAKE 1\r\n00\r\n")        # MCS260B 15.5: status after each statement
    said(b"GOWAVE 500\r\n", b"GOWAVE 500\r\n00\r\n")          # MCS260B 15.5, echo and handshake on
    said(b"HANDSHAKE 0\r\n", b"HANDSHAKE 0\r\n")
    said(b"ECHO 0\r\n", b"ECHO 0\r\n")                        # echoed as it arrives, before it acts
    said(b"WAVE?\r\n", b"500.00\r\n")                         # MCS260B 15.4, echo off
    port.write(b"GOWAVE 510\r\nECHO 1\r\n")                   # no echo, no response
    said(b"FOO\r\n", b"FOO\r\n")                              # echo on again
    said(b"ERROR?\r\n", b"ERROR?\r\n1\r\n")                   # 1: command not understood
    said(b"GRAT?\r\n", b"GRAT?\r\n1,1200,350NM\r\n")
    said(b"\r\n", b"\r\n")                                    # a blank line: echoed, nothing done
    said(b"X" * 300 + b"\r\nWAVE?\r\n", b"X" * 128 + b"\nWAVE?\r\n510.00\r\n")   # 128-byte buffer
    said(b"ERROR?\r\n", b"ERROR?\r\n1\r\n")
    port.timeout = 0.05
    assert port.read(64) == b""                               # nothing more was sent
    port.close()
    assert host.monochromator.drive.nm == 510.0


def test_wavelength_round_trip_picks_grating_and_filter_by_range(twin):
    host, path = twin
    drive = host.monochromator.drive
    with _open(path) as mono:
        assert mono.echo is True and mono.identify() == "CORNERSTONE 260 VER 2.31 TWIN"
        # DEFAULTS: grating 1 200-650 nm, 2 650-1400; filter 1 200-400, 2 400-750, 3 750-1400
        for nm, grating, filter_ in ((350.0, 1, 1), (600.0, 1, 2), (900.0, 2, 3), (532.1, 1, 2), (750.0, 2, 2)):
            assert mono.go_to(nm) == nm
            assert (mono.grating(), mono.filter()) == (grating, filter_)
            assert (drive.grating, drive.filter, drive.nm) == (grating, filter_, nm)
        assert mono.wavelength() == 750.0
        mono.shutter(True)
        assert drive.shutter_open
        mono.shutter(False)
        assert not drive.shutter_open
        assert mono.retries_used == 0


def test_moves_take_the_twins_time_on_the_sim_clock(twin):
    host, path = twin
    clock = host.clock
    with _open(path) as mono:
        t = clock.now()
        mono.go_to(500.0)               # power-on: grating 1 at 0 nm, filter 1 -> filter 2 and 500 nm
        # GRAT?, FILTER?, FILTER 2, STB?, FILTER?, GOWAVE, STB?, WAVE?: 8 statements, the 2 STB? received
        # while the drive moves cost nothing more (they wait for the move's end)
        assert clock.now() - t == pytest.approx(0.8 + 0.05 + 500 / 175 + 6 * LATENCY, abs=1e-9)
        t = clock.now()
        mono.go_to(900.0)               # turret to grating 2 (600 l/mm: 350 nm/s), filter 3, +400 nm
        expected = 6.0 + 0.05 + 0.8 + 0.05 + 400 / 350 + 8 * LATENCY     # 11 statements, 3 during moves
        assert clock.now() - t == pytest.approx(expected, abs=1e-9)
        t = clock.now()
        mono.go_to(1000.0)              # same grating and filter: the move alone, 100 nm
        short = clock.now() - t
        t = clock.now()
        mono.go_to(1200.0)              # 200 nm: twice the slewing
        assert (clock.now() - t) - short == pytest.approx(100 / 350, abs=1e-9)


def test_out_of_range_is_one_line(twin, tmp_path):
    host, path = twin
    wide = {"monochromator": {"gratings": [[1, 200, 1600]], "filters": [[1, 200, 1600]]}}
    with _open(path, settings=wide) as mono:
        mono.go_to(700.0)
        with pytest.raises(DeviceError) as exc:
            mono.go_to(1500.0)          # allowed by these settings, beyond the 1200 l/mm grating's 1400 nm
        text = _one_line(exc)
        assert "GOWAVE 1500" in text and "error 3" in text and "gratings" in text
        assert host.monochromator.drive.nm == 700.0 and mono.wavelength() == 700.0
    with _open(path) as mono:
        for bad in (5000.0, 100.0, math.nan, math.inf, -1.0, "abc", None):
            with pytest.raises(GonioError) as exc:
                mono.go_to(bad)
            assert "monochromator" in _one_line(exc) or "not a number" in str(exc.value)
        assert host.monochromator.drive.nm == 700.0
    for settings in ({"gratings": [[0, 200, 600]]}, {"gratings": [[1, 600, 200]]}, {"filters": "open"},
                     {"gratings": [[1, 200, math.nan]]}, {"move_timeout_s": -1}, {"baudrate": 1234},
                     {"grating": [[1, 200, 600]]}):
        with pytest.raises(GonioError) as exc:
            _open(path, settings={"monochromator": settings})
        assert "[monochromator]" in _one_line(exc)
    with pytest.raises(CommunicationError) as exc:
        _open(str(tmp_path / "no-such-port"))
    assert "cannot open the monochromator port" in _one_line(exc)


@pytest.mark.parametrize("twin", [{"filters": 0}], indirect=True)
def test_a_monochromator_without_filter_wheel(twin):
    host, path = twin
    with _open(path) as mono:                    # default filters: FILTER? answers error 6 (MCS260B 15.9)
        with pytest.raises(DeviceError) as exc:
            mono.filter()                        # echoed, unanswered: the status says why
        assert "refused 'FILTER?': error 6" in _one_line(exc) and mono.retries_used == 0
        with pytest.raises(DeviceError) as exc:
            mono.command("FILTER 2")
        assert "error 6" in _one_line(exc) and "filters = []" in str(exc.value)
    with _open(path, settings={"monochromator": {"filters": []}}) as mono:
        assert mono.go_to(900.0) == 900.0 and host.monochromator.drive.grating == 2
        with pytest.raises(GonioError) as exc:
            mono.go_to(1450.0)
        assert "(200-1400 nm" in _one_line(exc)


@pytest.mark.parametrize("twin", [{"echo": False}], indirect=True)
def test_an_instrument_that_does_not_echo(twin):
    host, path = twin
    host.monochromator.handshake = True          # left in handshake mode by another program
    with _open(path) as mono:
        assert mono.echo is False and not host.monochromator.handshake
        assert mono.go_to(455.5) == 455.5 and host.monochromator.drive.filter == 2


def test_a_dropped_reply_is_sent_again(twin):
    host, path = twin
    twin_ = host.monochromator
    with _open(path, settings=QUICK) as mono:
        mono.go_to(600.0)
        twin_.drop_at = frozenset({twin_.statements + 1})            # the next WAVE? answer is lost
        assert mono.wavelength() == 600.0
        assert (twin_.dropped, mono.retries_used) == (1, 1)
        twin_.drop_at = frozenset({twin_.statements + 3})            # GRAT?, FILTER?, then GOWAVE's echo
        assert mono.go_to(610.0) == 610.0                             # sent again: it sets an absolute state
        assert (twin_.dropped, mono.retries_used) == (2, 2)
        assert host.monochromator.drive.nm == 610.0


@pytest.mark.parametrize("twin", [{"stuck_filter": True}], indirect=True)
def test_a_stuck_filter_wheel_is_reported(twin):
    host, path = twin
    with _open(path) as mono:
        assert mono.go_to(350.0) == 350.0            # filter 1 already in place
        with pytest.raises(DeviceError) as exc:
            mono.go_to(600.0)
        text = _one_line(exc)
        assert "stayed at 1 after FILTER 2" in text and "stuck" in text
        assert host.monochromator.drive.nm == 350.0  # it did not drive on without its filter


def test_garbled_or_missing_answers(twin, monkeypatch):
    host, path = twin
    twin_ = host.monochromator
    with _open(path, settings=QUICK, retries=1) as mono:
        query = twin_._query
        garbage = iter(["5OO.O0", "\x7f\x01", "500.00"])
        monkeypatch.setattr(twin_, "_query", lambda head: next(garbage) if head == "WAVE?" else query(head))
        assert mono.wavelength() == 500.0 and mono.retries_used == 2
        monkeypatch.setattr(twin_, "_query", lambda head: "NaN" if head == "WAVE?" else query(head))
        with pytest.raises(CommunicationError) as exc:
            mono.wavelength()
        assert "garbled answer 'NaN'" in _one_line(exc)
        monkeypatch.setattr(twin_, "_query", query)
        twin_.drop_probability = 1.0
        with pytest.raises(CommunicationError) as exc:
            mono.wavelength()
        assert "gave no" in _one_line(exc) and "baud rate (9600)" in str(exc.value)


def test_the_instrument_serves_it_when_settings_ask(tmp_path):
    inst = gs.Instrument(seed=1)
    assert "monochromator" not in inst.ports
    inst = gs.Instrument(seed=1, settings={"monochromator": {}}).register("mono-test")
    try:
        with Monochromator(inst.url("monochromator"), timeout=0.2) as mono:
            assert mono.go_to(640.0) == 640.0 and inst.monochromator.drive.filter == 2
    finally:
        inst.unregister()
