"""The channels a measurement carries, declared once: every layer reads them from here.

A :class:`Channels` names the values of every f_r, parameter and uncertainty: three colour
channels in a colour space (linear camera RGB, sRGB, CIE XYZ), or a list of wavelengths (a
spectral measurement). It says how a value goes to Mitsuba (an ``rgb`` or a ``spectrum``),
which Mitsuba variant renders it and what dataset.nc's channel coordinate holds. Today every
measurement is :data:`RGB`; a spectral one changes this declaration, not the layers that read
it (docs/architecture.md, "What each coming capability touches").
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from dataclasses import dataclass

__all__ = ["Channels", "RGB", "CHANNELS", "COLOUR_SPACE_CHANNELS", "LUMINANCE", "SRGB_Y", "colour_space",
           "spectral", "current", "use", "of_values", "from_attrs"]


@dataclass(frozen=True)
class Channels:
    """The channels of one measurement.

    Attributes
    ----------
    names : tuple of str
        One label per channel (``("R", "G", "B")``, or ``"550nm"`` per wavelength).
    space : str
        ``"camera"``, ``"srgb"``, ``"xyz"`` or ``"spectral"``.
    wavelengths_nm : tuple of float, optional
        The wavelength of each channel (spectral only), strictly increasing.
    """

    names: tuple[str, ...]
    space: str
    wavelengths_nm: tuple[float, ...] | None = None

    def __post_init__(self):
        if not self.names:
            raise ValueError("a measurement has at least one channel")
        if self.space == "spectral":
            w = self.wavelengths_nm or ()
            if len(w) != len(self.names) or not all(math.isfinite(x) and 200.0 <= x <= 2500.0 for x in w) \
                    or any(b <= a for a, b in zip(w, w[1:])):
                raise ValueError("spectral channels need one finite wavelength per channel, increasing, in "
                                 "200-2500 nm")
        elif self.wavelengths_nm is not None:
            raise ValueError(f"{self.space} channels have no wavelengths")

    @property
    def n(self) -> int:
        """The number of channels."""
        return len(self.names)

    @property
    def is_spectral(self) -> bool:
        return self.space == "spectral"

    @property
    def variant_suffix(self) -> str:
        """The colour mode of the Mitsuba variants that render these channels."""
        return "spectral" if self.is_spectral else "rgb"

    def mitsuba(self, value) -> dict:
        """``value`` (one per channel) as a Mitsuba 3 property: ``{"type": "rgb", ...}`` or an
        irregular ``spectrum`` of (wavelength, value) pairs."""
        v = [float(x) for x in value]
        if len(v) != self.n:
            raise ValueError(f"{len(v)} values for {self.n} channels")
        if self.is_spectral:
            return {"type": "spectrum", "value": list(zip(self.wavelengths_nm, v))}
        return {"type": "rgb", "value": v}


#: The measurement's channels today: linear camera RGB.
RGB = Channels(("R", "G", "B"), "camera")

#: Number of channels of every f_r value, parameter and uncertainty.
CHANNELS = RGB.n

#: The channels of each colour space a dataset may be fitted in.
_SPACES = {space: Channels(names, space) for space, names in
           (("srgb", ("R", "G", "B")), ("xyz", ("X", "Y", "Z")), ("camera", ("R", "G", "B")))}

#: The channel names of each colour space a dataset may be fitted in.
COLOUR_SPACE_CHANNELS = {space: c.names for space, c in _SPACES.items()}

#: Y (CIE 1931 luminance) of linear sRGB: the Y row of IEC 61966-2-1's sRGB -> XYZ matrix
SRGB_Y = (0.2126, 0.7152, 0.0722)
#: Y of one value of each colour space's three channels: sRGB's row, camera RGB's taken as sRGB's
#: (its matrix is the dataset's, not known here), Y itself for XYZ
LUMINANCE = {"srgb": SRGB_Y, "camera": SRGB_Y, "xyz": (0.0, 1.0, 0.0)}


def colour_space(name: str) -> Channels:
    """The channels of colour space ``name``; ValueError naming the known spaces otherwise."""
    try:
        return _SPACES[name]
    except KeyError:
        raise ValueError(f"unknown colour space {str(name)[:40]!r}; give one of {', '.join(_SPACES)}") from None


def spectral(wavelengths_nm) -> Channels:
    """Channels at ``wavelengths_nm`` (a monochromator's steps)."""
    w = tuple(float(x) for x in wavelengths_nm)
    channels = Channels(tuple(f"{x:g}nm" for x in w), "spectral", w)
    _DECLARED.setdefault(channels.n, set()).add(channels)
    return channels


#: The spectral samplings declared so far, by channel count (:func:`of_values`).
_DECLARED: dict = {}


_CURRENT: contextvars.ContextVar = contextvars.ContextVar("gonio_channels", default=None)


def current() -> Channels:
    """The channels values are being exported in (:func:`use`); :data:`RGB` outside one."""
    return _CURRENT.get() or RGB


@contextlib.contextmanager
def use(channels: Channels | None):
    """Within this block, per-channel values go to Mitsuba as ``channels`` say (a spectral fit's
    wavelengths: a ``spectrum``); None keeps the current ones."""
    token = _CURRENT.set(channels if channels is not None else _CURRENT.get())
    try:
        yield current()
    finally:
        _CURRENT.reset(token)


def of_values(value) -> Channels:
    """The channels ``value`` (one number per channel) belongs to: :func:`current` where its
    count matches, :data:`RGB` for three, else the one spectral sampling of that count this
    process has declared (:func:`spectral`); ValueError where there is none or several."""
    n = len(value)
    c = current()
    if n == c.n:
        return c
    if n == RGB.n:
        return RGB
    if len(_DECLARED.get(n, ())) == 1:      # the one spectral sampling of that many wavelengths declared
        return next(iter(_DECLARED[n]))
    raise ValueError(f"{n} per-channel values and no wavelengths for them: export a spectral fit within "
                     "gonio.core.channels.use(spectral(wavelengths))")


def from_attrs(wavelengths) -> Channels | None:
    """``spectral(wavelengths)`` where a fit file or a dataset states them (nm), else None."""
    return spectral(wavelengths) if wavelengths else None
