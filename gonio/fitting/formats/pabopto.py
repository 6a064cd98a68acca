"""The PAB-Opto text format that Radiance's ``pabopto2bsdf`` reads (one file per incident direction).

Format as Radiance's reader ``src/cv/pabopto2bsdf.c`` (G. Ward, LBNL) parses it: a header of
``#`` lines (``#sample_name "NAME"``, ``#format: theta phi BRDF``, ``#colorimetry: CIE-XYZ``,
``#intheta T``, ``#inphi P``, ``#upphi U``), then records ``theta_out phi_out value [value
value]`` in degrees. Directions are gonio's (pointing away from the surface, +z the normal;
wi toward the light is the incident one), ``#upphi 90`` keeps gonio's frame, and all outgoing
angles of a file lie on one side (reflection: < 90).

gonio writes f_r as CIE XYZ (``#colorimetry: CIE-XYZ``): from a dataset fitted in CIE XYZ as
is; from linear sRGB (D65) through the IEC 61966-2-1 matrix; camera RGB that declares no
colour space is taken as linear sRGB and the header says so. Usage: ``pabopto2bsdf *.dat >
sample.sir`` then ``bsdf2ttree`` or ``bsdf2klems`` for a Radiance BSDF XML.
"""

# Reader details: each header keyword comes right after the #; #format may also be DSF, BSDF
# or BTDF; #colorimetry: CIE-XYZ gives three values per direction (CIE-Y or absent: one);
# #intheta and #inphi are the incident direction in degrees; #upphi U is the file's azimuth
# of "up" and the reader adds 90 - U to every phi, so U = 90 keeps gonio's frame, in which +y
# is "up"; other # lines are skipped. Records are whitespace-separated. BRDF values are f_r in
# 1/sr; the reader turns them into the DSF f_r cos(theta_out) (bsdfrep.c, add_bsdf_data).
# Both directions are (sin theta cos phi, sin theta sin phi, cos theta), +z the normal facing
# the room; wo toward the detector is the outgoing one.

from __future__ import annotations

from pathlib import Path

import numpy as np

from gonio.core.atomic import atomic_open
from gonio.core.geometry import angles_deg, directions_deg

__all__ = ["SRGB_TO_XYZ", "pabopto_files", "write_pabopto", "model_pabopto", "write_files"]

#: Linear sRGB (D65) -> CIE 1931 XYZ, IEC 61966-2-1:1999.
SRGB_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])


def _xyz(f: np.ndarray, channels) -> tuple[np.ndarray, str]:
    """(f_r as CIE XYZ (N, 3), a note on how it was obtained)."""
    names = tuple(str(c) for c in channels)[: f.shape[1]]
    if names == ("X", "Y", "Z"):
        return f, "CIE XYZ as measured"
    if f.shape[1] != 3:
        raise ValueError(f"PAB-Opto export needs three colour channels (RGB or XYZ), not {f.shape[1]}")
    return f @ SRGB_TO_XYZ.T, "linear sRGB (D65) through the IEC 61966-2-1 matrix"


def _clean_name(name: str) -> str:
    return "".join(ch for ch in str(name) if ch.isprintable() and ch not in '"\\')[:80] or "gonio"


def pabopto_files(theta_i, phi_i, theta_o, phi_o, xyz, *, sample_name="gonio", note="") -> dict[str, str]:
    """The PAB-Opto files (name -> text) of f_r given per direction pair, one per incident direction.

    Parameters
    ----------
    theta_i, phi_i, theta_o, phi_o : array_like, shape (N,)
        Degrees, gonio's convention (see the module docstring).
    xyz : array_like, shape (N, 3)
        f_r in 1/sr as CIE XYZ.
    sample_name : str
        Written as ``#sample_name``; quotes and control characters are dropped.
    note : str
        A comment line for the header.
    """
    ti, pi_, to, po = (np.asarray(a, float).ravel() for a in (theta_i, phi_i, theta_o, phi_o))
    xyz = np.asarray(xyz, float).reshape(ti.size, 3)
    if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite([ti, pi_, to, po]))):
        raise ValueError("PAB-Opto export: angles and f_r must be finite (drop the flagged points first)")
    if np.any(to >= 90) or np.any(ti >= 90) or np.any(to < 0) or np.any(ti < 0):
        raise ValueError("PAB-Opto export: every direction must be above the surface (0 <= theta < 90 deg)")
    key = np.round(np.stack([ti, np.where(ti < 1e-6, 0.0, np.mod(pi_, 360.0))], axis=1), 3)
    files = {}
    for t, p in np.unique(key, axis=0):
        sel = np.all(key == (t, p), axis=1)
        lines = [f'#sample_name "{_clean_name(sample_name)}"', "#format: theta phi BRDF", "#colorimetry: CIE-XYZ",
                 f"#intheta {t:.3f}", f"#inphi {p:.3f}", "#upphi 90",
                 f"# gonio: f_r in 1/sr per outgoing direction (theta_out phi_out X Y Z), {int(sel.sum())} directions"]
        if note:
            lines.append("# gonio: " + " ".join(str(note).split())[:200])
        order = np.lexsort((po[sel], to[sel]))
        for a, b, v in zip(to[sel][order], po[sel][order], xyz[sel][order]):
            lines.append(f"{a:.6f} {b % 360.0:.6f} {v[0]:.9g} {v[1]:.9g} {v[2]:.9g}")
        files[f"gonio_t{t:05.1f}_p{p:05.1f}.dat"] = "\n".join(lines) + "\n"
    return files


def write_pabopto(folder, meas, *, sample_name="gonio") -> list[Path]:
    """Write :class:`~gonio.fitting.Measurements` as PAB-Opto files into ``folder``; return their paths.

    Points with any channel not used (saturated or flagged) are left out (the header counts what
    each file holds)."""
    keep = meas.use.all(axis=1)
    xyz, how = _xyz(meas.brdf[keep], meas.channels)
    (ti, pi_), (to, po) = angles_deg(meas.wi[keep]), angles_deg(meas.wo[keep])
    space = (meas.attrs.get("colour") or {}).get("space") if isinstance(meas.attrs.get("colour"), dict) else None
    note = f"measured f_r ({how}{'' if space else '; the dataset declares no colour space'}); " \
           f"{int((~keep).sum())} flagged points left out"
    return write_files(folder, pabopto_files(ti, pi_, to, po, xyz, sample_name=sample_name, note=note))


def model_pabopto(model, params, *, theta_i=(0, 15, 30, 45, 60, 75), theta_step=5.0, phi_step=10.0,
                  channels=("R", "G", "B"), sample_name="gonio fit") -> dict[str, str]:
    """A fitted (isotropic) model sampled as PAB-Opto files: incidences ``theta_i`` at phi 0,
    outgoing directions on a grid theta 0..85 deg by ``theta_step``, phi 0..360 by ``phi_step``."""
    t_o = np.arange(0.0, 85.0 + 1e-9, theta_step)
    p_o = np.arange(0.0, 360.0 - 1e-9, phi_step)
    T, P = np.meshgrid(t_o, p_o, indexing="ij")
    T, P = T.ravel(), P.ravel()
    rows = []
    for t in theta_i:
        wi = directions_deg(np.full(T.size, float(t)), np.zeros(T.size))
        f = model.eval(wi, directions_deg(T, P), params)
        rows.append((np.full(T.size, float(t)), np.zeros(T.size), T, P, f))
    ti, pi_, to, po, f = (np.concatenate(c) for c in zip(*rows))
    xyz, how = _xyz(f, channels)
    return pabopto_files(ti, pi_, to, po, xyz, sample_name=sample_name,
                         note=f"model {model.name} sampled on a grid ({how})")


def write_files(folder, files: dict) -> list[Path]:
    """Write ``{name: text}`` (from :func:`pabopto_files`) into ``folder`` (made if missing), each atomically."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for name, text in files.items():
        with atomic_open(folder / name, "w", encoding="ascii") as fh:
            fh.write(text)
        out.append(folder / name)
    return out
