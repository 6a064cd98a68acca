"""``gonio convert``: exchange formats. A fit -> Mitsuba XML (a plain Mitsuba's, or with gonio's
plugins) / dict JSON / MERL / PAB-Opto; a dataset -> CSV / MERL (binned) / PAB-Opto."""

from __future__ import annotations

import json
import os
from pathlib import Path

from gonio.core.atomic import atomic_open

from gonio.core.errors import GonioError
from gonio.cli.fit import _open_dataset, load_fit_file

__all__ = ["convert_cli"]


def convert_cli(source: Path, out: Path, to: str):
    """Exchange formats: fit -> Mitsuba XML / dict JSON / MERL; dataset -> CSV / MERL (binned)."""
    from gonio.fitting import load_fit, write_json_atomic
    from gonio.fitting import formats

    from gonio.core.preflight import check_output_dir, check_output_file, writing

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
            _convert(source, out, to, formats, load_fit, write_json_atomic, atomic_open)
    except BaseException:
        for folder in made:              # innermost first: only the folders this call made, if empty
            if folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
        raise
    print(f"wrote {out}")


def _make_parent(out: Path) -> None:
    """``--out``'s missing folders are made (as ``mkdir -p``) once the source has been read:
    check_output_file has already checked that their nearest existing ancestor is writable."""
    Path(out).parent.mkdir(parents=True, exist_ok=True)


def _convert_pabopto(source, out, formats, load_fit):
    """``--to pabopto``: a fit's model on a grid, or a dataset's measured values, one file per incidence."""
    if source.suffix.lower() == ".json":
        try:
            loaded = load_fit(source)
        except (ValueError, KeyError, json.JSONDecodeError) as exc:
            raise GonioError(f"{source} is not a readable gonio fit file ({exc})") from None
        # the fitted channels (R, G, B or X, Y, Z) as the fit file names them
        named = [p.get("channel") for p in loaded.parameters.values() if isinstance(p, dict) and p.get("channel")]
        channels = tuple(dict.fromkeys(named)) or ("R", "G", "B")
        files = formats.model_pabopto(loaded.model, loaded.params, channels=channels, sample_name=source.stem)
        paths = formats.write_pabopto_files(out, files)
        line = f"{len(paths)} PAB-Opto files (one per incident direction)"
    else:
        try:
            done = formats.export_pabopto(out, _open_dataset(source), sample_name=source.parent.name or source.stem)
        except ValueError as exc:
            raise GonioError(f"{source}: {exc}") from None
        line = done.summary()
    print(f"{line} in {out}; Radiance: pabopto2bsdf {out}/*.dat > sample.sir")


def _convert(source, out, to, formats, load_fit, write_json_atomic, atomic_open):
    if to == "pabopto":
        return _convert_pabopto(source, out, formats, load_fit)
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
        note = writer(out, model.name, dict(model.options), params, plugins=plugins)
        if note:
            print(note)
    elif to == "csv":
        meas = _open_dataset(source)
        _make_parent(out)
        formats.dataset_to_csv(meas, out)
    elif to == "merl-data":
        merl = formats.dataset_to_merl(_open_dataset(source))
        _make_parent(out)
        formats.write_merl(out, merl)
        print(f"{int(merl.valid.sum())} of {merl.valid.size} MERL bins hold measured data; the rest are marked no-data")
    else:
        raise GonioError(f"unknown --to {to!r}: mitsuba-xml, mitsuba-xml-gonio, mitsuba-dict, merl, pabopto (from a fit), csv, merl-data "
                         "or pabopto (from a dataset)")
