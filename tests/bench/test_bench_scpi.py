"""SCPI power meter driver, byte for byte."""

import pytest

from benchfakes import expect
from gonio.bench.drivers.meter import PowerMeter
from gonio.core.errors import CommunicationError, DeviceError, GonioError


def test_identify_configure_read():
    ex = expect("m1", [
        ("*IDN?\n", "Thorlabs,PM100USB,P1000,1.4\n"),
        ("SENS:CORR:WAV 550\n", None), ("SYST:ERR?\n", '0,"No error"\n'),
        ("SENS:AVER:COUN 100\n", None), ("SYST:ERR?\n", '+0,"No error"\n'),
        ("SENS:CORR:WAV?\n", "550\n"),
        ("MEAS:POW?\n", "1.2345E-03\n"),
    ])
    m = PowerMeter("expect://m1")
    assert m.identify() == "Thorlabs,PM100USB,P1000,1.4"
    m.configure(550, 100)
    assert m.wavelength() == 550.0
    assert m.power() == pytest.approx(1.2345e-3)
    assert ex.done()


def test_error_queue_after_set_raises():
    expect("m2", [("SENS:CORR:WAV 99999\n", None), ("SYST:ERR?\n", '-222,"Data out of range"\n')])
    with pytest.raises(DeviceError) as e:
        PowerMeter("expect://m2").command("SENS:CORR:WAV 99999")
    assert "-222" in str(e.value) and "Data out of range" in str(e.value) and "\n" not in str(e.value)


def test_bad_settings_rejected_before_sending():
    expect("m3", [])
    m = PowerMeter("expect://m3")
    with pytest.raises(GonioError):
        m.configure(float("nan"), 10)
    with pytest.raises(GonioError):
        m.configure(550, 0)


def test_retries_then_reconnect():
    # a silent or garbled answer may be a late one on its way: the marker *OPC?;*OPC? (answered
    # 1;1, which no single query gives) resynchronises before the query is sent again
    ex = expect("m4", [("SENS:AVER:COUN?\n", "10\n"),
                       ("MEAS:POW?\n", None), ("*OPC?;*OPC?\n", "1;1\n"),
                       ("MEAS:POW?\n", "1.0E-0\x003\n"), ("*OPC?;*OPC?\n", "1;1\n"),
                       ("MEAS:POW?\n", "nan\n"), ("*OPC?;*OPC?\n", "1;1\n"),
                       ("MEAS:POW?\n", "2.5E-03\n")])
    m = PowerMeter("expect://m4", retries=2)
    assert m.power() == 2.5e-3
    assert m.reconnects == 1 and ex.opened == 2 and ex.done()


def test_late_reply_is_dropped_not_paired_with_the_next_query():
    # MEAS:POW?'s answer misses its wait; the resync marker finds it still queued before its own
    # answer, drops it, and the next query gets its own answer
    ex = expect("m6", [("MEAS:POW?\n", None), ("*OPC?;*OPC?\n", "1.2E-03\n1;1\n"),
                       ("MEAS:POW?\n", "1.3E-03\n"), ("*IDN?\n", "Thorlabs,PM100USB,P1,1.7.0\n")])
    m = PowerMeter("expect://m6", retries=2)
    m.averaging = 10
    assert m.power() == 1.3e-3
    assert m.identify() == "Thorlabs,PM100USB,P1,1.7.0" and ex.done()


@pytest.mark.parametrize("code, word", [("9.9E37", "over"), ("+9.900000E+37", "over"), ("-9.9E37", "under"),
                                        ("9.91E37", "not-a-number"), ("9.910000E+37", "not-a-number")])
def test_scpi_range_and_nan_codes_are_errors_not_powers(code, word):
    # SCPI-99 vol. 1, 7.2.1.5: 9.9E37 is +infinity, -9.9E37 -infinity, 9.91E37 not-a-number
    from gonio.bench.drivers.meter import MeterRangeError

    ex = expect("m7", [("MEAS:POW?\n", code + "\n")])
    m = PowerMeter("expect://m7")
    m.averaging = 1
    with pytest.raises(MeterRangeError) as e:
        m.power()
    assert word in str(e.value) and "\n" not in str(e.value) and ex.done()


def test_reading_waits_for_its_averaging():
    expect("m8", [])
    m = PowerMeter("expect://m8", timeout=0.5, sample_time_s=2e-3)
    m.averaging = 5000
    assert m.reading_time() == pytest.approx(10.0)


def test_silent_meter_is_one_line():
    expect("m5", [("SENS:AVER:COUN?\n", "1\n"), ("MEAS:POW?\n", None), ("*OPC?;*OPC?\n", None),
                  ("*OPC?;*OPC?\n", None)])
    with pytest.raises(CommunicationError) as e:
        PowerMeter("expect://m5", retries=0).power()
    assert "\n" not in str(e.value) and "resume" in str(e.value)
    with pytest.raises(CommunicationError, match="--meter-port"):
        PowerMeter("/dev/no-such-meter")
