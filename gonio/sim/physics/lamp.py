"""LED source physics: flux setting, thermal warm-up, seeded slow drift, failure.

Notes
-----
The LED junction temperature settles exponentially towards ``t_ambient + delta_t * flux``
(time constant ``tau``, s) while on, and back to ``t_ambient`` while off. LED output falls
with temperature (thermal droop ``droop`` per kelvin), so after switch-on the emitted power
starts high and settles over minutes:

    P(t) = flux * p0 * (1 - droop (T(t) - T_amb)) / (1 - droop delta_t) * exp(w(t))

normalised so that ``p0`` is the settled power at full flux (W). ``w(t)`` is a random walk
(``drift_sigma`` per sqrt(s), linearly interpolated on a 1 s grid) drawn from a Generator
derived from the instrument seed: the same seed gives the same drift whatever the order of
the queries.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["Lamp"]

_BLOCK = 4096


class Lamp:
    """LED source state.

    Parameters
    ----------
    seed : int
        Instrument seed (the drift Generator is ``default_rng([seed, 0x1A3B])``).
    p0 : float
        Settled emitted power at full flux, W.
    tau : float
        Thermal time constant, s.
    delta_t : float
        Junction temperature rise at full flux, K.
    droop : float
        Relative output loss per kelvin, 1/K.
    drift_sigma : float
        Random-walk standard deviation of log power per sqrt(second).
    t_ambient : float
        Ambient temperature, deg C.
    flux_max : float
        What the controller reports as ``lamp.flux.max``; ``lamp.flux`` on the wire is
        ``flux * flux_max``. The units of Zaber's ``lamp.flux`` are not published: the
        default 1.0 (wire value = relative flux) is invented.
    """

    def __init__(self, seed: int = 0, p0: float = 0.01, tau: float = 120.0,
                 delta_t: float = 15.0, droop: float = 0.004, drift_sigma: float = 2e-4,
                 t_ambient: float = 25.0, flux_max: float = 1.0):
        if not (math.isfinite(flux_max) and flux_max > 0):
            raise ValueError("flux_max must be finite and > 0")
        self.flux_max = float(flux_max)
        self.p0 = float(p0)
        self.tau = float(tau)
        self.delta_t = float(delta_t)
        self.droop = float(droop)
        self.drift_sigma = float(drift_sigma)
        self.t_ambient = float(t_ambient)
        self.flux = 1.0
        self.on = False
        self.dead = False
        self._t_ref = 0.0                  # time of the last state change, s
        self._temp_ref = self.t_ambient    # temperature then, deg C
        self._rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x1A3B])
        self._walk = np.zeros(1)

    # ------------------------------------------------------------------ thermal
    def _target_temp(self) -> float:
        lit = self.on and not self.dead
        return self.t_ambient + (self.delta_t * self.flux if lit else 0.0)

    def temperature(self, t: float) -> float:
        """Junction temperature at simulated time ``t`` (s), deg C."""
        target = self._target_temp()
        return target + (self._temp_ref - target) * math.exp(-max(0.0, t - self._t_ref) / self.tau)

    def _change(self, t: float) -> None:
        self._temp_ref = self.temperature(t)
        self._t_ref = t

    def switch(self, t: float, on: bool) -> None:
        """Switch the LED on or off at time ``t`` (s)."""
        self._change(t)
        self.on = bool(on)

    def set_flux(self, t: float, flux: float) -> None:
        """Set the relative flux (0..1) at time ``t`` (s)."""
        if not 0.0 <= flux <= 1.0:
            raise ValueError("flux must lie in [0, 1]")
        self._change(t)
        self.flux = float(flux)

    def die(self, t: float) -> None:
        """The LED fails at time ``t``: no more light, whatever the controller says."""
        self._change(t)
        self.dead = True

    # ------------------------------------------------------------------ output
    def drift(self, t: float) -> float:
        """Multiplicative drift factor exp(w(t)) at time ``t`` (s)."""
        t = max(0.0, t)
        i = int(t)
        while i + 1 >= self._walk.size:
            steps = self._rng.normal(0.0, self.drift_sigma, _BLOCK)
            self._walk = np.concatenate([self._walk, self._walk[-1] + np.cumsum(steps)])
        f = t - i
        return math.exp((1 - f) * self._walk[i] + f * self._walk[i + 1])

    def power(self, t: float) -> float:
        """Emitted power at simulated time ``t`` (s), W."""
        if not self.on or self.dead or self.flux <= 0.0:
            return 0.0
        temp = self.temperature(t)
        rel = (1 - self.droop * (temp - self.t_ambient)) / (1 - self.droop * self.delta_t)
        return self.flux * self.p0 * rel * self.drift(t)
