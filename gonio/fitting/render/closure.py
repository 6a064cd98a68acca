"""Closing the loop on files: the fit of a fit file re-rendered in Mitsuba at a dataset's
geometry (``render.json``) and as sphere previews beside the measured data
(``preview/preview.json``), each with its provenance; and the checks of the render options
(variant, preview size and samples, the measured file) before anything renders."""

from __future__ import annotations

from pathlib import Path

from gonio.core.errors import GonioError
from gonio.fitting.formats.fitfile import load_fit_file

__all__ = ["render_closure", "render_previews", "check_measured", "check_variant", "check_preview_options",
           "provenance", "PREVIEW_SIZE", "PREVIEW_SPP", "PREVIEW_MAX_SAMPLES"]


def provenance(fit_path, meas=None) -> dict:
    """Versions, and the fit and dataset a derived file was made from."""
    from gonio.fitting import versions

    out = {"versions": versions(), "fit": str(fit_path)}
    if meas is not None:
        out["dataset_seed"] = meas.attrs.get("seed")
    return out


def render_closure(fit_path: Path, meas, out_dir: Path, variant=None) -> dict:
    """Render the fit at the dataset's geometry; write ``out_dir/render.json``; return its content."""
    from gonio.fitting import write_json_atomic
    from gonio.fitting.render import loop_closure

    if not fit_path.exists():
        raise GonioError(f"fit file {fit_path} does not exist; run `gonio fit DATASET --out FIT.json` first")
    model, params = load_fit_file(fit_path)
    from gonio.fitting.render.batch import check_renders_in
    from gonio.models.mitsuba import select_variant

    try:
        check_renders_in(model, select_variant(variant))
    except ValueError as exc:
        raise GonioError(str(exc)) from None
    result = loop_closure(model, params, meas, variant=variant)
    result["provenance"] = provenance(fit_path, meas)
    from gonio.core.preflight import writing

    with writing(Path(out_dir) / "render.json"):
        write_json_atomic(Path(out_dir) / "render.json", result)
    return result


def check_measured(path: Path) -> None:
    """``--measured``: an existing MERL .binary or a well-formed RGL .bsdf file."""
    from gonio.fitting.formats import check_rgl_file, read_merl

    if not path.is_file():
        raise GonioError(f"measured data {path} does not exist or is not a file; give a MERL .binary or RGL .bsdf file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".bsdf":
            check_rgl_file(path)
        elif suffix == ".binary":
            read_merl(path)
        else:
            raise GonioError(f"measured data {path}: give a MERL .binary or an RGL .bsdf file")
    except ValueError as exc:
        raise GonioError(f"measured data {path} is not readable ({' '.join(str(exc).split())[:200]})") from None


def render_previews(fit_path: Path, out_dir: Path, measured=None, size: int = 128, spp: int = 256) -> dict:
    """Sphere previews of the fit (and of the measured data) with CIEDE2000; writes preview.json."""
    from gonio.fitting import load_fit, write_json_atomic
    from gonio.fitting.render.preview import preview

    loaded = load_fit(fit_path)
    model, params = loaded.model, loaded.params
    if isinstance(measured, (str, Path)) and not Path(measured).exists():
        raise GonioError(f"measured data {measured} does not exist; give a MERL .binary or RGL .bsdf file")
    result = preview(model, params, Path(out_dir) / "preview", measured=measured, size=size, spp=spp)
    summary = {k: (str(v) if isinstance(v, Path) else v) for k, v in result.items() if k != "images"}
    summary["images"] = {lighting: {k: str(v) for k, v in paths.items()} for lighting, paths in result["images"].items()}
    summary["provenance"] = provenance(fit_path)
    write_json_atomic(Path(out_dir) / "preview" / "preview.json", summary)
    return summary


#: preview bounds: a size x size image at spp samples per pixel, rendered four times
PREVIEW_SIZE = (8, 2048)
PREVIEW_SPP = (1, 16384)
PREVIEW_MAX_SAMPLES = 1 << 30


def check_variant(variant):
    """``--variant``: a Mitsuba RGB variant that this machine can run (None: gonio's choice)."""
    if variant is None:
        return None
    import mitsuba as mi

    import gonio.models as gm

    known = [v for v in mi.variants() if v.endswith("_rgb")]
    if variant not in known:
        raise GonioError(f"--variant {str(variant)[:60]!r}: use one of {', '.join(known)} (gonio renders RGB)")
    if mi.variant() is None:
        mi.set_variant(gm.mitsuba_variant())
    try:
        with mi.scoped_set_variant(variant):
            mi.load_dict({"type": "diffuse"})
    except (ImportError, RuntimeError) as exc:
        first = str(exc).split(".")[0][:160]
        raise GonioError(f"--variant {variant} does not run on this machine ({first}); "
                         f"use {gm.mitsuba_variant()} or scalar_rgb") from None
    return variant


def check_preview_options(size, spp):
    """``--size`` and ``--spp`` within bounds (one line otherwise)."""
    lo, hi = PREVIEW_SIZE
    if not lo <= int(size) <= hi:
        raise GonioError(f"--size {size}: give a preview size from {lo} to {hi} pixels")
    lo, hi = PREVIEW_SPP
    if not lo <= int(spp) <= hi:
        raise GonioError(f"--spp {spp}: give from {lo} to {hi} samples per pixel")
    if int(size) ** 2 * int(spp) > PREVIEW_MAX_SAMPLES:
        raise GonioError(f"--size {size} with --spp {spp} is {int(size) ** 2 * int(spp):.3g} samples per image; "
                         f"keep size^2 x spp at most {PREVIEW_MAX_SAMPLES:.3g}")
