"""gonio's meter driver through PyVISA (pyvisa-py) on the simulated meter's pty."""

import time

import pytest

import gonio.sim as gs
from gonio.bench.drivers.meter import PowerMeter, is_visa_resource
from gonio.core.errors import CommunicationError, GonioError
from gonio.sim.devices.scpi_grammar import ScpiMeter

pytest.importorskip("pyvisa", reason="PyVISA is not installed")
pytest.importorskip("pyvisa_py", reason="pyvisa-py is not installed")
pytestmark = pytest.mark.timeout(60)


def test_resource_strings():
    for ok in ("USB0::0x1313::0x8072::P2000000::INSTR", "ASRL/dev/ttyUSB0::INSTR", "TCPIP0::10.0.0.2::5025::SOCKET",
               "asrl/dev/pts/3::instr", "GPIB0::22::INSTR"):
        assert is_visa_resource(ok), ok
    for bad in ("/dev/ttyUSB0", "sim://lab/meter", "USB0::INSTR::x", "ASRL/dev/tty USB0::INSTR", "", None,
                "USB0::" + "1" * 300 + "::INSTR", "rfc2217://host:1::INSTR"):
        assert not is_visa_resource(bad), bad


def test_meter_over_visa(tmp_path):
    srv = gs.serve(seed=1, clock=gs.SimClock("instant"), link_dir=str(tmp_path / "p"), block=False, echo=None)
    try:
        m = PowerMeter(f"ASRL{srv.devices['meter']}::INSTR", baudrate=9600, timeout=1.0)
        assert m.identify() == "Thorlabs,PM100D,P0000001,2.8.0"
        m.configure(633, 10)
        assert m.wavelength() == 633.0
        assert abs(m.power()) < 1e-7            # lamp off
        m.close()
    finally:
        srv.stop()


def test_missing_resource_is_one_line():
    with pytest.raises(CommunicationError) as e:
        PowerMeter("ASRL/dev/gonio-no-such-port::INSTR", timeout=0.2)
    assert "power-meter resource" in str(e.value) and "\n" not in str(e.value)


def _real_meter(tmp_path, **lamp):
    return gs.serve(seed=2, clock="real", link_dir=str(tmp_path / "p"), block=False, echo=None,
                    lamp={"drift_sigma": 0.0, "delta_t": 0.0, **lamp})


@pytest.mark.slow
def test_slow_reading_waits_for_its_averaging(tmp_path):
    # issue 40: a fixed 1 s wait took a 1.2 s reading for silence, asked again, and paired the late
    # answer with the next query. The wait now follows the averaging (count x sample time + timeout).
    srv = _real_meter(tmp_path)
    inst = srv.instrument
    try:
        inst.lamp.switch(inst.clock.now(), True)
        m = PowerMeter(f"ASRL{srv.devices['meter']}::INSTR", timeout=1.0, visa_library="@py")
        m.configure(550, 4000)                      # 4000 x 0.3 ms: a 1.2 s reading in real time
        before = inst.meter.readings
        t0 = time.monotonic()
        p = m.power()
        took = time.monotonic() - t0
        assert p == pytest.approx(1e-3, rel=0.01)
        assert inst.meter.readings == before + 1, "the reading was asked for again"
        assert m.retries_used == 0 and 1.1 < took < 5.0, (m.retries_used, took)
        assert m.wavelength() == 550.0 and m.error() == (0, "No error")
        m.close()
    finally:
        srv.stop()


@pytest.mark.slow
def test_late_reply_is_never_paired_with_the_next_query(tmp_path):
    # a meter slower than the driver allows for (sample_time_s too small): the reading misses its
    # wait and arrives later; the next query must get its own answer, not the late reading
    srv = _real_meter(tmp_path)
    inst = srv.instrument
    try:
        inst.lamp.switch(inst.clock.now(), True)
        m = PowerMeter(f"ASRL{srv.devices['meter']}::INSTR", timeout=1.0, retries=0, sample_time_s=1e-6,
                       visa_library="@py")
        m.configure(550, 4000)
        with pytest.raises(CommunicationError):
            m.power()
        assert m.wavelength() == 550.0              # not the late 1e-3 W reading
        assert m.identify() == ScpiMeter.IDN and m.error() == (0, "No error")
        m.close()
    finally:
        srv.stop()


def test_visa_library_is_a_setting():
    # [meter] visa_library picks the VISA library; left out, PyVISA's own default (IVI where
    # installed, else pyvisa-py); a library that is not there is one line naming the setting
    with pytest.raises(CommunicationError) as e:
        PowerMeter.from_settings("ASRL/dev/gonio-no-such-port::INSTR", {"meter": {"visa_library": "@nosuch"}},
                                 timeout=0.2)
    assert "visa_library" in str(e.value) and "@nosuch" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(GonioError, match="visa_library"):
        PowerMeter.from_settings("ASRL/dev/x::INSTR", {"meter": {"visa_library": 5}})


def test_over_range_and_nan_codes_are_errors_not_powers(tmp_path):
    # issue 40: 9.9E37 (SCPI-99 vol. 1, 7.2.1.5: +infinity, the meter's over-range) was taken as
    # a power. A lab's own tool (PyVISA here) leaves the meter on a low range, then the sensor is
    # unplugged (9.91E37, not-a-number): gonio's driver refuses both with a line saying which.
    from gonio.bench.drivers.meter import MeterRangeError
    import pyvisa

    srv = gs.serve(seed=1, clock=gs.SimClock("instant"), link_dir=str(tmp_path / "p"), block=False, echo=None,
                   lamp={"drift_sigma": 0.0, "delta_t": 0.0})
    inst = srv.instrument
    try:
        inst.lamp.switch(inst.clock.now(), True)
        resource = f"ASRL{srv.devices['meter']}::INSTR"
        rm = pyvisa.ResourceManager("@py")
        lab = rm.open_resource(resource, read_termination="\n", write_termination="\n", timeout=2000)
        lab.write("SENS:POW:RANG 5E-6")                     # 5 uW range, auto-ranging off; the light is 1 mW
        assert float(lab.query("MEAS:POW?")) == pytest.approx(9.9e37)
        lab.close()
        rm.close()
        m = PowerMeter(resource, timeout=1.0, visa_library="@py")
        m.configure(550, 1)
        with pytest.raises(MeterRangeError, match="over the meter's range"):
            m.power()
        m.command("SENS:POW:RANG:AUTO ON")
        assert m.power() == pytest.approx(1e-3, rel=0.01)
        inst.meter.sensor = False
        with pytest.raises(MeterRangeError, match="not-a-number"):
            m.power()
        m.close()
    finally:
        srv.stop()
