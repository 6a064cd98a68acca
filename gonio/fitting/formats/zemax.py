"""Zemax OpticStudio / LightTools tabular BSDF (``.bsdf`` text, "BSDF Data Interchange"): read, write.

A file holds one scatter type (BRDF or BTDF) on a grid: sample rotations, angles of incidence,
scatter azimuths and radial scatter angles measured about the specular direction, one block of
BSDF values (sr^-1) and its TIS per (rotation, incidence) and channel (``Monochrome`` or the three
``TristimulusX/Y/Z`` blocks). :func:`is_zemax_bsdf` tells it from an RGL tensor ``.bsdf`` by
content; :func:`read_zemax` checks every field (one-line :class:`ZemaxError`); :func:`zemax_measurements`
gives gonio's :class:`~gonio.fitting.measurements.Measurements`; :func:`model_zemax` tabulates a
model and :func:`write_zemax` writes tables, each read back and compared value by value first.
Geometry: the module notes below. Reference: R. Rykowski, "Zemax Tabular BSDF data file format"
(Zemax knowledge base article 1500005486801; Radiant Imaging's BSDF Data Interchange format, 2008).
"""

# Geometry, in gonio's frame (+z the normal of the lit face, wi toward the light, wo toward the
# detector, directions.py's phi = atan2(y, x)):
# * SampleRotation rho: the plane of incidence's normal makes the angle rho with +x (the format's
#   definition), so the light lies at azimuth phi_i = rho + 90 deg. Which of the plane's two
#   halves holds the light is this module's choice; it only matters for anisotropic samples.
# * AngleOfIncidence a: wi = (sin a cos phi_i, sin a sin phi_i, cos a). The format's a is the
#   specular angle; gonio reads it as the incidence, i.e. the specular BTDF direction is straight
#   through (-wi), as for a slab or a film (the example in ../shared/data/zemax checks this: its
#   azimuth-0 rows end at radial 90 + a, the 180 deg rows at 90 - a).
# * The pole p of the scatter angles: the mirror direction (BRDF) or -wi (BTDF); azimuth 0 points
#   from p toward the normal axis on p's side, e1 = -+ d p / d theta_p, and azimuth increases
#   toward e2 = p x e1 (counter-clockwise seen from the detector looking at the sample);
#   wo = cos r p + sin r (cos psi e1 + sin psi e2). Radial angles run to 180 deg; grid points on
#   the other side of the surface (or on it) are no data and are left out of the measurements.
# * TIS: integral of f |cos theta_o| over the side, written from the grid (midpoint rule in r and
#   psi); read, checked finite and in [0, 2], and kept in attrs.

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np

from gonio.core.channels import SRGB_Y
from gonio.core.errors import GonioError
from gonio.core.files import text_head
from gonio.core.preflight import check_input_file
from gonio.core.sides import Side
from gonio.fitting.formats.readback import expect, written

__all__ = ["ZemaxError", "ZemaxBSDF", "is_zemax_bsdf", "read_zemax", "zemax_directions", "zemax_measurements",
           "model_zemax", "write_zemax", "export_zemax", "MAX_BYTES", "MAX_VALUES"]

#: The largest file read (bytes) and the most BSDF values a file may declare.
MAX_BYTES = 512 << 20
MAX_VALUES = 1 << 24
#: The most entries an angle list may declare.
_MAX_ANGLES = {"SampleRotation": 360, "AngleOfIncidence": 900, "ScatterAzimuth": 3601, "ScatterRadial": 1801}
#: Angle ranges (deg), closed: rotation [0, 360), incidence [0, 90), azimuth [0, 360], radial [0, 180].
_RANGES = {"SampleRotation": (0.0, 360.0, False), "AngleOfIncidence": (0.0, 90.0, False),
           "ScatterAzimuth": (0.0, 360.0, True), "ScatterRadial": (0.0, 180.0, True)}
_HEADER = ("Source", "Symmetry", "SpectralContent", "ScatterType", "SampleRotation", "AngleOfIncidence",
           "ScatterAzimuth", "ScatterRadial")
_CHOICES = {"Source": ("Measured", "Simulated"), "Symmetry": ("PlaneSymmetrical", "Asymmetrical"),
            "SpectralContent": ("Monochrome", "XYZ"), "ScatterType": ("BRDF", "BTDF")}
_BLOCKS = {"Monochrome": ("Monochrome",), "XYZ": ("TristimulusX", "TristimulusY", "TristimulusZ")}
_NUMBER_CHARS = frozenset("0123456789+-.eE \t")
_F_MAX = 1e10   # sr^-1: as gonio.bench's dataset reader refuses beyond it
_WAVELENGTH = re.compile(r"#\s*wavelength\s*\(nm\)\s*[=:]\s*([0-9.eE+-]+)", re.IGNORECASE)


class ZemaxError(GonioError, ValueError):
    """A Zemax tabular BSDF file that gonio cannot read as it is (one line: where and what)."""


@dataclasses.dataclass
class ZemaxBSDF:
    """One Zemax tabular BSDF file's content.

    Attributes
    ----------
    scatter_type : {"BRDF", "BTDF"}
    symmetry : {"PlaneSymmetrical", "Asymmetrical"}
    spectral : {"Monochrome", "XYZ"}
    rotation, aoi, azimuth, radial : ndarray
        The angle lists (deg), as in the file.
    tis : ndarray, shape (C, R, A)
        Total integrated scatter per channel, rotation and incidence.
    data : ndarray, shape (C, R, A, n_azimuth, n_radial)
        BSDF values (sr^-1).
    comments : list of str
        The ``#`` lines (without the ``#``).
    source : str
    """

    scatter_type: str
    symmetry: str
    spectral: str
    rotation: np.ndarray
    aoi: np.ndarray
    azimuth: np.ndarray
    radial: np.ndarray
    tis: np.ndarray
    data: np.ndarray
    comments: list = dataclasses.field(default_factory=list)
    source: str = "Measured"

    @property
    def side(self) -> Side:
        return Side.REFLECT if self.scatter_type == "BRDF" else Side.TRANSMIT

    @property
    def channels(self) -> tuple:
        if self.spectral == "XYZ":
            return ("X", "Y", "Z")
        wl = self.wavelength_nm
        return (f"{wl:g}nm",) if wl is not None else ("Y",)

    @property
    def wavelength_nm(self):
        """The wavelength a ``# Wavelength (nm) = X`` comment states, or None."""
        for c in self.comments:
            m = _WAVELENGTH.match("#" + c.strip())
            if m:
                try:
                    w = float(m.group(1))
                except ValueError:
                    return None
                return w if math.isfinite(w) and 200.0 <= w <= 2500.0 else None
        return None


# ---------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------
def is_zemax_bsdf(path) -> bool:
    """True when the file's first lines are a Zemax tabular BSDF header (by content: an RGL
    tensor ``.bsdf`` or any other file gives False)."""
    head = text_head(path)
    if head is None:
        return False
    words = []
    for line in head.decode("latin-1").splitlines()[:-1 if len(head) == 1 << 14 else None]:
        s = line.strip()
        if s and not s.startswith("#"):
            words.append(s.split()[0])
        if len(words) >= 4:
            break
    return len(words) >= 4 and words[0] in _HEADER and set(words) <= set(_HEADER)


class _Lines:
    """The file's lines with their numbers, ``#`` comments and blank lines set aside."""

    def __init__(self, path: Path, text: str):
        self.path = path
        self.comments = []
        self.items = []
        for n, line in enumerate(text.splitlines(), 1):
            s = line.strip()
            if s.startswith("#"):
                if not self.items:
                    self.comments.append(s[1:].strip()[:200])
                continue
            if s:
                self.items.append((n, s))
        self.i = 0

    def error(self, n, what) -> ZemaxError:
        return ZemaxError(f"{self.path}: line {n}: {what}")

    def next(self, expecting: str):
        if self.i >= len(self.items):
            last = self.items[-1][0] if self.items else 0
            raise ZemaxError(f"{self.path}: the file ends after line {last} where {expecting} should follow: "
                             "it is truncated; export it again")
        item = self.items[self.i]
        self.i += 1
        return item


def _numbers(lines: _Lines, n: int, s: str, count: int, what: str) -> np.ndarray:
    if not set(s) <= _NUMBER_CHARS:
        bad = next((t for t in s.split() if not set(t) <= _NUMBER_CHARS), s)[:20]
        raise lines.error(n, f"{bad!r} is not a number ({what}); give plain decimal numbers (no NaN or inf)")
    tokens = s.split()
    if len(tokens) != count:
        raise lines.error(n, f"{len(tokens)} values where {what} needs {count}; the counts in the header "
                             "and the data must agree")
    try:
        v = np.array([float(t) for t in tokens])
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))[:20]
        raise lines.error(n, f"{bad!r} is not a number ({what})") from None
    if not np.all(np.isfinite(v)):
        raise lines.error(n, f"a value of {what} overflows (not finite); give finite numbers")
    return v


def _is_float(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def _keyword(lines: _Lines, key: str) -> tuple[int, str]:
    n, s = lines.next(f"the header line {key!r}")
    parts = s.split()
    if parts[0].lower() != key.lower():
        raise lines.error(n, f"{parts[0][:40]!r} where the header line {key!r} belongs; the header is "
                             + ", ".join(_HEADER) + " in this order")
    if len(parts) != 2:
        raise lines.error(n, f"{key} takes one value, found {len(parts) - 1}")
    return n, parts[1]


def _angles(lines: _Lines, key: str, symmetry: str) -> np.ndarray:
    n, value = _keyword(lines, key)
    if not value.isdigit():
        raise lines.error(n, f"{key} needs a count (a positive integer), found {value[:20]!r}")
    count = int(value)
    if not 1 <= count <= _MAX_ANGLES[key]:
        raise lines.error(n, f"{key} count {count} outside 1..{_MAX_ANGLES[key]}")
    n, s = lines.next(f"the {count} values of {key}")
    v = _numbers(lines, n, s, count, key)
    lo, hi, closed = _RANGES[key]
    if key == "ScatterAzimuth" and symmetry == "PlaneSymmetrical":
        hi = 180.0
    if v.min() < lo or (v.max() > hi if closed else v.max() >= hi):
        raise lines.error(n, f"{key} values must lie in [{lo:g}, {hi:g}{']' if closed else ')'} deg")
    if np.any(np.diff(v) <= 0):
        raise lines.error(n, f"{key} values must be strictly increasing")
    return v


def read_zemax(path) -> ZemaxBSDF:
    """Read and check a Zemax tabular BSDF file.

    Raises
    ------
    ZemaxError
        One line naming the file, the line and what to fix: a missing or misspelt header
        keyword, a count outside its bounds (``MAX_VALUES`` values at most), an angle outside
        its range or not increasing, a row with the wrong number of values, a value that is not
        a finite non-negative number (NaN, inf, text), a negative or implausible TIS, a
        truncated file, anything after the last ``DataEnd``, or a symmetry gonio does not read
        (``Asymmetrical4D``).
    """
    try:
        path = check_input_file(path, "Zemax BSDF file", max_bytes=MAX_BYTES)
    except GonioError as exc:
        raise ZemaxError(str(exc)) from None
    raw = path.read_bytes()
    if b"\x00" in raw[: 1 << 16] or not is_zemax_bsdf(path):
        raise ZemaxError(f"{path} is not a Zemax tabular BSDF file (no Source/Symmetry/ScatterType header); "
                         "an RGL .bsdf goes through the rgl reader")
    lines = _Lines(path, raw.decode("latin-1"))
    head = {}
    for key in _HEADER[:4]:
        n, value = _keyword(lines, key)
        if key == "Symmetry" and value.lower() == "asymmetrical4d":
            raise lines.error(n, "Symmetry Asymmetrical4D is not read by gonio; export as Asymmetrical")
        match = [c for c in _CHOICES[key] if c.lower() == value.lower()]
        if not match:
            raise lines.error(n, f"{key} {value[:40]!r} is not one of {', '.join(_CHOICES[key])}")
        head[key] = match[0]
    angles = {key: _angles(lines, key, head["Symmetry"]) for key in _HEADER[4:]}
    rot, aoi, az, rad = (angles[k] for k in _HEADER[4:])
    blocks = _BLOCKS[head["SpectralContent"]]
    size = len(blocks) * rot.size * aoi.size * az.size * rad.size
    if size > MAX_VALUES:
        raise ZemaxError(f"{path}: the header declares {size} BSDF values, more than {MAX_VALUES}; "
                         "give a coarser grid")
    data = np.empty((len(blocks), rot.size, aoi.size, az.size, rad.size))
    tis = np.empty((len(blocks), rot.size, aoi.size))
    for c, name in enumerate(blocks):
        n, s = lines.next(f"the data block {name!r}")
        if s.lower() != name.lower():
            raise lines.error(n, f"{s[:40]!r} where the data block {name!r} begins (SpectralContent "
                                 f"{head['SpectralContent']} has the blocks {', '.join(blocks)})")
        n, s = lines.next("DataBegin")
        if s.lower() != "databegin":
            raise lines.error(n, f"{s[:40]!r} where DataBegin belongs")
        for r in range(rot.size):
            for a in range(aoi.size):
                where = f"rotation {rot[r]:g}, incidence {aoi[a]:g}"
                n, s = lines.next(f"the TIS line of {where}")
                parts = s.split()
                if parts[0].lower() != "tis" or len(parts) != 2:
                    raise lines.error(n, f"{s[:40]!r} where 'TIS value' of {where} belongs (the data hold "
                                         f"{az.size} rows of {rad.size} values per incidence)")
                t = _numbers(lines, n, parts[1], 1, f"the TIS of {where}")[0]
                if not 0.0 <= t <= 2.0:
                    raise lines.error(n, f"TIS {t:g} of {where} outside [0, 2]; it is a fraction of the power")
                tis[c, r, a] = t
                for k in range(az.size):
                    n, s = lines.next(f"row {k + 1} of {az.size} of {where}")
                    v = _numbers(lines, n, s, rad.size, f"a row of {where} (ScatterRadial)")
                    if v.min() < 0.0 or v.max() > _F_MAX:
                        raise lines.error(n, f"a BSDF value of {where} outside [0, {_F_MAX:g}] sr^-1")
                    data[c, r, a, k] = v
        n, s = lines.next("DataEnd")
        if s.lower() != "dataend":
            raise lines.error(n, f"{s[:40]!r} where DataEnd belongs: more rows than the header declares")
    if lines.i < len(lines.items):
        n, s = lines.items[lines.i]
        raise lines.error(n, f"{s[:40]!r} after the last DataEnd; remove it")
    return ZemaxBSDF(head["ScatterType"], head["Symmetry"], head["SpectralContent"], rot, aoi, az, rad, tis, data,
                     lines.comments, head["Source"])


# ---------------------------------------------------------------------------------------------
# Geometry and measurements
# ---------------------------------------------------------------------------------------------
def zemax_directions(scatter_type: str, rotation_deg, aoi_deg, azimuth_deg, radial_deg):
    """(wi, wo), each (R, A, Z, D, 3): the light and detector directions of every grid point
    (module notes), for rotations R, incidences A, azimuths Z and radial angles D (deg)."""
    rho, a, psi, r = (np.radians(np.asarray(x, dtype=float)) for x in (rotation_deg, aoi_deg, azimuth_deg, radial_deg))
    rho, a = rho[:, None, None, None], a[None, :, None, None]
    psi, r = psi[None, None, :, None], r[None, None, None, :]
    phi_i = rho + 0.5 * np.pi
    zero = np.zeros(np.broadcast_shapes(rho.shape, a.shape))
    wi = np.stack(np.broadcast_arrays(np.sin(a) * np.cos(phi_i), np.sin(a) * np.sin(phi_i), np.cos(a) + zero), -1)
    phi_p = phi_i + np.pi
    theta_p = a if scatter_type == "BRDF" else np.pi - a
    p = np.stack(np.broadcast_arrays(np.sin(theta_p) * np.cos(phi_p), np.sin(theta_p) * np.sin(phi_p),
                                     np.cos(theta_p) + zero), -1)
    d_theta = np.stack(np.broadcast_arrays(np.cos(theta_p) * np.cos(phi_p), np.cos(theta_p) * np.sin(phi_p),
                                           -np.sin(theta_p) + zero), -1)
    e1 = -d_theta if scatter_type == "BRDF" else d_theta
    e2 = np.cross(p, e1)
    c, s = np.cos(r)[..., None], np.sin(r)[..., None]
    wo = c * p + s * (np.cos(psi)[..., None] * e1 + np.sin(psi)[..., None] * e2)
    wo = wo / np.linalg.norm(wo, axis=-1, keepdims=True)
    return np.broadcast_to(wi, wo.shape), wo


def zemax_measurements(source, *, rel_std: float = 0.02, floor: float = 1e-4, as_rgb: bool = False):
    """A Zemax file (path) or :class:`ZemaxBSDF` as gonio :class:`Measurements`.

    Every grid point whose detector direction lies on the file's side (above the surface for
    a BRDF, below it for a BTDF, more than 1e-9 from the plane) is one measurement; the others
    are no data. ``brdf_std = rel_std * max(f, floor)`` (the format carries no uncertainty).
    Channels: the file's (``"550nm"`` from a ``# Wavelength (nm) = 550`` comment, else ``"Y"``;
    or X, Y, Z); ``as_rgb=True`` repeats a monochrome value in R, G and B for RGB-only fits.
    ``attrs`` hold the format, the side, the TIS values (as the file states them: a converted
    file's need not equal its table's integral), the comments and how many non-zero values lay
    off the side (``off_side_nonzero``: a grid's cells straddling the horizon).
    """
    from gonio.fitting.measurements import Measurements

    table = source if isinstance(source, ZemaxBSDF) else read_zemax(source)
    wi, wo = zemax_directions(table.scatter_type, table.rotation, table.aoi, table.azimuth, table.radial)
    keep = table.side.mask(wi[..., 2], wo[..., 2], 1e-9).reshape(-1)
    off = int(np.count_nonzero(np.moveaxis(table.data, 0, -1).reshape(-1, table.data.shape[0])[~keep]))
    if not keep.any():
        raise ZemaxError("the Zemax table holds no grid point on its own side of the surface")
    f = np.moveaxis(table.data, 0, -1).reshape(-1, table.data.shape[0])[keep]
    channels = table.channels
    if as_rgb:
        if f.shape[1] != 1:
            raise ZemaxError("as_rgb repeats a monochrome table; this one has X, Y, Z")
        f, channels = np.repeat(f, 3, axis=1), ("R", "G", "B")
    attrs = {"format": "zemax", "scatter_type": table.scatter_type, "sides": [table.side.value],
             "symmetry": table.symmetry, "spectral_content": table.spectral, "tis": table.tis.tolist(),
             "comments": list(table.comments), "off_side_nonzero": off}
    if table.wavelength_nm is not None:
        attrs["wavelength_nm"] = table.wavelength_nm
    std = rel_std * np.maximum(np.abs(f), floor)
    return Measurements(wi.reshape(-1, 3)[keep], wo.reshape(-1, 3)[keep], f, std, np.ones_like(f, dtype=bool),
                        attrs, channels)


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------
#: The default grid of :func:`model_zemax` (deg): the radial angles reach 90 + the largest incidence.
DEFAULT_AOI = np.arange(0.0, 90.0, 5.0)
DEFAULT_AZIMUTH = np.arange(0.0, 360.0, 5.0)
DEFAULT_RADIAL = np.arange(0.0, 181.0, 2.0)
_LUMINANCE = np.array(SRGB_Y)   # Y of linear sRGB (IEC 61966-2-1)


def _edges(v_deg: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Cell edges (rad) about each grid value: halfway between neighbours, the outer ones
    as far out as the inner ones, clipped to [lo, hi] (deg)."""
    v = np.asarray(v_deg, dtype=float)
    if v.size == 1:
        return np.radians([lo, hi])
    mid = 0.5 * (v[1:] + v[:-1])
    return np.radians(np.concatenate([[max(lo, 2 * v[0] - mid[0])], mid, [min(hi, 2 * v[-1] - mid[-1])]]))


def _tis(table: ZemaxBSDF) -> np.ndarray:
    """TIS of each block: every grid value times its cell's solid angle and |cos theta_o|
    (the cell about radial r spans the annulus between its edges: cos(lo) - cos(hi))."""
    wi, wo = zemax_directions(table.scatter_type, table.rotation, table.aoi, table.azimuth, table.radial)
    plane = table.symmetry == "PlaneSymmetrical"
    dpsi = np.diff(_edges(table.azimuth, 0.0, 180.0 if plane else 360.0)) * (2.0 if plane else 1.0)
    e = _edges(table.radial, 0.0, 180.0)
    w = (np.cos(e[:-1]) - np.cos(e[1:]))[None, :] * dpsi[:, None]
    g = np.where(table.side.mask(wi[..., 2], wo[..., 2], 1e-9), np.abs(wo[..., 2]), 0.0) * w
    return np.einsum("craij,raij->cra", table.data, g)


def model_zemax(model, params, scatter_type: str, *, aoi=DEFAULT_AOI, azimuth=DEFAULT_AZIMUTH,
                radial=DEFAULT_RADIAL, spectral: str = "Monochrome", comments=()) -> ZemaxBSDF:
    """Tabulate a gonio model as a Zemax table of one side (rotation 0, isotropic models).

    ``spectral="Monochrome"`` writes the luminance Y of the model's linear sRGB values
    (IEC 61966-2-1 weights); ``"XYZ"`` the three tristimulus blocks. Grid points off the side
    hold 0. The TIS is the grid's midpoint-rule integral.
    """
    from gonio.fitting.formats.pabopto import SRGB_TO_XYZ

    scatter_type = str(scatter_type).upper()
    if scatter_type not in ("BRDF", "BTDF"):
        raise ValueError(f"scatter_type {scatter_type!r}: give BRDF or BTDF")
    rot = np.zeros(1)
    aoi, azimuth, radial = (np.asarray(x, dtype=float) for x in (aoi, azimuth, radial))
    wi, wo = zemax_directions(scatter_type, rot, aoi, azimuth, radial)
    f = model.eval(wi.reshape(-1, 3), wo.reshape(-1, 3), params)
    if spectral == "Monochrome":
        vals = (f @ _LUMINANCE)[None]
    elif spectral == "XYZ":
        vals = (f @ SRGB_TO_XYZ.T).T
    else:
        raise ValueError(f"spectral {spectral!r}: give Monochrome or XYZ")
    data = np.maximum(vals, 0.0).reshape((vals.shape[0],) + wo.shape[:-1])
    table = ZemaxBSDF(scatter_type, "Asymmetrical", spectral, rot, aoi, azimuth, radial,
                      np.zeros(data.shape[:3]), data, [str(c) for c in comments], "Measured")
    table.tis = np.clip(_tis(table), 0.0, 2.0)
    return table


def _format(v: np.ndarray) -> str:
    return "\t".join(repr(float(x)) for x in v)


def _text(table: ZemaxBSDF) -> str:
    out = [f"#{c}" for c in table.comments]
    out += [f"Source  {table.source}", f"Symmetry  {table.symmetry}", f"SpectralContent  {table.spectral}",
            f"ScatterType  {table.scatter_type}"]
    for key, v in zip(_HEADER[4:], (table.rotation, table.aoi, table.azimuth, table.radial)):
        out += [f"{key} {v.size}", _format(v)]
    out.append("")
    for c, name in enumerate(_BLOCKS[table.spectral]):
        out += [name, "DataBegin"]
        for r in range(table.rotation.size):
            for a in range(table.aoi.size):
                out.append(f"TIS {float(table.tis[c, r, a])!r}")
                out += [_format(row) for row in table.data[c, r, a]]
        out.append("DataEnd")
    return "\n".join(out) + "\n"


def _check(table: ZemaxBSDF, got: ZemaxBSDF) -> None:
    for what in ("scatter_type", "symmetry", "spectral", "source"):
        expect(what, getattr(table, what), getattr(got, what))
    for what in ("rotation", "aoi", "azimuth", "radial", "tis", "data"):
        a, b = np.asarray(getattr(table, what)), np.asarray(getattr(got, what))
        expect(f"{what} shape", a.shape, b.shape)
        expect(f"{what} values differing", 0, int(np.count_nonzero(a != b)))


def write_zemax(tables: dict) -> list:
    """Write ``{path: ZemaxBSDF}`` all or nothing, each file read back with :func:`read_zemax`
    and compared angle by angle and value by value (values written as Python's shortest
    round-trip decimal) before it gets its name; returns the paths."""
    for table in tables.values():
        if not np.all(np.isfinite(table.data)) or table.data.min() < 0 or not np.all(np.isfinite(table.tis)):
            raise ZemaxError("a Zemax table to write holds a negative or non-finite value")

    def check(tmps):
        for path, tmp in tmps.items():
            _check(tables[path], read_zemax(tmp))

    return written({Path(p): (lambda tmp, t=t: Path(tmp).write_text(_text(t), encoding="ascii"))
                    for p, t in tables.items()}, check)


def export_zemax(stem, model, params, **grid) -> list:
    """Write a model's BRDF and, where it transmits, its BTDF as ``<stem>_brdf.bsdf`` and
    ``<stem>_btdf.bsdf`` (:func:`model_zemax`'s grid keywords), read back and checked."""
    stem = Path(stem)
    opts = ", ".join(f"{k}={v}" for k, v in model.options.items())
    comments = [f"gonio model {model.name}({opts})",
                "params " + ", ".join(f"{k}={np.round(v, 9).tolist()}" for k, v in model.validate(params).items())]
    tables = {}
    for side in model.structure.sides:
        kind = "BRDF" if side is Side.REFLECT else "BTDF"
        tables[stem.with_name(f"{stem.name}_{kind.lower()}.bsdf")] = model_zemax(model, params, kind, comments=comments, **grid)
    return write_zemax(tables)
