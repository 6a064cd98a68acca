"""The sides of a measurement, declared once: reflection (a BRDF) and transmission (a BTDF).

Light arrives on the lit face (+z, cos(theta_i) > 0). It leaves on the same face (reflection,
theta_o in [0, 90) deg) or through the surface (transmission, theta_o in (90, 180] deg). Every
horizon mask, angle check and side label in gonio reads this declaration: a model declares
the sides it scatters into (``Structure.sides``), a plan and a dataset the sides they hold.
The masks work on numpy and Dr.Jit arrays alike (they use only comparisons and ``&``/``|``).
"""

from __future__ import annotations

import enum
from typing import Iterable

import numpy as np

__all__ = ["Side", "REFLECTION_ONLY", "sides_mask", "side_of", "parse_sides"]


class Side(enum.Enum):
    """Where light leaves the surface, seen from the lit face (+z)."""

    REFLECT = "reflect"
    TRANSMIT = "transmit"

    @property
    def theta_o_deg(self) -> tuple[float, float]:
        """The half-open range of theta_o (deg) this side holds: [0, 90) or (90, 180]."""
        return (0.0, 90.0) if self is Side.REFLECT else (90.0, 180.0)

    @property
    def quantity(self) -> str:
        """The distribution function measured on this side (its CF long name's subject)."""
        return ("bidirectional reflectance distribution function" if self is Side.REFLECT
                else "bidirectional transmittance distribution function")

    def mask(self, cos_i, cos_o, eps: float = 0.0):
        """Pairs on this side: the light on the lit face and the detector on this side's face,
        both more than ``eps`` from the surface plane. numpy or Dr.Jit arrays."""
        if self is Side.REFLECT:
            return (cos_i > eps) & (cos_o > eps)
        return (cos_i > eps) & (cos_o < -eps)

    def holds_theta_o(self, theta_o_deg) -> np.ndarray:
        """Whether each theta_o (deg) lies on this side (the surface plane on neither)."""
        t = np.asarray(theta_o_deg, dtype=float)
        return (t >= 0.0) & (t < 90.0) if self is Side.REFLECT else (t > 90.0) & (t <= 180.0)


#: What every gonio model and measurement holds until it says otherwise.
REFLECTION_ONLY: tuple[Side, ...] = (Side.REFLECT,)


def sides_mask(sides: Iterable[Side], cos_i, cos_o, eps: float = 0.0):
    """Pairs on any of ``sides`` (see :meth:`Side.mask`)."""
    sides = tuple(sides)
    if not sides:
        raise ValueError("a model or measurement holds at least one side")
    m = sides[0].mask(cos_i, cos_o, eps)
    for s in sides[1:]:
        m = m | s.mask(cos_i, cos_o, eps)
    return m


def side_of(cos_i, cos_o) -> np.ndarray:
    """The side of each pair as an int array: 0 reflection, 1 transmission, -1 neither (the
    light not on the lit face, or either direction in the surface plane)."""
    cos_i, cos_o = np.asarray(cos_i, dtype=float), np.asarray(cos_o, dtype=float)
    out = np.full(np.broadcast(cos_i, cos_o).shape, -1, dtype=np.int8)
    out[Side.REFLECT.mask(cos_i, cos_o)] = 0
    out[Side.TRANSMIT.mask(cos_i, cos_o)] = 1
    return out


def parse_sides(value, where: str) -> tuple[Side, ...]:
    """Sides from a file's value (``"reflect"``, ``["reflect", "transmit"]``); ValueError naming
    ``where`` and the accepted spellings otherwise."""
    if isinstance(value, np.ndarray):             # a NetCDF attribute's list comes back as an array
        value = value.tolist()
    items = [value] if isinstance(value, str) else value
    if not isinstance(items, (list, tuple)) or not items:
        raise ValueError(f"{where}: sides must be 'reflect', 'transmit' or a list of them")
    out = []
    for v in items:
        try:
            s = Side(v)
        except ValueError:
            raise ValueError(f"{where}: unknown side {str(v)[:40]!r}; give 'reflect' or 'transmit'") from None
        if s not in out:
            out.append(s)
    return tuple(out)
