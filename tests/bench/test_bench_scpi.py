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
    ex = expect("m4", [("MEAS:POW?\n", None), ("MEAS:POW?\n", "1.0E-0\x003\n"), ("MEAS:POW?\n", "nan\n"),
                       ("MEAS:POW?\n", "2.5E-03\n")])
    m = PowerMeter("expect://m4", retries=2)
    assert m.power() == 2.5e-3
    assert m.reconnects == 1 and ex.opened == 2


def test_silent_meter_is_one_line():
    expect("m5", [("MEAS:POW?\n", None)] * 2)
    with pytest.raises(CommunicationError) as e:
        PowerMeter("expect://m5", retries=0).power()
    assert "\n" not in str(e.value) and "resume" in str(e.value)
    with pytest.raises(CommunicationError, match="--meter-port"):
        PowerMeter("/dev/no-such-meter")
