"""gonio's meter driver through PyVISA (pyvisa-py) on the simulated meter's pty."""

import pytest

import gonio.sim as gs
from gonio.bench.drivers.meter import PowerMeter, is_visa_resource
from gonio.core.errors import CommunicationError

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
        assert m.identify() == "gonio,SimPowerMeter,SIM00001,0.1.0"
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
