"""The ThorlabsPM100 package (1.2.2, the PyPI client a lab drives a PM100A/D with) against the
simulated meter on a `gonio sim serve` pseudo-terminal, over PyVISA with pyvisa-py.

Every operation the package offers is tried: each property read (and written back), each
command method. What a PM100D with a silicon photodiode sensor (S120C) answers is the reference:
a value and an empty error queue, or, for what needs hardware the photodiode lacks (a
thermopile, a pyroelectric head, a thermistor: voltage, energy, temperature, resistance), the
SCPI error -241 "Hardware missing"; never -113 "Undefined header", never a timeout, and every
reply a line of printable ASCII (no NUL). Issue 40: 8 of 17 of its calls failed with -113.
"""

import re

import pytest

import gonio.sim as gs
from gonio.sim.devices.scpi_grammar import ScpiMeter

pyvisa = pytest.importorskip("pyvisa", reason="PyVISA is not installed")
pytest.importorskip("pyvisa_py", reason="pyvisa-py is not installed")
tl = pytest.importorskip("ThorlabsPM100.ThorlabsPM100", reason="ThorlabsPM100 is not installed")
meta = pytest.importorskip("ThorlabsPM100.VISA_wrapper_metaclass")

pytestmark = pytest.mark.timeout(120)

#: what the S120C photodiode has no hardware for (SCPI -241 on a PM100D with that sensor)
_MISSING = re.compile(r"voltage|temperature|energy|edensity|resistance|thermopile|pyro", re.IGNORECASE)


class _Raw:
    """The resource as ThorlabsPM100 uses it (``write``, ``query``), each reply read raw and
    checked: one line of printable ASCII ending in LF."""

    def __init__(self, res):
        self.res = res
        self.sent: list[str] = []

    def write(self, cmd):
        self.sent.append(cmd)
        self.res.write(cmd)

    def query(self, cmd):
        self.sent.append(cmd)
        self.res.write(cmd)
        raw = self.res.read_raw()
        assert raw.endswith(b"\n") and re.fullmatch(rb"[ -~]*\n", raw), f"{cmd!r} got {raw!r}"
        return raw[:-1].decode("ascii")


@pytest.fixture
def pm100(tmp_path):
    srv = gs.serve(seed=3, clock=gs.SimClock("instant"), link_dir=str(tmp_path / "p"), block=False, echo=None,
                   lamp={"drift_sigma": 0.0, "delta_t": 0.0})
    rm = pyvisa.ResourceManager("@py")
    res = rm.open_resource(f"ASRL{srv.devices['meter']}::INSTR", read_termination="\n", write_termination="\n",
                           timeout=2000)
    raw = _Raw(res)
    yield srv, raw, tl.ThorlabsPM100(inst=raw)
    res.close()
    rm.close()
    srv.stop()


def _operations(group, path=""):
    """``(dotted name, command class)`` of every operation of a ThorlabsPM100 group, depth first."""
    cls = group if isinstance(group, type) else type(group)
    for name, klass in dict(cls._property_list.mapping).items():
        yield f"{path}{name}", klass
    for name in cls._subgroups:
        yield from _operations(getattr(cls, name), f"{path}{name}.")


def _target(pm, dotted):
    *groups, name = dotted.split(".")
    obj = pm
    for g in groups:
        obj = getattr(obj, g)
    return obj, name


def test_every_thorlabspm100_operation(pm100):
    srv, raw, pm = pm100
    inst = srv.instrument
    inst.lamp.switch(inst.clock.now(), True)
    pm.initiate.immediate()                      # FETCh? has a reading to give
    tried, answered, missing = [], [], []
    for dotted, klass in _operations(tl.ThorlabsPM100):
        obj, name = _target(pm, dotted)
        sent = len(raw.sent)
        lacking = bool(_MISSING.search(klass.cmd))
        if issubclass(klass, meta.GenericGetCommandClass) or issubclass(klass, meta.GenericGetSetCommandClass):
            if lacking:                                  # SCPI: a query in error has no response
                raw.res.timeout = 200
                with pytest.raises(pyvisa.errors.VisaIOError):
                    getattr(obj, name)
                raw.res.timeout = 2000
            else:
                value = getattr(obj, name)
            if issubclass(klass, meta.GenericGetSetCommandClass) and not lacking:
                try:
                    setattr(obj, name, value)            # written back: the meter takes its own answer
                except ValueError:
                    pass                                 # the package's own check refuses it (a tuple)
        elif issubclass(klass, meta.GenericSetCommandClass):
            setattr(obj, name, klass.get_argument_list()[0].list_value[0])
        else:
            getattr(obj, name)()
        err = raw.res.query("SYST:ERR?")
        rest = raw.res.query("SYST:ERR?")
        tried.append(dotted)
        if lacking:
            assert err == '-241,"Hardware missing"', (dotted, raw.sent[sent:], err)
            missing.append(dotted)
        else:
            assert err == '0,"No error"', (dotted, raw.sent[sent:], err)
            answered.append(dotted)
        assert rest == '0,"No error"', (dotted, raw.sent[sent:], rest)
    assert len(tried) >= 128 and len(answered) >= 92, (len(tried), len(answered))
    assert "sense.power.dc.range.auto" in answered and "measure.scalar.power" in answered
    assert "input.thermopile.accelerator.tau" in missing


def test_thorlabspm100_reads_the_lamp(pm100):
    srv, raw, pm = pm100
    inst = srv.instrument
    inst.lamp.switch(inst.clock.now(), True)
    expected = 0.01 * 0.1                           # p0 * splitter at 550 nm (gonio/sim/physics/lamp, scpi_meter)
    assert pm.system.sensor.idn.startswith("S120C,")
    pm.sense.average.count = 20
    assert pm.sense.average.count == 20
    pm.sense.correction.wavelength = 550
    assert pm.sense.correction.minimum_wavelength == 400 and pm.sense.correction.maximum_wavelength == 1100
    pm.sense.power.dc.range.auto = "ON"
    pm.configure.scalar.power()
    assert pm.getconfigure == "POW"
    assert pm.read == pytest.approx(expected, rel=0.01)
    pm.measure.scalar.power()                       # without "?", as the package sends it: measured for FETCh?
    assert pm.fetch == pytest.approx(expected, rel=0.01)
    pm.initiate.immediate()
    assert pm.fetch == pytest.approx(expected, rel=0.01)
    pm.sense.power.dc.unit = "DBM"
    assert pm.read == pytest.approx(0.0, abs=0.05)  # 1 mW is 0 dBm
    pm.sense.power.dc.unit = "W"
    pm.sense.correction.wavelength = 1100           # a silicon diode's responsivity doubles: half the reading
    assert pm.read == pytest.approx(expected / 2, rel=0.01)
    assert raw.res.query("*IDN?") == ScpiMeter.IDN
    assert ScpiMeter.IDN.startswith("Thorlabs,PM100D,")


def test_over_range_and_no_sensor_are_scpi_codes(pm100):
    srv, raw, pm = pm100
    inst = srv.instrument
    inst.lamp.switch(inst.clock.now(), True)
    pm.sense.power.dc.range.upper = 5e-6            # the light (1 mW) is over this range
    assert pm.sense.power.dc.range.auto == 0
    assert pm.read == pytest.approx(9.9e37)         # SCPI-99 vol. 1, 7.2.1.5: +infinity
    pm.sense.power.dc.range.auto = 1
    assert pm.read == pytest.approx(1e-3, rel=0.01)
    inst.meter.sensor = False
    assert pm.read == pytest.approx(9.91e37)        # not-a-number
    assert pm.system.sensor.idn.startswith("no sensor")
