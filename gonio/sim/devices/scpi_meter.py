"""SCPI power meter: physics (``PowerMeter``) and protocol server (``ScpiMeter``).

The meter watches the lamp through a beam splitter. Reading (W):

    reading = P_lamp(t) * splitter * (550 nm / wavelength setting) + noise

(a silicon photodiode's responsivity grows roughly linearly with wavelength, so a meter set
to the wrong wavelength scales its readings; the LED's centroid is 550 nm). Monochromatic
light at lambda (power P) reads ``P * splitter * (lambda / wavelength setting)``. Noise:
Gaussian, ``sqrt((rel_noise P)^2 + abs_noise^2) / sqrt(average count)``, drawn from
``default_rng([seed, 0x3E7E, reading index])``; a reading takes ``average count * sample_time``.

Grammar: IEEE 488.2 and the SCPI command set of a Thorlabs PM100D with a photodiode sensor
(``scpi_grammar.py``); set commands reply nothing; errors queue with SCPI-1999 codes and texts.
"""

# The grammar is what the ThorlabsPM100 package, PyMeasure and PyVISA scripts send.

from __future__ import annotations

import math

import numpy as np

__all__ = ["PowerMeter", "ScpiMeter"]

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
        self.sensor = True          # a sensor head is plugged in (False: every reading is SCPI's NaN)
        self.reset()

    def reset(self) -> None:
        """``*RST`` defaults: 550 nm, no averaging."""
        self.wavelength = 550.0
        self.average = 1

    def read(self, lamp_power: float, nm: float | None = None) -> float:
        """One reading for the given power (W) of the white LED, or of monochromatic light at
        ``nm``; consumes one noise draw."""
        rng = np.random.default_rng([self.seed & 0xFFFFFFFF, 0x3E7E, self.readings])
        self.readings += 1
        mean = lamp_power * self.splitter * (550.0 if nm is None else float(nm)) / self.wavelength
        sigma = math.hypot(self.rel_noise * mean, self.abs_noise) / math.sqrt(self.average)
        return mean + sigma * rng.standard_normal()


from gonio.sim.devices.scpi_grammar import ScpiMeter  # noqa: E402  (the protocol server, after the physics)
