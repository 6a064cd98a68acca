"""The fit's parameter vector, read from a model's own parameter declarations.

A model declares each parameter once (default, bounds, unit, per-channel or shared); the
fitter never repeats that declaration. Per-channel parameters expand to one entry per colour
channel (``diffuse_reflectance[R]``...), shared ones (roughness, index of refraction) stay one
entry, so shared and per-channel parameters are fitted jointly.

The optimiser works in the unit box u in [0, 1]^P. A parameter whose bounds are positive and
span more than two decades is mapped logarithmically (roughness alpha from 1e-3 to 1 is the
usual case), so that the optimiser's steps are relative where the physics is.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gonio.core.channels import CHANNELS, RGB

__all__ = ["ParameterSpace"]


@dataclasses.dataclass(frozen=True)
class _Entry:
    name: str          # display name, e.g. "diffuse_reflectance[R]"
    param: str         # model parameter name
    channel: int       # channel index, or -1 for a shared parameter
    lower: float
    upper: float
    log: bool
    unit: str


class ParameterSpace:
    """Flatten a model's parameters into a vector and back.

    Parameters
    ----------
    model
        A gonio model (see docs/interfaces.md section 2).
    n_channels : int
        Channels of the data (:data:`gonio.core.channels.CHANNELS` for RGB).
    fixed : dict, optional
        Parameters held at a given value rather than fitted.
    """

    def __init__(self, model, n_channels: int = CHANNELS, fixed: dict | None = None, channels=None):
        self.model = model
        self.n_channels = int(n_channels)
        self.channels = tuple(channels or (RGB.names + ("A",))[: self.n_channels])
        self.fixed = dict(fixed or {})
        entries = []
        for p in model.parameters:
            if p.name in self.fixed:
                continue
            lower, upper = float(p.lower), float(p.upper)
            use_log = lower > 0 and upper / lower > 100.0
            if p.per_channel:
                for c in range(self.n_channels):
                    entries.append(_Entry(f"{p.name}[{self.channels[c]}]", p.name, c, lower, upper, use_log, p.unit))
            else:
                entries.append(_Entry(p.name, p.name, -1, lower, upper, use_log, p.unit))
        self.entries = tuple(entries)
        self.lower = np.array([e.lower for e in entries])
        self.upper = np.array([e.upper for e in entries])
        self._log = np.array([e.log for e in entries], dtype=bool)

    # ------------------------------------------------------------------ sizes and names
    @property
    def size(self) -> int:
        return len(self.entries)

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.entries]

    # ------------------------------------------------------------------ vector <-> dict
    def to_params(self, x) -> dict:
        """Natural-unit vector -> the model's params dict (per-channel values as (C,) arrays)."""
        x = np.asarray(x, dtype=np.float64)
        params: dict = {}
        for p in self.model.parameters:
            if p.name in self.fixed:
                params[p.name] = self.fixed[p.name]
            elif p.per_channel:
                params[p.name] = np.zeros(self.n_channels)
        for value, e in zip(x, self.entries):
            if e.channel >= 0:
                params[e.param][e.channel] = value
            else:
                params[e.param] = float(value)
        return params

    def from_params(self, params: dict) -> np.ndarray:
        """The model's params dict -> natural-unit vector."""
        return np.array([_pick(params[e.param], e.channel) for e in self.entries])

    def default(self) -> np.ndarray:
        """The declared defaults as a natural-unit vector."""
        return np.array([_pick(p.default, e.channel)
                         for e in self.entries
                         for p in self.model.parameters if p.name == e.param])

    # ------------------------------------------------------------------ unit box
    def to_unit(self, x) -> np.ndarray:
        x = np.clip(np.asarray(x, dtype=np.float64), self.lower, self.upper)
        lo, hi = self.lower, self.upper
        with np.errstate(divide="ignore", invalid="ignore"):
            u_log = (np.log(np.where(self._log, x, 1.0)) - np.log(np.where(self._log, lo, 1.0))) / \
                np.where(self._log, np.log(hi / np.where(self._log, lo, 1.0)), 1.0)
        u_lin = (x - lo) / np.where(hi > lo, hi - lo, 1.0)
        return np.clip(np.where(self._log, u_log, u_lin), 0.0, 1.0)

    def from_unit(self, u) -> np.ndarray:
        u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
        lo, hi = self.lower, self.upper
        safe_lo = np.where(self._log, lo, 1.0)
        x_log = safe_lo * np.power(np.where(self._log, hi / safe_lo, 1.0), u)
        x_lin = lo + u * (hi - lo)
        return np.where(self._log, x_log, x_lin)

    def dx_du(self, x) -> np.ndarray:
        """d x / d u at x, per coordinate: hi - lo (linear), x ln(hi / lo) (logarithmic)."""
        lo, hi = self.lower, self.upper
        safe_lo = np.where(self._log, lo, 1.0)
        return np.where(self._log, np.asarray(x, dtype=np.float64) * np.log(np.where(self._log, hi / safe_lo, 1.0)),
                        hi - lo)

    def at_bound(self, x, rtol: float = 1e-6) -> np.ndarray:
        u = self.to_unit(x)
        return (u <= rtol) | (u >= 1.0 - rtol)


def _pick(value, channel: int) -> float:
    """One channel of a per-channel value, or the value itself where it is shared."""
    flat = np.asarray(value, dtype=np.float64).reshape(-1)
    return float(flat[channel] if (channel >= 0 and flat.size > 1) else flat[0])
