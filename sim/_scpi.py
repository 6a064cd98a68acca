"""SCPI power meter: physics (``PowerMeter``) and protocol server (``ScpiMeter``).

The meter watches the lamp through a beam splitter. Reading (W):

    reading = P_lamp(t) * splitter * (550 nm / wavelength setting) + noise

(a silicon photodiode's responsivity grows roughly linearly with wavelength, so a meter set
to the wrong wavelength scales its readings; the LED's centroid is 550 nm). Noise: Gaussian,
standard deviation ``sqrt((rel_noise P)^2 + abs_noise^2) / sqrt(average count)``, drawn from
``default_rng([seed, 0x3E7E, reading index])``. A reading takes ``average count *
sample_time`` of simulated time.

Grammar (long or short header forms, case-insensitive, optional leading colon, optional
``SENSe:`` node): ``*IDN?``, ``*RST``, ``*CLS``, ``SENS:CORR:WAV <nm>`` (400..1100),
``SENS:CORR:WAV?``, ``SENS:AVER:COUN <n>`` (1..10000), ``SENS:AVER:COUN?``, ``MEAS:POW?``,
``SYST:ERR?``. Set commands reply nothing; errors go to the queue (-113 undefined header,
-222 data out of range, -104 data type error, -109 missing parameter, -350 queue overflow).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["PowerMeter", "ScpiMeter"]

_LONG = {
    "SENSE": "SENS", "CORRECTION": "CORR", "WAVELENGTH": "WAV", "AVERAGE": "AVER",
    "COUNT": "COUN", "MEASURE": "MEAS", "POWER": "POW", "SYSTEM": "SYST", "ERROR": "ERR",
}
_SHORT = set(_LONG.values())
_ERRORS = {
    -104: "Data type error", -109: "Missing parameter", -113: "Undefined header",
    -222: "Data out of range", -350: "Queue overflow",
}


class PowerMeter:
    """Power meter state and reading physics.

    Parameters
    ----------
    seed : int
        Instrument seed.
    splitter : float
        Fraction of the lamp power the meter receives.
    rel_noise, abs_noise : float
        Relative and absolute (W) noise of one sample.
    sample_time : float
        Simulated seconds per averaged sample, s.
    """

    def __init__(self, seed: int = 0, splitter: float = 0.1, rel_noise: float = 5e-4,
                 abs_noise: float = 2e-9, sample_time: float = 3e-4):
        self.seed = int(seed)
        self.splitter = float(splitter)
        self.rel_noise = float(rel_noise)
        self.abs_noise = float(abs_noise)
        self.sample_time = float(sample_time)
        self.readings = 0
        self.reset()

    def reset(self) -> None:
        """``*RST`` defaults: 550 nm, no averaging."""
        self.wavelength = 550.0
        self.average = 1

    def read(self, lamp_power: float) -> float:
        """One reading for the given lamp power (W); consumes one noise draw."""
        rng = np.random.default_rng([self.seed & 0xFFFFFFFF, 0x3E7E, self.readings])
        self.readings += 1
        mean = lamp_power * self.splitter * 550.0 / self.wavelength
        sigma = math.hypot(self.rel_noise * mean, self.abs_noise) / math.sqrt(self.average)
        return mean + sigma * rng.standard_normal()


class ScpiMeter:
    """SCPI server of the power meter port."""

    IDN = "gonio,SimPowerMeter,SIM00001,0.1.0"

    def __init__(self, instrument):
        self.inst = instrument
        self.queue: list[int] = []

    @property
    def meter(self) -> PowerMeter:
        return self.inst.meter

    def _error(self, code: int) -> None:
        if len(self.queue) >= 10:
            self.queue[-1] = -350
        else:
            self.queue.append(code)

    @staticmethod
    def _canon(header: str) -> str | None:
        h = header.upper().lstrip(":")
        if h.startswith("*"):
            return h
        query = h.endswith("?")
        nodes = h.rstrip("?").split(":")
        out = []
        for n in nodes:
            n = _LONG.get(n, n)
            if n not in _SHORT:
                return None
            out.append(n)
        if out[:1] in (["CORR"], ["AVER"]):
            out.insert(0, "SENS")
        return ":".join(out) + ("?" if query else "")

    def handle(self, text: str) -> list[str]:
        """Execute one line; return the reply lines (none for set commands)."""
        text = text.strip()
        if not text:
            return []
        parts = text.split(None, 1)
        header = self._canon(parts[0])
        arg = parts[1].strip() if len(parts) > 1 else None
        m = self.meter
        if header == "*IDN?" and arg is None:
            return [self.IDN]
        if header == "*RST" and arg is None:
            m.reset()
            return []
        if header == "*CLS" and arg is None:
            self.queue.clear()
            return []
        if header == "SYST:ERR?" and arg is None:
            if not self.queue:
                return ['0,"No error"']
            code = self.queue.pop(0)
            return [f'{code},"{_ERRORS[code]}"']
        if header == "SENS:CORR:WAV?" and arg is None:
            return [f"{m.wavelength:.6E}"]
        if header == "SENS:AVER:COUN?" and arg is None:
            return [str(m.average)]
        if header == "MEAS:POW?" and arg is None:
            clock = self.inst.clock
            t0 = clock.now()
            duration = m.average * m.sample_time
            power = self.inst.lamp.power(t0 + 0.5 * duration)
            clock.advance(duration)
            return [f"{m.read(power):.6E}"]
        if header == "SENS:CORR:WAV":
            v = self._number(arg)
            if v is not None:
                if 400.0 <= v <= 1100.0:
                    m.wavelength = v
                else:
                    self._error(-222)
            return []
        if header == "SENS:AVER:COUN":
            v = self._number(arg)
            if v is not None:
                if v == int(v) and 1 <= v <= 10000:
                    m.average = int(v)
                else:
                    self._error(-222)
            return []
        self._error(-113)
        return []

    def _number(self, arg: str | None) -> float | None:
        if arg is None:
            self._error(-109)
            return None
        try:
            v = float(arg)
        except ValueError:
            self._error(-104)
            return None
        if not math.isfinite(v):
            self._error(-222)
            return None
        return v
