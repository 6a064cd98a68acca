"""``gonio convert``'s use case: one file in an exchange format, from a fit or a dataset.

A fit -> Mitsuba XML (a plain Mitsuba's, or with gonio's plugins) / dict JSON / MERL /
PAB-Opto / Zemax tabular BSDF; a dataset -> CSV / MERL (binned) / PAB-Opto. Every output is checked before anything
is written (one line naming what to fix), written through the formats' checked writers, and
what a failed call made (folders) is removed. :func:`convert` says its lines through ``say``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Callable

from gonio.bench.dataset.reader import open_dataset
from gonio.core.channels import RGB, from_attrs, use
from gonio.core.errors import GonioError
from gonio.core.preflight import check_output_dir, check_output_file, writing
from gonio.fitting import formats, load_fit
from gonio.fitting.pipeline import load_fit_file

__all__ = ["convert", "TARGETS"]

#: What ``--to`` accepts.
TARGETS = ("mitsuba-xml", "mitsuba-xml-gonio", "mitsuba-dict", "merl", "pabopto", "zemax", "astm", "rgl-bsdf", "csv", "merl-data")


def convert(source: Path, out: Path, to: str, say: Callable[[str], None] = print) -> None:
    """Write ``source`` (a fit file or a dataset) to ``out`` in format ``to``."""
    source, out = Path(source), Path(out)
    if not source.exists():
        raise GonioError(f"{source} does not exist")
    if source.is_dir():
        raise GonioError(f"{source} is a folder; give a fit file (FIT.json) or a dataset.nc")
    merl_bytes = 12 + 3 * 90 * 90 * 180 * 8
    if to == "pabopto":
        check_output_dir(out, "PAB-Opto output folder (--out)")
    else:
        check_output_file(out, "converted file (--out)", need_bytes=merl_bytes if to in ("merl", "merl-data") else 0)
    if Path(os.path.abspath(out)) == Path(os.path.abspath(source)):
        raise GonioError(f"--out {out} is the source file; give another file name")
    made = [p for p in (Path(os.path.abspath(out)), *Path(os.path.abspath(out)).parents) if not p.exists()]
    try:
        with writing(out):
            _convert(source, out, to, say)
    except BaseException:
        for folder in made:              # innermost first: only the folders this call made, if empty
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        raise
    say(f"wrote {out}")


def _make_parent(out: Path) -> None:
    """``--out``'s missing folders are made (as ``mkdir -p``) once the source has been read:
    check_output_file has already checked that their nearest existing ancestor is writable."""
    Path(out).parent.mkdir(parents=True, exist_ok=True)


def _read_fit(source):
    """The fit file at ``source`` (its wavelengths checked as it is read), or one line saying
    it is not a readable one."""
    try:
        return load_fit(source)
    except (ValueError, KeyError, json.JSONDecodeError) as exc:
        raise GonioError(f"{source} is not a readable gonio fit file ({exc})") from None


def _convert_pabopto(source, out, say):
    """``--to pabopto``: a fit's model on a grid, or a dataset's measured values, one file per incidence."""
    if source.suffix.lower() == ".json":
        loaded = _read_fit(source)
        # the fitted channels (R, G, B or X, Y, Z) as the fit file names them
        named = [p.get("channel") for p in loaded.parameters.values() if isinstance(p, dict) and p.get("channel")]
        channels = tuple(dict.fromkeys(named)) or RGB.names
        files = formats.model_pabopto(loaded.model, loaded.params, channels=channels, sample_name=source.stem)
        paths = formats.write_pabopto_files(out, files)
        line = f"{len(paths)} PAB-Opto files (one per incident direction)"
    else:
        try:
            done = formats.export_pabopto(out, open_dataset(source), sample_name=source.parent.name or source.stem)
        except ValueError as exc:
            raise GonioError(f"{source}: {exc}") from None
        line = done.summary()
    say(f"{line} in {out}; Radiance: pabopto2bsdf {out}/*.dat > sample.sir")


def _convert_zemax(source, out, say):
    """``--to zemax``: a fit's model as Zemax/LightTools tabular BSDF files, ``OUT_brdf.bsdf`` and,
    for a model that transmits, ``OUT_btdf.bsdf`` (each read back and checked)."""
    from gonio.fitting.formats.zemax import export_zemax

    if source.suffix.lower() != ".json":
        raise GonioError(f"--to zemax converts a fit file (FIT.json); {source} is not one")
    model, params = load_fit_file(source)
    _make_parent(out)
    stem = out.with_suffix("") if out.suffix.lower() == ".bsdf" else out
    paths = export_zemax(stem, model, params)
    say(f"{len(paths)} Zemax tabular BSDF file(s): " + ", ".join(str(p) for p in paths))


def _convert_astm(source, out, say, geometry=None):
    """``--to astm``: a spectral fit's f_r as an ASTM E1392 table, on the geometry of the ASTM
    file it was fitted from where that file is still there (else a standard grid)."""
    from gonio.fitting.formats import astm

    if source.suffix.lower() != ".json":
        raise GonioError(f"--to astm converts a spectral fit file (FIT.json); {source} is not one")
    loaded = _read_fit(source)
    wavelengths = loaded.wavelengths
    if wavelengths is None:
        raise GonioError(f"{source} is not a spectral fit (no wavelengths): --to astm writes one column per wavelength")
    dataset = (loaded.document.get("provenance") or {}).get("dataset")
    if geometry is None and dataset and Path(dataset).is_file() and astm.is_astm(dataset):
        geometry = astm.read_astm(dataset)
    table = astm.model_astm(loaded.model, loaded.params, wavelengths, geometry)
    table.header["FILE_NAME"] = out.name
    _make_parent(out)
    astm.write_astm(out, table)
    where = f"the geometry of {dataset}" if geometry is not None else "the standard grid"
    say(f"{table.values.shape[0]} points x {len(wavelengths)} wavelengths on {where}")


def _convert_rgl(source, out, say):
    """``--to rgl-bsdf``: a fit of an RGL-EPFL ``.bsdf`` file written on that file's own grid
    (:func:`gonio.fitting.formats.rgl_grid.fit_on_rgl_grid`), so Mitsuba's ``measured`` plugin
    reads and samples it as it does the measurement; how closely it gives the fit is printed."""
    from gonio.core.files import sha256_file
    from gonio.fitting.formats.fitfile import versions
    from gonio.fitting.formats.rgl_grid import fit_on_rgl_grid, grid_error

    if source.suffix.lower() != ".json":
        raise GonioError(f"--to rgl-bsdf converts a fit file (FIT.json); {source} is not one")
    loaded = _read_fit(source)
    provenance = loaded.document.get("provenance")
    provenance = provenance if isinstance(provenance, dict) else {}
    grid = provenance.get("dataset")
    if not isinstance(grid, str) or not grid.lower().endswith(".bsdf"):
        raise GonioError(f"--to rgl-bsdf writes a fit on the grid of the RGL .bsdf file it was fitted to; {source} was "
                         f"fitted to {grid!r}, not an RGL file")
    # the path as `gonio fit` was given it: from the folder it ran in, or beside the fit file
    grid = next((p for p in (Path(grid), source.parent / grid) if p.is_file()), Path(grid))
    if not grid.is_file():
        raise GonioError(f"{source} was fitted to {grid}, which is no longer there: --to rgl-bsdf writes on that file's grid")
    if os.path.realpath(out) == os.path.realpath(grid):
        raise GonioError(f"--out {out} is the RGL file the fit was made from; give another file name")
    if provenance.get("dataset_sha256") and sha256_file(grid) != provenance["dataset_sha256"]:
        raise GonioError(f"{grid} has changed since {source} was fitted to it (its SHA-256 differs); refit it")
    if loaded.wavelengths is not None or loaded.model.n_channels(loaded.params) != 3:
        raise GonioError(f"{source} is not a three-channel RGB fit: --to rgl-bsdf writes an RGB file")
    v = versions()
    goodness = loaded.document.get("goodness")
    loss = goodness.get("loss", "?") if isinstance(goodness, dict) else "?"
    text = (f"gonio {v.get('gonio', '?')}: {loaded.model.name} {dict(loaded.model.options) or ''} fitted to {grid.name} "
            f"(seed {provenance.get('seed')}, loss {loss}), written on its grid; "
            f"mitsuba {v.get('mitsuba', '?')}, numpy {v.get('numpy', '?')}")
    error = []
    _make_parent(out)
    try:        # scored on the temporary file: a refusal leaves nothing
        summary = fit_on_rgl_grid(loaded.model, loaded.params, grid, out, description=text,
                                  verify=lambda tmp: error.append(grid_error(loaded.model, loaded.params, tmp)))
    except ValueError as exc:
        raise GonioError(f"{source}: {' '.join(str(exc).split())[:300]}") from None
    say(f"{loaded.model.name} on the grid of {grid.name!r}: {summary['nodes']} nodes ({summary['held']} without a "
        f"value of their own, below the horizon: held at their nearest neighbour's); against the fit itself its Ngan relative L2 is "
        f"{error[0]:.3f} (equal-solid-angle pairs, theta <= 80 deg: the format interpolates between the measured "
        "incidences, and repeats the last one up to 90 deg, as it does the measurement)")


def _convert(source, out, to, say):
    if to == "rgl-bsdf":
        return _convert_rgl(source, out, say)
    if to == "astm":
        return _convert_astm(source, out, say)
    if to == "pabopto":
        return _convert_pabopto(source, out, say)
    if to == "zemax":
        return _convert_zemax(source, out, say)
    if to in ("mitsuba-xml", "mitsuba-xml-gonio", "mitsuba-dict", "merl"):
        if source.suffix.lower() != ".json":
            raise GonioError(f"--to {to} converts a fit file (FIT.json); {source} is not one")
        model, params = load_fit_file(source)
        if to == "merl":
            merl = formats.resample_to_merl(model, params)
            _make_parent(out)
            formats.write_merl(out, merl)
            return
        # a plain Mitsuba loads mitsuba-xml and mitsuba-dict (the closest native family where the model has no
        # plugin); mitsuba-xml-gonio keeps gonio's Python plugin (exact, for a process that imports gonio)
        plugins = "gonio" if to == "mitsuba-xml-gonio" else "native"
        writer = formats.write_mitsuba_dict if to == "mitsuba-dict" else formats.write_mitsuba_document
        _make_parent(out)
        try:        # a spectral fit's values as spectra (its wavelengths), for a *_spectral variant
            with use(from_attrs(load_fit(source).wavelengths)):
                note = writer(out, model.name, dict(model.options), params, plugins=plugins)
        except ValueError as exc:
            raise GonioError(f"{source}: {' '.join(str(exc).split())[:300]}") from None
        if note:
            say(note)
    elif to == "csv":
        meas = open_dataset(source)
        _make_parent(out)
        formats.dataset_to_csv(meas, out)
    elif to == "merl-data":
        merl = formats.dataset_to_merl(open_dataset(source))
        _make_parent(out)
        formats.write_merl(out, merl)
        say(f"{int(merl.valid.sum())} of {merl.valid.size} MERL bins hold measured data; the rest are marked no-data")
    else:
        raise GonioError(f"unknown --to {to!r}: mitsuba-xml, mitsuba-xml-gonio, mitsuba-dict, merl, pabopto (from a fit), csv, merl-data "
                         "or pabopto (from a dataset)")
