"""Exchange formats of the field: MERL ``.binary``, RGL ``.bsdf``, Mitsuba XML, PAB-Opto text, CSV.

Mitsuba XML snippets and files are in :mod:`.mitsuba_xml`, Radiance's PAB-Opto text (for
``pabopto2bsdf``) in :mod:`.pabopto`. MERL ``.binary`` follows Matusik, Pfister, Brand &
McMillan, "A Data-Driven Reflectance Model", ACM TOG 22(3), 2003, and the conventions of the
MERL distribution's ``BRDFRead.cpp``: Rusinkiewicz half/difference angles, isotropic and
reciprocal, a 90 x 90 x 180 grid, f_r = stored value * a per-channel scale, negative = no data.

gonio's direction convention (docs/interfaces.md): ``wi`` toward the light, ``wo`` toward the
detector, f_r without the cosine, (N, 3) per channel. MERL's "in" vector is the light, i.e.
gonio's ``wi``; with reciprocity folded in, swapping wi and wo lands in the same bin.
"""

# MERL .binary in detail (this module's own code was written from BRDFRead.cpp's conventions):
# - Rusinkiewicz half/difference angles: the half vector h = normalize(wi + wo) gives
#   (theta_h, phi_h); wi rotated by -phi_h about the normal and then by -theta_h about the
#   binormal gives the difference vector's (theta_d, phi_d). Isotropic: phi_h is dropped;
#   reciprocity: phi_d is folded onto [0, pi) (phi_d < 0 -> phi_d + pi).
# - Grid 90 (theta_h) x 90 (theta_d) x 180 (phi_d), C order with phi_d fastest:
#   index = i_pd + 180 * (i_td + 90 * i_th).
# - i_th = floor(90 * sqrt(theta_h / (pi/2))) (square-root mapping: fine bins near the
#   specular peak); i_td = floor(90 * theta_d / (pi/2)); i_pd = floor(180 * phi_d / pi);
#   each clamped to the grid, theta_h <= 0 maps to 0.
# - File: three int32 (90, 90, 180), then 90*90*180 float64 for red, the same for green, then
#   blue, little-endian. f_r = stored * scale with scale = 1/1500, 1.15/1500, 1.66/1500 for
#   R, G, B. A negative stored value means "no data" (e.g. below the horizon).

from __future__ import annotations

import csv
import math
import struct
from pathlib import Path

import numpy as np

from gonio.core.geometry import angles_deg as _angles_deg
from gonio.models.mitsuba import divide_cos, eval_cos, quarter_turns, select_variant, turn

from gonio.fitting.measurements import Measurements, load_dataset
from gonio.fitting.formats.mitsuba_xml import (MITSUBA_XML_VERSION, mitsuba_document, mitsuba_snippet,
                                               write_mitsuba_dict, write_mitsuba_document)
from gonio.fitting.formats.native import NativeBSDF, native_bsdf
from gonio.fitting.formats.readback import ExportError, expect, written
from gonio.fitting.formats.pabopto import PaboptoExport, export_pabopto, model_pabopto, pabopto_files, write_pabopto
from gonio.fitting.formats.pabopto import write_files as write_pabopto_files

__all__ = [
    "MERL_SCALE", "MERL_SHAPE", "MerlBRDF", "RGLBRDF", "dataset_to_csv", "dataset_to_merl", "half_diff_angles",
    "merl_bin_directions", "merl_to_measurements", "mitsuba_document", "mitsuba_snippet", "MITSUBA_XML_VERSION",
    "read_merl", "resample_to_merl", "model_pabopto", "pabopto_files", "write_pabopto", "write_pabopto_files",
    "rgl_measurements", "write_merl", "check_rgl_file", "ExportError", "PaboptoExport", "export_pabopto",
    "write_mitsuba_document", "write_mitsuba_dict", "NativeBSDF", "native_bsdf",
]

#: Grid size (theta_h, theta_d, phi_d) of a MERL table.
MERL_SHAPE = (90, 90, 180)
#: f_r = stored value * scale, per channel R, G, B (BRDFRead.cpp's RED/GREEN/BLUE_SCALE).
MERL_SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
#: A MERL file's colour channels (R, G, B: the format's, whatever gonio measures)
_MERL_RGB = len(MERL_SCALE)
_HALF_PI = 0.5 * math.pi


# ---------------------------------------------------------------------------------------
# Half/difference angles and the MERL index mapping
# ---------------------------------------------------------------------------------------
def half_diff_angles(wi, wo):
    """Rusinkiewicz angles (theta_h, phi_h, theta_d, phi_d), radians, of direction pairs.

    ``wi`` (toward the light) is the vector rotated into the half-vector frame, as MERL does
    with its "in" vector. phi_d is in (-pi, pi] (not folded).
    """
    wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
    wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
    h = wi + wo
    norm = np.linalg.norm(h, axis=1)
    norm = np.where(norm > 0, norm, 1.0)
    h = h / norm[:, None]
    theta_h = np.arccos(np.clip(h[:, 2], -1.0, 1.0))
    phi_h = np.arctan2(h[:, 1], h[:, 0])
    # rotate wi by -phi_h about z (the normal) ...
    c, s = np.cos(phi_h), np.sin(phi_h)
    x = c * wi[:, 0] + s * wi[:, 1]
    y = -s * wi[:, 0] + c * wi[:, 1]
    z = wi[:, 2]
    # ... then by -theta_h about y (the binormal)
    c, s = np.cos(theta_h), np.sin(theta_h)
    dx = c * x - s * z
    dz = s * x + c * z
    theta_d = np.arccos(np.clip(dz, -1.0, 1.0))
    phi_d = np.arctan2(y, dx)
    return theta_h, phi_h, theta_d, phi_d


def _merl_indices(theta_h, theta_d, phi_d):
    """Flat MERL table index per configuration (BRDFRead.cpp's mapping, vectorised)."""
    th = np.floor(90.0 * np.sqrt(np.clip(theta_h, 0.0, None) / _HALF_PI))
    i_th = np.clip(th, 0, MERL_SHAPE[0] - 1).astype(np.int64)
    i_td = np.clip(np.floor(theta_d / _HALF_PI * MERL_SHAPE[1]), 0, MERL_SHAPE[1] - 1).astype(np.int64)
    pd = np.where(phi_d < 0.0, phi_d + math.pi, phi_d)  # reciprocity: phi_d and phi_d + pi agree
    i_pd = np.clip(np.floor(pd / math.pi * MERL_SHAPE[2]), 0, MERL_SHAPE[2] - 1).astype(np.int64)
    return i_pd + MERL_SHAPE[2] * (i_td + MERL_SHAPE[1] * i_th)


def merl_bin_directions():
    """Directions (wi, wo), each (90*90*180, 3), at the centre of every MERL bin, flat order.

    The centre is taken in index space: theta_h = ((i + 1/2) / 90)^2 pi/2,
    theta_d = (j + 1/2) / 90 pi/2, phi_d = (k + 1/2) / 180 pi, phi_h = 0. Looking a centre
    up gives back its own bin. Pairs with a direction below the horizon are included (the
    caller masks them).
    """
    i = (np.arange(MERL_SHAPE[0]) + 0.5) / MERL_SHAPE[0]
    theta_h = i * i * _HALF_PI
    theta_d = (np.arange(MERL_SHAPE[1]) + 0.5) / MERL_SHAPE[1] * _HALF_PI
    phi_d = (np.arange(MERL_SHAPE[2]) + 0.5) / MERL_SHAPE[2] * math.pi
    th, td, pd = np.meshgrid(theta_h, theta_d, phi_d, indexing="ij")
    th, td, pd = th.ravel(), td.ravel(), pd.ravel()
    # difference vector in the half-vector frame, then rotated by +theta_h about y
    dx, dy, dz = np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)
    c, s = np.cos(th), np.sin(th)
    wi = np.stack([c * dx + s * dz, dy, -s * dx + c * dz], axis=1)
    h = np.stack([s, np.zeros_like(s), c], axis=1)
    wo = 2.0 * np.sum(wi * h, axis=1, keepdims=True) * h - wi  # mirror of wi about h
    return wi, wo


# ---------------------------------------------------------------------------------------
# MERL tables
# ---------------------------------------------------------------------------------------
class MerlBRDF:
    """A MERL table: stored values and their evaluation as f_r.

    Parameters
    ----------
    raw : array_like, shape (3, 90, 90, 180)
        The values as the file stores them (f_r / scale; negative = no data). Kept as
        given, so ``read_merl`` -> ``write_merl`` is byte-identical.
    path : str, optional
        Where it came from (provenance only).
    """

    def __init__(self, raw, path=None):
        raw = np.asarray(raw, dtype=np.float64)
        if raw.shape != (_MERL_RGB, *MERL_SHAPE):
            raise ValueError(f"a MERL table has shape (3, 90, 90, 180), got {raw.shape}")
        self.raw = raw
        self.path = None if path is None else str(path)

    @classmethod
    def from_brdf(cls, table, path=None) -> "MerlBRDF":
        """From f_r values (3, 90, 90, 180) in sr^-1; NaN or negative = no data (stored -1)."""
        table = np.asarray(table, dtype=np.float64)
        if table.shape != (_MERL_RGB, *MERL_SHAPE):
            raise ValueError(f"a MERL table has shape (3, 90, 90, 180), got {table.shape}")
        raw = table / MERL_SCALE[:, None, None, None]
        raw[~np.isfinite(raw) | (raw < 0)] = -1.0
        return cls(raw, path)

    @property
    def table(self) -> np.ndarray:
        """f_r (3, 90, 90, 180), sr^-1 (stored * scale; negative where there is no data)."""
        return self.raw * MERL_SCALE[:, None, None, None]

    @property
    def valid(self) -> np.ndarray:
        """Bins with data in every channel, (90, 90, 180) bool."""
        return np.all(self.raw >= 0, axis=0)

    def indices(self, wi, wo) -> np.ndarray:
        """Flat bin index of each (wi, wo) pair, shape (N,)."""
        theta_h, _, theta_d, phi_d = half_diff_angles(wi, wo)
        return _merl_indices(theta_h, theta_d, phi_d)

    def has_data(self, wi, wo) -> np.ndarray:
        """True where both directions are above the horizon and the bin holds data, (N,)."""
        wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
        wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
        up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        return up & self.valid.reshape(-1)[self.indices(wi, wo)]

    def eval(self, wi, wo, missing: float = np.nan) -> np.ndarray:
        """f_r (N, 3) by nearest-bin look-up (MERL's own mapping, no interpolation).

        0 where either direction is at or below the horizon; ``missing`` (NaN by default)
        in bins without data.
        """
        wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
        wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
        idx = self.indices(wi, wo)
        raw = self.raw.reshape(_MERL_RGB, -1)[:, idx].T
        out = raw * MERL_SCALE
        out[np.any(raw < 0, axis=1)] = missing
        out[(wi[:, 2] <= 0) | (wo[:, 2] <= 0)] = 0.0
        return out

    def write(self, path) -> Path:
        return write_merl(path, self)

    def __repr__(self):
        return f"MerlBRDF(path={self.path!r}, valid bins={int(self.valid.sum())}/{int(np.prod(MERL_SHAPE))})"


def read_merl(path) -> MerlBRDF:
    """Read a MERL ``.binary`` file.

    Raises
    ------
    ValueError
        When the header's dimensions are not 90 x 90 x 180 or the file is truncated.
    """
    path = Path(path)
    n = int(np.prod(MERL_SHAPE))
    size = path.stat().st_size
    if size != 12 + 3 * n * 8:          # checked before reading: a huge file is never loaded
        raise ValueError(f"{path}: {size} bytes, a MERL file has {12 + 3 * n * 8}")
    data = path.read_bytes()
    if len(data) < 12:
        raise ValueError(f"{path}: too short for a MERL header ({len(data)} bytes)")
    dims = tuple(int(d) for d in np.frombuffer(data[:12], dtype="<i4"))
    if dims != MERL_SHAPE:
        raise ValueError(f"{path}: MERL dimensions {dims}, expected {MERL_SHAPE}")
    n = int(np.prod(MERL_SHAPE))
    expected = 12 + 3 * n * 8
    if len(data) != expected:
        raise ValueError(f"{path}: {len(data)} bytes, a MERL file has {expected}")
    raw = np.frombuffer(data[12:], dtype="<f8").astype(np.float64).reshape(_MERL_RGB, *MERL_SHAPE)
    return MerlBRDF(raw, path)


def write_merl(path, table) -> Path:
    """Write a MERL ``.binary`` file atomically (temporary file in the same folder, rename),
    after reading it back: it must hold every value, else ``ExportError`` and nothing written.

    ``table`` is a :class:`MerlBRDF` (its stored values are written unchanged) or f_r values
    of shape (3, 90, 90, 180) in sr^-1 (divided by the scale factors; NaN/negative -> -1).
    """
    merl = table if isinstance(table, MerlBRDF) else MerlBRDF.from_brdf(table)
    path = Path(path)

    def write(tmp):
        with open(tmp, "wb") as fh:
            fh.write(np.asarray(MERL_SHAPE, dtype="<i4").tobytes())
            fh.write(np.ascontiguousarray(merl.raw, dtype="<f8").tobytes())

    def check(tmps):
        back = read_merl(tmps[path])
        expect("MERL bins with data", int(merl.valid.sum()), int(back.valid.sum()))
        same = np.array_equal(back.raw, merl.raw, equal_nan=True)
        expect("MERL values read back", merl.raw.size, merl.raw.size if same else int(np.sum(back.raw == merl.raw)))

    written({path: write}, check)
    return path


def resample_to_merl(eval_fn, params=None, *, chunk: int = 200_000) -> MerlBRDF:
    """Fill a MERL table from any f_r function.

    Parameters
    ----------
    eval_fn : callable or gonio.models.Model
        ``eval_fn(wi, wo) -> (N, 3)`` f_r in sr^-1 (gonio convention), or a model together
        with ``params`` (``model.eval(wi, wo, params)``), or anything with ``.eval(wi, wo)``
        (a :class:`MerlBRDF`, an :class:`RGLBRDF`).
    params : dict, optional
        The model's parameters.

    Each bin gets the value at its centre (:func:`merl_bin_directions`). Bins whose centre
    has a direction at or below the horizon, or where the function returns NaN, are stored
    as -1 (no data). Finite negative values (measured data after colour conversion) are
    clipped to 0, since MERL reads negative as "no data".
    """
    if params is not None:
        model = eval_fn

        def fn(wi, wo):
            return model.eval(wi, wo, params)
    elif not callable(eval_fn) and hasattr(eval_fn, "eval"):  # MerlBRDF, RGLBRDF
        fn = eval_fn.eval
    else:
        fn = eval_fn
    wi, wo = merl_bin_directions()
    n = wi.shape[0]
    up = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    values = np.full((n, _MERL_RGB), np.nan)
    todo = np.flatnonzero(up)
    for start in range(0, todo.size, chunk):
        sel = todo[start:start + chunk]
        f = np.asarray(fn(wi[sel], wo[sel]), dtype=np.float64)
        values[sel] = np.broadcast_to(f.reshape(sel.size, -1), (sel.size, _MERL_RGB))
    bad = ~np.isfinite(values)
    values = np.where(bad, np.nan, np.clip(values, 0.0, None))
    return MerlBRDF.from_brdf(values.T.reshape(_MERL_RGB, *MERL_SHAPE))


def dataset_to_merl(meas) -> MerlBRDF:
    """Bin measured f_r into the MERL grid: the inverse-variance mean of the points falling in
    each bin; bins without a point are marked no-data (-1), nothing is interpolated.

    A MERL table holds 1.46 million bins, so a capture of a few thousand points fills a few
    thousand of them: the file is an exchange format for what was measured, and tools that
    read it must honour MERL's negative = no-data convention.
    """
    use = np.all(meas.use, axis=1) & (meas.wi[:, 2] > 0) & (meas.wo[:, 2] > 0)
    theta_h, _, theta_d, phi_d = half_diff_angles(meas.wi[use], meas.wo[use])
    idx = _merl_indices(theta_h, theta_d, phi_d)
    n_bins = int(np.prod(MERL_SHAPE))
    table = np.full((_MERL_RGB, n_bins), np.nan)
    for c in range(_MERL_RGB):
        w = 1.0 / meas.brdf_std[use, c] ** 2
        wsum = np.bincount(idx, weights=w, minlength=n_bins)
        fsum = np.bincount(idx, weights=w * meas.brdf[use, c], minlength=n_bins)
        hit = wsum > 0
        table[c, hit] = np.maximum(fsum[hit] / wsum[hit], 0.0)
    return MerlBRDF.from_brdf(table.reshape(_MERL_RGB, *MERL_SHAPE))


def merl_to_measurements(merl, wi=None, wo=None, *, n: int | None = None, rng=None, rel_std: float = 0.01,
                         floor: float = 1e-4) -> Measurements:
    """Sample a MERL table as :class:`Measurements`, so it can be fitted with gonio.fitting.

    Parameters
    ----------
    merl : MerlBRDF or path
    wi, wo : array_like (N, 3), optional
        Where to sample (nearest-bin look-up). By default the centres of all bins with data.
    n : int, optional
        Keep a random subset of ``n`` points (``rng``: seed or Generator).
    rel_std, floor : float
        The 1-sigma given to each value: ``rel_std * max(|f_r|, floor)``. MERL files carry
        no uncertainty, so this sets the weighting of the fit (relative by default).

    Points without data (or below the horizon) are kept with ``use = False`` and f_r = 0.
    """
    if not isinstance(merl, MerlBRDF):
        merl = read_merl(merl)
    if (wi is None) != (wo is None):
        raise ValueError("give both wi and wo, or neither")
    if wi is None:
        wi, wo = merl_bin_directions()
        keep = merl.valid.reshape(-1) & (wi[:, 2] > 0) & (wo[:, 2] > 0)
        wi, wo = wi[keep], wo[keep]
    else:
        wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
        wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
    if n is not None and n < wi.shape[0]:
        idx = np.sort(np.random.default_rng(rng).choice(wi.shape[0], size=n, replace=False))
        wi, wo = wi[idx], wo[idx]
    ok = merl.has_data(wi, wo)
    f = merl.eval(wi, wo, missing=0.0)
    f[~ok] = 0.0
    std = rel_std * np.maximum(np.abs(f), floor)
    use = np.repeat(ok[:, None], 3, axis=1)
    attrs = {"source": "MERL", "path": merl.path or "", "rel_std": rel_std, "floor": floor}
    return Measurements(wi, wo, f, std, use, attrs)


# ---------------------------------------------------------------------------------------
# RGL .bsdf (through Mitsuba's `measured` plugin)
# ---------------------------------------------------------------------------------------
#: the tensor file's dtype codes (Mitsuba's Struct types: u8 i8 u16 i16 u32 i32 u64 i64 f16 f32
#: f64) as little-endian numpy dtypes, and their element sizes
_TENSOR_DTYPES = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<u8", 8: "<i8", 9: "<f2", 10: "<f4", 11: "<f8"}
_TENSOR_DTYPE_SIZE = {code: np.dtype(d).itemsize for code, d in _TENSOR_DTYPES.items()}
#: fields Mitsuba's ``measured`` plugin reads (besides rgb, or spectra and wavelengths)
_RGL_FIELDS = ("theta_i", "phi_i", "ndf", "sigma", "vndf", "luminance", "description", "jacobian")
_RGL_MAX_BYTES = 1 << 30


def check_rgl_file(path) -> dict:
    """Check an RGL-EPFL ``.bsdf`` tensor file's structure in Python, before Mitsuba reads it.

    The header, every field's name, dtype, shape and byte range must be well formed and lie
    inside the file, and the fields the ``measured`` plugin needs must be there (float32
    where they are numbers). Returns ``{name: (dtype code, shape, byte offset)}``.

    Raises
    ------
    ValueError
        With one line saying what is wrong.
    """
    path = Path(path)
    size = path.stat().st_size
    if size > _RGL_MAX_BYTES:
        raise ValueError(f"{path}: {size} bytes, more than an RGL .bsdf file holds ({_RGL_MAX_BYTES} at most)")
    with open(path, "rb") as fh:
        head = fh.read(min(size, 1 << 16))
    if not head.startswith(b"tensor_file\x00"):
        raise ValueError(f"{path} is not an RGL-EPFL tensor .bsdf file (bad header)")
    fields = {}
    try:
        pos = 12
        major, minor = head[pos], head[pos + 1]
        (count,) = struct.unpack_from("<I", head, pos + 2)
        pos += 6
        if (major, minor) != (1, 0) or not 1 <= count <= 64:
            raise ValueError(f"{path}: tensor file version {major}.{minor} with {count} fields is not an RGL .bsdf file")
        for _ in range(count):
            (length,) = struct.unpack_from("<H", head, pos)
            name = head[pos + 2:pos + 2 + length].decode("ascii")
            pos += 2 + length
            ndim, dtype, offset = struct.unpack_from("<HBQ", head, pos)
            pos += 11
            if not 0 <= ndim <= 8 or dtype not in _TENSOR_DTYPE_SIZE:
                raise ValueError(f"{path}: field {name!r} has {ndim} dimensions and dtype {dtype}")
            shape = struct.unpack_from(f"<{ndim}Q", head, pos)
            pos += 8 * ndim
            nbytes = _TENSOR_DTYPE_SIZE[dtype] * int(np.prod(shape, dtype=object))
            if offset < pos or offset + nbytes > size:
                raise ValueError(f"{path}: field {name!r} lies outside the file (truncated or damaged)")
            fields[name] = (dtype, tuple(int(d) for d in shape), int(offset))
    except (struct.error, IndexError, UnicodeDecodeError):
        raise ValueError(f"{path}: the tensor file's header is truncated or damaged") from None
    missing = [f for f in _RGL_FIELDS if f not in fields]
    if "rgb" not in fields and not {"spectra", "wavelengths"} <= set(fields):
        missing.append("rgb")
    if missing:
        raise ValueError(f"{path}: not an RGL BSDF measurement (no {', '.join(missing)} field)")
    for name in ("theta_i", "phi_i", "ndf", "sigma", "vndf", "luminance", "rgb", "spectra", "wavelengths"):
        if name in fields and fields[name][0] != 10:
            raise ValueError(f"{path}: field {name!r} is not float32")
    return fields


def rgl_field(path, name: str) -> np.ndarray:
    """One float32 field of a checked RGL ``.bsdf`` file (:func:`check_rgl_file`), as float64."""
    fields = check_rgl_file(path)
    if name not in fields:
        raise ValueError(f"{path}: no {name} field")
    dtype, shape, offset = fields[name]
    if dtype != 10:
        raise ValueError(f"{path}: field {name!r} is not float32")
    with open(path, "rb") as fh:
        fh.seek(offset)
        data = fh.read(4 * int(np.prod(shape, dtype=object)))
    return np.frombuffer(data, dtype="<f4").astype(np.float64).reshape(shape)


class RGLBRDF:
    """An RGL-EPFL ``.bsdf`` file (isotropic RGB) evaluated through Mitsuba's ``measured``.

    ``eval(wi, wo)`` returns f_r (N, 3) in gonio's convention: Mitsuba's ``si.wi`` is set to
    gonio's ``wo`` (sensor side) and the evaluated direction to gonio's ``wi`` (light side);
    ``bsdf.eval`` returns f_r * cos(theta_i), divided out here. Values can be slightly
    negative (the data's colour conversion), as in the file. In an isotropic file (one or two
    phi_i, as Mitsuba decides) each pair is evaluated turned about the normal by
    :func:`~gonio.models.mitsuba.quarter_turns`: the same pair, on which the plugin's
    uninitialised mirroring never applies.
    """

    def __init__(self, path, variant: str | None = None):
        self.path = str(Path(path))
        if not Path(self.path).is_file():
            raise FileNotFoundError(f"RGL BSDF file not found: {self.path}")
        check_rgl_file(self.path)
        self.isotropic = rgl_field(self.path, "phi_i").size <= 2
        self.variant = select_variant(variant)
        import mitsuba as mi

        with mi.scoped_set_variant(self.variant):
            try:
                self._bsdf = mi.load_dict(self.mitsuba_dict())
            except RuntimeError as exc:
                reason = str(exc).rsplit("]", 1)[-1].strip()[:200]
                raise ValueError(f"{self.path}: Mitsuba cannot read it as an RGL .bsdf file ({reason})") from None

    def mitsuba_dict(self) -> dict:
        return {"type": "measured", "filename": self.path}

    def eval_cos(self, wi, wo) -> np.ndarray:
        """f_r * cos(theta_i) (N, 3) as Mitsuba returns it, each pair turned (see the class)."""
        wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
        wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
        k = quarter_turns(wo) if self.isotropic else np.zeros(len(wo), int)
        return eval_cos(self._bsdf, turn(wi, k), turn(wo, k), self.variant)

    def eval(self, wi, wo) -> np.ndarray:
        wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
        wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
        return divide_cos(self.eval_cos(wi, wo), wi, wo)

    def __repr__(self):
        return f"RGLBRDF({self.path!r})"


def rgl_measurements(path, wi, wo, *, rel_std: float = 0.02, floor: float = 1e-4,
                     variant: str | None = None) -> Measurements:
    """f_r of an RGL ``.bsdf`` file at the given directions, as :class:`Measurements`.

    ``brdf_std = rel_std * max(|f_r|, floor)`` (the file carries no uncertainty); pairs with
    a direction at or below the horizon get ``use = False``.
    """
    rgl = RGLBRDF(path, variant)
    wi = np.asarray(wi, dtype=np.float64).reshape(-1, 3)
    wo = np.asarray(wo, dtype=np.float64).reshape(-1, 3)
    f = rgl.eval(wi, wo)
    up = (wi[:, 2] > 1e-9) & (wo[:, 2] > 1e-9)
    std = rel_std * np.maximum(np.abs(f), floor)
    use = np.repeat(up[:, None], 3, axis=1)
    attrs = {"source": "RGL", "path": rgl.path, "rel_std": rel_std, "floor": floor, "variant": rgl.variant,
             "isotropic": True}
    return Measurements(wi, wo, f, std, use, attrs)


# ---------------------------------------------------------------------------------------
# CSV
# ---------------------------------------------------------------------------------------
def dataset_to_csv(meas_or_dataset_path, out_csv) -> Path:
    """Write a dataset (``dataset.nc`` path) or :class:`Measurements` as CSV, atomically.

    One header line names each column with its unit: angles in degrees (``theta_i [deg]``
    ...; i toward the light, o toward the detector, local frame, +z the normal), f_r and
    its 1-sigma in ``1/sr`` per channel, and a 0/1 ``use`` flag per channel (0 = saturated or
    flagged). One row per measured configuration.
    """
    if isinstance(meas_or_dataset_path, Measurements):
        meas = meas_or_dataset_path
        angles = (*_angles_deg(meas.wi), *_angles_deg(meas.wo))
    else:
        path = Path(meas_or_dataset_path)
        meas = load_dataset(path)
        angles = _dataset_angles_deg(path)
        if angles is None:
            angles = (*_angles_deg(meas.wi), *_angles_deg(meas.wo))
    channels = list(meas.channels)[: meas.n_channels]
    header = ["theta_i [deg]", "phi_i [deg]", "theta_o [deg]", "phi_o [deg]"]
    header += [f"brdf_{c} [1/sr]" for c in channels]
    header += [f"brdf_std_{c} [1/sr]" for c in channels]
    header += [f"use_{c} [0/1]" for c in channels]
    out_csv = Path(out_csv)
    rows = []
    for k in range(meas.n_points):
        row = [f"{a[k]:.6f}" for a in angles]
        row += [repr(float(v)) for v in meas.brdf[k]]
        row += [repr(float(v)) for v in meas.brdf_std[k]]
        row += [str(int(u)) for u in meas.use[k]]
        rows.append(row)

    def write(tmp):
        with open(tmp, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            writer.writerows(rows)

    def check(tmps):
        with open(tmps[out_csv], newline="") as fh:
            back = list(csv.reader(fh))
        expect("CSV header", header, back[0] if back else None)
        expect("CSV rows (one per point)", meas.n_points, len(back) - 1)
        expect("CSV values read back", meas.n_points, sum(a == b for a, b in zip(rows, back[1:])))

    written({out_csv: write}, check)
    return out_csv


def _dataset_angles_deg(path):
    """The four angle coordinates of a dataset.nc exactly as stored, in degrees (or None)."""
    import xarray as xr

    try:
        with xr.open_dataset(path, engine="h5netcdf") as ds:
            out = []
            for name in ("theta_i", "phi_i", "theta_o", "phi_o"):
                var = ds[name]
                values = np.asarray(var.values, dtype=np.float64)
                unit = str(var.attrs.get("units", "degree")).lower()
                out.append(values if unit.startswith("deg") else np.degrees(values))
            return tuple(out)
    except (KeyError, OSError, ValueError):
        return None
