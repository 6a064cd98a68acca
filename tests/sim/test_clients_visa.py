"""PyVISA 1.16 (pyvisa-py backend) and PyMeasure 0.16's ThorlabsPM100USB against the simulated
meter on a `gonio sim serve` pseudo-terminal (``ASRL/dev/pts/N::INSTR``).

Reference behaviour: IEEE 488.2 (common commands; status byte bit 2 = error queue not empty
in SCPI's status model, bit 5 = ESB; ESR bit 5 = command error), SCPI-1999 error codes
(-113 undefined header, -131 invalid suffix, -230 data stale), Thorlabs' PM100 sensor
identification as PyMeasure parses it (name, serial, date, type, subtype, flags).
"""

import warnings

import pytest

import gonio.sim as gs

pyvisa = pytest.importorskip("pyvisa", reason="PyVISA is not installed")
pytest.importorskip("pyvisa_py", reason="pyvisa-py is not installed")

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def meter(tmp_path):
    srv = gs.serve(seed=1, clock=gs.SimClock("instant"), link_dir=str(tmp_path / "p"), block=False, echo=None,
                   lamp={"drift_sigma": 0.0, "delta_t": 0.0})
    yield srv
    srv.stop()


def _resource(srv, write_termination="\n"):
    rm = pyvisa.ResourceManager("@py")
    return rm.open_resource(f"ASRL{srv.devices['meter']}::INSTR", read_termination="\n",
                            write_termination=write_termination, timeout=2000)


@pytest.mark.parametrize("ending", ["\n", "\r", "\r\n"])
def test_common_commands_any_line_ending(meter, ending):
    r = _resource(meter, ending)
    try:
        assert r.query("*IDN?") == "Thorlabs,PM100D,P0000001,2.8.0"
        assert r.query("*OPC?") == "1" and r.query("*STB?") == "0" and r.query("*TST?") == "0"
        r.write("BOGUS:HEADER")
        assert r.query("*STB?") == "4"                 # error queue not empty
        assert r.query("*ESR?") == "32" and r.query("*ESR?") == "0"    # command error, cleared on read
        assert r.query("SYST:ERR:NEXT?") == '-113,"Undefined header"'
        r.write("*ESE 32;*SRE 32")
        r.write("FOO")
        assert r.query("*STB?") == str(4 | 32 | 64)     # EAV, ESB, MSS
        r.write("*CLS")
        assert r.query("*STB?") == "0" and r.query("SYST:ERR?") == '0,"No error"'
    finally:
        r.close()


def test_scpi_subset_compound_min_max_suffix(meter):
    r = _resource(meter)
    try:
        r.write("SENS:CORR:WAV 633NM;:SENS:AVER:COUN 10")
        assert r.query("SENS:CORR:WAV?;:SENS:AVER:COUN?") == "6.330000E+02;10"
        r.write("SENS:CORR:WAV 0.7UM")
        assert float(r.query("SENSE:CORRECTION:WAVELENGTH?")) == 700.0
        assert r.query("SENS:CORR:WAV? MIN") == "4.000000E+02" and r.query("SENS:CORR:WAV? MAX") == "1.100000E+03"
        r.write("SENS:CORR:WAV 633FURLONG")
        assert r.query("SYST:ERR?") == '-131,"Invalid suffix"'
        r.write("SENS:CORR:WAV MAX;WAV?")                # relative header after ';'
        assert float(r.read()) == 1100.0
        r.write("SENS:AVER:COUN DEF")
        assert r.query("SENS:AVER:COUN?") == "1"
        assert r.query("FETC?;*OPC?") == "1"            # nothing measured yet: FETC? has no answer
        assert r.query("SYST:ERR?") == '-230,"Data corrupt or stale"'
        r.write("CONF:POW;:INIT")
        assert r.query("CONF?") == "POW"
        fetched = float(r.query("FETC?"))
        assert float(r.query("FETC?")) == fetched       # the same reading until the next INIT
        assert abs(float(r.query("READ?"))) < 1e-7      # lamp off: only the meter's noise
        assert r.query("SYST:VERS?") == "1999.0"
    finally:
        r.close()


pymeasure = pytest.importorskip("pymeasure", reason="PyMeasure is not installed")


def test_pymeasure_thorlabs_pm100usb(meter):
    from pymeasure.instruments.thorlabs import ThorlabsPM100USB

    inst = meter.instrument
    inst.lamp.switch(inst.clock.now(), True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)      # "not known whether this device supports SCPI"
        pm = ThorlabsPM100USB(f"ASRL{meter.devices['meter']}::INSTR", visa_library="@py",
                              read_termination="\n", write_termination="\n", timeout=2000)
    try:
        assert (pm.sensor_name, pm.sensor_sn, pm.sensor_type) == ("S120C", "SIM00002", 1)
        assert pm.is_power_sensor and pm.wavelength_settable and not pm.is_energy_sensor
        assert pm.wavelength_min == 400 and pm.wavelength_max == 1100
        pm.wavelength = 5000                              # PyMeasure truncates to the sensor's range
        assert pm.wavelength == 1100
        pm.wavelength = 550
        assert pm.power == pytest.approx(0.01 * 0.1, rel=0.01)    # p0 * splitter (gonio/sim/physics/lamp, gonio/sim/devices/scpi_meter)
        assert pm.id == "Thorlabs,PM100D,P0000001,2.8.0"
        assert pm.ask("SYST:ERR?").strip() == '0,"No error"'
    finally:
        pm.adapter.close()
