"""Byte-exact SCPI power meter exchanges and reading statistics."""

import numpy as np
import pytest

from sim_helpers import exchange


def test_scpi_exchange(make):
    inst = make()
    m = inst.open("meter", timeout=0.2)
    exchange(m, [
        (b"*IDN?", b"Thorlabs,PM100D,P0000001,2.8.0\n"),
        (b"SYST:ERR?", b'0,"No error"\n'),
        (b"SENS:CORR:WAV 633", b""),
        (b"SENS:CORR:WAV?", b"6.330000E+02\n"),
        (b"sense:correction:wavelength 2000", b""),
        (b"SYST:ERR?", b'-222,"Data out of range"\n'),
        (b"SENS:CORR:WAV?", b"6.330000E+02\n"),
        (b"SENS:AVER:COUN 100", b""),
        (b"SENS:AVER:COUN?", b"100\n"),
        (b"SENS:AVER:COUN 0", b""),
        (b"FOO:BAR?", b""),
        (b"SYST:ERR?", b'-222,"Data out of range"\n'),
        (b"SYST:ERR?", b'-113,"Undefined header"\n'),
        (b"SYST:ERR?", b'0,"No error"\n'),
        (b"SENS:CORR:WAV abc", b""),
        (b"SYST:ERR?", b'-104,"Data type error"\n'),
        (b"*RST", b""),
        (b"SENS:CORR:WAV?", b"5.500000E+02\n"),
        (b"SENS:AVER:COUN?", b"1\n"),
    ], end=b"\n")
    m.write(b"MEAS:POW?\n")
    line = m.readline()
    assert line.endswith(b"\n") and b"E" in line
    assert abs(float(line)) < 1e-7            # lamp off: only the meter's own noise


def test_reading_tracks_lamp_and_noise(make):
    inst = make(lamp={"drift_sigma": 0.0, "delta_t": 0.0})
    z, m = inst.open("zaber"), inst.open("meter", timeout=0.2)
    z.write(b"/2 0 lamp on\r\n"), z.readline()
    vals = []
    for _ in range(400):
        m.write(b"MEAS:POW?\n")
        vals.append(float(m.readline()))
    vals = np.array(vals)
    expected = 0.01 * 0.1              # p0 * splitter
    assert vals.mean() == pytest.approx(expected, rel=2e-4)
    sigma = np.hypot(5e-4 * expected, 2e-9)
    assert vals.std(ddof=1) == pytest.approx(sigma, rel=0.15)
    m.write(b"SENS:AVER:COUN 100\n")
    vals = []
    for _ in range(200):
        m.write(b"MEAS:POW?\n")
        vals.append(float(m.readline()))
    assert np.std(vals, ddof=1) == pytest.approx(sigma / 10, rel=0.2)
