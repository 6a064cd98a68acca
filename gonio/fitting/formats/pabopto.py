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

import dataclasses
from pathlib import Path

import numpy as np

from gonio.core.channels import CHANNELS
from gonio.core.geometry import angles_deg, directions_deg
from gonio.fitting.formats.readback import expect, written

__all__ = ["SRGB_TO_XYZ", "PaboptoExport", "pabopto_files", "export_pabopto", "write_pabopto", "model_pabopto",
           "write_files", "LEFT_OUT_NAME"]

#: Linear sRGB (D65) -> CIE 1931 XYZ, IEC 61966-2-1:1999.
SRGB_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
#: The listing of the points a measured export left out, beside the ``.dat`` files (not read by pabopto2bsdf).
LEFT_OUT_NAME = "left_out.tsv"
#: Why a point is not in the files, by the check that left it out.
REASONS = {"flagged": "flagged (saturated or not usable in some channel)",
           "horizon": "a direction at or below the horizon (PAB-Opto needs theta < 90 deg)",
           "not finite": "f_r or an angle is not finite"}


def _xyz(f: np.ndarray, channels) -> tuple[np.ndarray, str]:
    """(f_r as CIE XYZ (N, 3), a note on how it was obtained)."""
    names = tuple(str(c) for c in channels)[: f.shape[1]]
    if names == ("X", "Y", "Z"):
        return f, "CIE XYZ as measured"
    if f.shape[1] != CHANNELS:
        raise ValueError(f"PAB-Opto export needs {CHANNELS} colour channels (RGB or XYZ), not {f.shape[1]}")
    return f @ SRGB_TO_XYZ.T, "linear sRGB (D65) through the IEC 61966-2-1 matrix"


def _clean_name(name: str) -> str:
    return "".join(ch for ch in str(name) if ch.isprintable() and ch not in '"\\')[:80] or "gonio"


def _incidence_key(ti, pi_):
    """Each point's incident direction as a file holds it: (theta, phi) in degrees rounded to 1e-3
    (the header's precision), phi in [0, 360) and 0 at normal incidence."""
    t = np.round(ti, 3)
    p = np.mod(np.round(np.where(t < 1e-6, 0.0, np.mod(pi_, 360.0)), 3), 360.0)
    return np.stack([t, p], axis=1)


def _file_name(t: float, p: float) -> str:
    return f"gonio_t{t:07.3f}_p{p:07.3f}.dat"


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

    Notes
    -----
    An incident direction is its angles rounded to 1e-3 deg, as the header and the file's
    name write them: the incidences of a calibrated capture differ by hundredths of a degree,
    and each has a file of its own.
    """
    ti, pi_, to, po = (np.asarray(a, float).ravel() for a in (theta_i, phi_i, theta_o, phi_o))
    xyz = np.asarray(xyz, float).reshape(ti.size, CHANNELS)
    if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite([ti, pi_, to, po]))):
        raise ValueError("PAB-Opto export: angles and f_r must be finite (drop the flagged points first)")
    if np.any(to >= 90) or np.any(ti >= 90) or np.any(to < 0) or np.any(ti < 0):
        raise ValueError("PAB-Opto export: every direction must be above the surface (0 <= theta < 90 deg)")
    key = _incidence_key(ti, pi_)
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
        files[_file_name(t, p)] = "\n".join(lines) + "\n"
    expect("PAB-Opto files, one per incident direction", len(np.unique(key, axis=0)), len(files))
    return files


def _read_records(text: str):
    """(incident (theta, phi), records (M, 5)) of a PAB-Opto text gonio wrote, read as pabopto2bsdf
    does: ``#`` lines are the header, the rest whitespace-separated numbers."""
    head = {}
    body = []
    for line in text.splitlines():
        if line.startswith("#"):
            word, _, value = line[1:].partition(" ")
            head[word] = value
        elif line.strip():
            body.append(line)
    numbers = np.array(" ".join(body).split(), dtype=float)
    return (float(head.get("intheta", "nan")), float(head.get("inphi", "nan"))), numbers.reshape(-1, 2 + CHANNELS)


def _check_files(files: dict, n_points: int):
    """A check for :func:`written`: every file holds the records its text was made with, and they
    add up to ``n_points``."""
    def check(tmps):
        total = 0
        for path, tmp in tmps.items():
            text = Path(tmp).read_text(encoding="ascii")
            expect(f"{path.name}: its text", len(files[path.name]), len(text))
            (t, p), got = _read_records(text)
            _, want = _read_records(files[path.name])
            expect(f"{path.name}: records", want.shape[0], got.shape[0])
            expect(f"{path.name}: incident direction", path.name, _file_name(t, p))
            if not np.array_equal(got, want):
                expect(f"{path.name}: values read back", "the values written", "others")
            total += got.shape[0]
        expect("points in the PAB-Opto files", n_points, total)
    return check


def write_files(folder, files: dict, *, n_points: int | None = None, extra: dict | None = None) -> list[Path]:
    """Write ``{name: text}`` (from :func:`pabopto_files`) into ``folder`` (made if missing), all or none.

    Every file is read back before it gets its name; ``n_points`` (the directions the texts were
    made from; by default what their headers count) must be what they hold, else
    :class:`~gonio.fitting.formats.readback.ExportError` and no file is written. ``extra``:
    ``{name: text}`` written beside them (ASCII), read back byte for byte.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if n_points is None:
        n_points = sum(_read_records(text)[1].shape[0] for text in files.values())
    extra = dict(extra or {})

    def writer(text):
        def write(tmp):
            with open(tmp, "w", encoding="ascii", newline="\n") as fh:
                fh.write(text)
        return write

    check_dat = _check_files(files, n_points)

    def check(tmps):
        check_dat({p: t for p, t in tmps.items() if p.name in files})
        for name, text in extra.items():
            back = Path(tmps[folder / name]).read_text(encoding="ascii")
            expect(f"{name}: lines", text.count("\n"), back.count("\n") if back == text else -1)

    writers = {folder / name: writer(text) for name, text in {**files, **extra}.items()}
    return [p for p in written(writers, check) if p.name in files]


@dataclasses.dataclass(frozen=True)
class PaboptoExport:
    """What a measured PAB-Opto export wrote, counted from the files read back.

    Attributes
    ----------
    paths : list of Path
        The ``.dat`` files, one per incident direction.
    n_points : int
        Points in the dataset.
    n_written : int
        Records the files hold (one per point written).
    left_out : dict
        ``{reason key: point indices}`` of the points not written (keys of :data:`REASONS`);
        listed, with their angles, in ``left_out.tsv`` beside the files.
    """

    paths: list
    n_points: int
    n_written: int
    left_out: dict

    def summary(self) -> str:
        """One line: what was written and what was left out, and why."""
        n_left = sum(len(v) for v in self.left_out.values())
        line = f"{self.n_written} of {self.n_points} points in {len(self.paths)} PAB-Opto files (one per incident direction)"
        if n_left:
            why = ", ".join(f"{len(v)} {REASONS[k]}" for k, v in self.left_out.items())
            line += f"; {n_left} left out, listed in {LEFT_OUT_NAME}: {why}"
        return line


def _left_out_text(left_out: dict, angles, sample_name: str) -> str:
    rows = sorted((int(i), key) for key, idx in left_out.items() for i in idx)
    lines = [f"# gonio: points of {_clean_name(sample_name)} not in the PAB-Opto files, and why",
             "point\ttheta_i\tphi_i\ttheta_o\tphi_o\treason"]
    for i, key in rows:
        lines.append("\t".join([str(i), *(f"{a[i]:.6f}" for a in angles), REASONS[key]]))
    return "\n".join(lines) + "\n"


def export_pabopto(folder, meas, *, sample_name="gonio") -> PaboptoExport:
    """Write :class:`~gonio.fitting.Measurements` as PAB-Opto files into ``folder``, every point
    written or listed with its reason.

    A point is left out when a channel is not used (saturated or flagged), when a direction is
    at or below the horizon (PAB-Opto needs theta < 90 deg as written, to 1e-6) or when a value is
    not finite; those points are listed in ``left_out.tsv`` (point, angles, reason) and each
    file's header counts its directions. The files are read back before they get their names;
    a mismatch raises :class:`~gonio.fitting.formats.readback.ExportError` and writes nothing.
    """
    (ti, pi_), (to, po) = angles_deg(meas.wi), angles_deg(meas.wo)
    n = meas.n_points
    flagged = ~meas.use.all(axis=1)
    finite = np.all(np.isfinite(meas.brdf), axis=1) & np.all(np.isfinite(np.stack([ti, pi_, to, po])), axis=0)
    horizon = (np.round(ti, 3) >= 90) | (np.round(to, 6) >= 90) | (ti < 0) | (to < 0)
    reasons = {"flagged": flagged, "not finite": ~flagged & ~finite, "horizon": ~flagged & finite & horizon}
    keep = ~(flagged | ~finite | horizon)
    left_out = {k: np.flatnonzero(m) for k, m in reasons.items() if m.any()}
    xyz, how = _xyz(meas.brdf[keep], meas.channels)
    colour = meas.attrs.get("colour")
    space = colour.get("space") if isinstance(colour, dict) else None
    note = (f"measured f_r ({how}{'' if space else '; the dataset declares no colour space'}); "
            f"{int(keep.sum())} of {n} points written, {n - int(keep.sum())} left out (see {LEFT_OUT_NAME})")
    files = pabopto_files(ti[keep], pi_[keep], to[keep], po[keep], xyz, sample_name=sample_name, note=note)
    extra = {LEFT_OUT_NAME: _left_out_text(left_out, (ti, pi_, to, po), sample_name)} if left_out else {}
    paths = write_files(folder, files, n_points=int(keep.sum()), extra=extra)
    n_written = sum(_read_records(Path(p).read_text(encoding="ascii"))[1].shape[0] for p in paths)
    expect("points written or left out", n, n_written + sum(len(v) for v in left_out.values()))
    return PaboptoExport(paths, n, n_written, left_out)


def write_pabopto(folder, meas, *, sample_name="gonio") -> list[Path]:
    """Write :class:`~gonio.fitting.Measurements` as PAB-Opto files into ``folder``; return their paths
    (:func:`export_pabopto`, which also says what it left out and why)."""
    return export_pabopto(folder, meas, sample_name=sample_name).paths


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
