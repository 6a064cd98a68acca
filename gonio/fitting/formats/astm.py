"""ASTM E1392 BRDF text files (Cornell's published spectral BRDFs): detect, read, write.

A file is ``KEY value`` header lines, ``NUM_POINTS n``, ``VARS theta_i,phi_i,theta_s,phi_s,
400nm,...`` and then n comma-separated rows: the four angles in radians (incidence toward the
source, scatter toward the detector, both azimuths in one frame: the specular direction is
phi_s = phi_i + pi), then f_r (sr^-1) at each wavelength. Files are told by content
(:func:`is_astm`), not extension. Read into :class:`Measurements` with one channel per
wavelength (``gonio.core.channels.spectral``); a fit is written back on a file's own geometry
or a standard grid. Read -> write -> read keeps every angle and value; a damaged file gets one
line (:class:`AstmError`) before anything is made.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np

from gonio.core.channels import spectral
from gonio.core.errors import GonioError
from gonio.core.files import text_head
from gonio.core.geometry import directions

from gonio.fitting.measurements import Measurements
from gonio.fitting.formats.readback import expect, written

__all__ = ["AstmBRDF", "AstmError", "astm_measurements", "is_astm", "model_astm", "read_astm", "standard_grid",
           "write_astm"]

#: The four angle columns every file starts with (ASTM E1392's names).
ANGLES = ("theta_i", "phi_i", "theta_s", "phi_s")
#: A file larger than this is no BRDF table (Cornell's are 0.45 MB); checked before reading.
MAX_BYTES = 256 << 20
#: At most this many value columns (wavelengths).
MAX_BANDS = 4096
_BAND = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?)\s*nm\s*$", re.IGNORECASE)


class AstmError(GonioError):
    """A file that is not a well-formed ASTM E1392 BRDF table (one line: what and where)."""


@dataclasses.dataclass
class AstmBRDF:
    """One ASTM E1392 table: angles (radians, (N,) each), wavelengths (nm) and f_r (N, W)."""

    angles: np.ndarray                       # (N, 4): theta_i, phi_i, theta_s, phi_s in radians
    wavelengths: tuple
    values: np.ndarray                       # (N, W) f_r in sr^-1
    header: dict = dataclasses.field(default_factory=dict)     # the other KEY value lines, in order
    path: str | None = None

    @property
    def wi(self) -> np.ndarray:
        """Unit directions toward the source (gonio's ``wi``), (N, 3)."""
        return directions(self.angles[:, 0], self.angles[:, 1])

    @property
    def wo(self) -> np.ndarray:
        """Unit directions toward the detector (gonio's ``wo``), (N, 3)."""
        return directions(self.angles[:, 2], self.angles[:, 3])


def is_astm(path) -> bool:
    """True when the file's head holds an ASTM E1392 ``VARS`` line starting with the four angles."""
    head = text_head(path)
    if head is None:
        return False
    for line in head.decode("latin-1").splitlines():
        key, _, rest = line.strip().partition(" ")
        if key == "VARS":
            return tuple(v.strip().lower() for v in rest.split(",")[:4]) == ANGLES
    return False


def read_astm(path) -> AstmBRDF:
    """Read an ASTM E1392 file; :class:`AstmError` (one line) for anything malformed."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise AstmError(f"cannot read {path}: {exc.strerror or exc}") from None
    if size > MAX_BYTES:
        raise AstmError(f"{path}: {size} bytes, more than an ASTM E1392 BRDF table holds ({MAX_BYTES} at most)")
    text = path.read_bytes()
    if b"\x00" in text:
        raise AstmError(f"{path} is not an ASTM E1392 text file (binary content)")
    lines = text.decode("latin-1").splitlines()
    header, n_points, names, first = {}, None, None, None
    for k, line in enumerate(lines):
        s = line.strip()
        if not s:
            continue
        key, _, rest = s.partition(" ")
        if key == "NUM_POINTS":
            try:
                n_points = int(rest.strip())
            except ValueError:
                raise AstmError(f"{path}:{k + 1}: NUM_POINTS {rest.strip()[:40]!r} is not a whole number") from None
        elif key == "VARS":
            names = [v.strip() for v in rest.split(",")]
            first = k + 1
            break
        else:
            header[key] = rest.strip()
    if names is None:
        raise AstmError(f"{path} is not an ASTM E1392 BRDF file (no VARS line)")
    if n_points is None or n_points < 1:
        raise AstmError(f"{path}: no NUM_POINTS line (or it is below 1) before VARS")
    if tuple(v.lower() for v in names[:4]) != ANGLES:
        raise AstmError(f"{path}: VARS starts {','.join(names[:4])[:60]!r}, not theta_i,phi_i,theta_s,phi_s")
    bands = names[4:]
    if not 1 <= len(bands) <= MAX_BANDS:
        raise AstmError(f"{path}: VARS names {len(bands)} value columns (1 to {MAX_BANDS} wavelengths)")
    wl = []
    for b in bands:
        m = _BAND.match(b)
        if m is None:
            raise AstmError(f"{path}: VARS column {b[:40]!r} is not a wavelength such as 550nm")
        wl.append(float(m.group(1)))
    try:
        channels = spectral(wl)
    except ValueError as exc:
        raise AstmError(f"{path}: wavelengths {wl[0]:g}-{wl[-1]:g} nm: {exc}") from None
    rows = [(k, s) for k, s in ((k, lines[k].strip()) for k in range(first, len(lines))) if s]
    if len(rows) != n_points:
        raise AstmError(f"{path}: NUM_POINTS says {n_points} rows, the file holds {len(rows)} (truncated or damaged)")
    ncol = len(names)
    data = np.empty((n_points, ncol))
    for i, (k, s) in enumerate(rows):
        cells = s.split(",")
        if len(cells) != ncol:
            raise AstmError(f"{path}:{k + 1}: {len(cells)} columns, VARS names {ncol}")
        try:
            data[i] = [float(c) for c in cells]
        except ValueError:
            bad = next(c for c in cells if not _is_float(c))
            raise AstmError(f"{path}:{k + 1}: {bad.strip()[:40]!r} is not a number") from None
        if not np.all(np.isfinite(data[i])):
            raise AstmError(f"{path}:{k + 1}: NaN or inf in a row; fix or drop it")
    angles, values = data[:, :4], data[:, 4:]
    theta = angles[:, [0, 2]]
    if np.any((theta < 0) | (theta > 0.5 * math.pi + 1e-6)):
        i = int(np.argwhere((theta < 0) | (theta > 0.5 * math.pi + 1e-6))[0, 0])
        raise AstmError(f"{path}:{rows[i][0] + 1}: a polar angle outside [0, pi/2] radians (ASTM E1392 angles "
                        "are radians; reflection only)")
    if np.any(np.abs(angles[:, [1, 3]]) > 2 * math.pi + 1e-6):
        i = int(np.argwhere(np.abs(angles[:, [1, 3]]) > 2 * math.pi + 1e-6)[0, 0])
        raise AstmError(f"{path}:{rows[i][0] + 1}: an azimuth beyond 2 pi (ASTM E1392 angles are radians)")
    if np.any(np.abs(values) > 1e10):
        i = int(np.argwhere(np.abs(values) > 1e10)[0, 0])
        raise AstmError(f"{path}:{rows[i][0] + 1}: f_r beyond 1e10 sr^-1 is no measurement")
    return AstmBRDF(angles, channels.wavelengths_nm, values, header, str(path))


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _lines(data: AstmBRDF) -> list[str]:
    header = {k: v for k, v in data.header.items() if k not in ("NUM_POINTS", "VARS")}
    out = [f"{k} {v}".rstrip() for k, v in header.items()]
    out.append(f"NUM_POINTS {data.values.shape[0]}")
    out.append("VARS " + ",".join([*ANGLES, *(f"{w:g}nm" for w in data.wavelengths)]))
    out.append("")
    table = np.concatenate([data.angles, data.values], axis=1)
    out += [",".join(repr(float(v)) for v in row) for row in table]
    return out


def write_astm(path, data: AstmBRDF) -> Path:
    """Write ``data`` as an ASTM E1392 file, atomically, after reading it back: every angle and
    value must come back exactly (shortest round-trip decimals), else nothing is written."""
    path = Path(path)
    values = np.asarray(data.values, float)
    if values.ndim != 2 or values.shape[1] != len(data.wavelengths) or data.angles.shape != (values.shape[0], 4):
        raise AstmError(f"ASTM table: {values.shape} values for {len(data.wavelengths)} wavelengths and "
                        f"{data.angles.shape} angles")
    if not (np.all(np.isfinite(values)) and np.all(np.isfinite(data.angles))):
        raise AstmError("ASTM table: NaN or inf among the values or angles; nothing written")
    text = "\n".join(_lines(data)) + "\n"

    def write(tmp):
        Path(tmp).write_text(text, encoding="latin-1")

    def check(tmps):
        back = read_astm(tmps[path])
        expect("ASTM rows", values.shape[0], back.values.shape[0])
        expect("ASTM wavelengths", tuple(data.wavelengths), tuple(back.wavelengths))
        same = int(np.sum(np.all(back.values == values, axis=1) & np.all(back.angles == data.angles, axis=1)))
        expect("ASTM rows read back unchanged", values.shape[0], same)

    written({path: write}, check)
    return path


def astm_measurements(source, *, rel_std: float = 0.02, floor: float = 1e-3) -> Measurements:
    """An ASTM file (path or :class:`AstmBRDF`) as Measurements: one channel per wavelength.

    The file carries no uncertainty: each value gets ``rel_std * max(|f_r|, floor)`` (``floor`` in
    sr^-1: Cornell's tables hold exact zeros, below their noise) with ``attrs["nominal_sigma"] =
    True`` (the real-data loss, not these sigmas, weights the fit), like RGL's."""
    data = source if isinstance(source, AstmBRDF) else read_astm(source)
    channels = spectral(data.wavelengths)
    f = data.values
    std = rel_std * np.maximum(np.abs(f), floor)
    wi, wo = data.wi, data.wo
    use = np.repeat(((wi[:, 2] > 1e-9) & (wo[:, 2] > 1e-9))[:, None], channels.n, axis=1)
    attrs = {"source": "ASTM E1392", "path": data.path or "", "rel_std": rel_std, "floor": floor,
             "nominal_sigma": True, "wavelengths_nm": list(data.wavelengths),
             "sample": data.header.get("SAMPLE_NAME", "")}
    return Measurements(wi, wo, f, std, use, attrs, channels.names)


def standard_grid() -> np.ndarray:
    """A standard geometry (radians, (N, 4)): theta_i 0-80 deg by 10, phi_i 0, theta_s 0-80 deg by
    10, phi_s 0-180 deg by 15 (isotropic materials: one half plane)."""
    t = np.radians(np.arange(0.0, 81.0, 10.0))
    p = np.radians(np.arange(0.0, 181.0, 15.0))
    ti, ts, ps = (a.ravel() for a in np.meshgrid(t, t, p, indexing="ij"))
    return np.stack([ti, np.zeros_like(ti), ts, ps], axis=1)


def model_astm(model, params, wavelengths, geometry: AstmBRDF | None = None, header: dict | None = None) -> AstmBRDF:
    """A fitted model's f_r as an ASTM table on ``geometry``'s angles (or :func:`standard_grid`).

    ``model.eval`` must give one column per wavelength (a spectral fit)."""
    angles = standard_grid() if geometry is None else np.asarray(geometry.angles, float)
    wl = tuple(float(w) for w in wavelengths)
    wi, wo = directions(angles[:, 0], angles[:, 1]), directions(angles[:, 2], angles[:, 3])
    f = np.asarray(model.eval(wi, wo, params), float).reshape(angles.shape[0], -1)
    if f.shape[1] != len(wl):
        raise AstmError(f"the fit gives {f.shape[1]} channels, not one per wavelength ({len(wl)}): --to astm "
                        "converts a spectral fit")
    if not np.all(np.isfinite(f)):
        raise AstmError("the fit's f_r is NaN or inf on the ASTM geometry; nothing written")
    head = dict(header if header is not None else (geometry.header if geometry is not None else {}))
    head.setdefault("MEAS_NAME", "BRDF")
    head["LAB_COMMENTS"] = f"gonio fit ({model.name})"
    return AstmBRDF(angles, wl, f, head)
