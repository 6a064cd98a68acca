"""Virtual samples: what the simulated instrument has on its holder.

A SAMPLE is a TOML file (``model = "roughplastic"``, ``[options]`` distribution = "ggx",
``[params]`` diffuse_reflectance = [0.5, 0.3, 0.2], alpha = 0.2, int_ior = 1.5) or a measured
RGL-EPFL ``.bsdf`` file (Mitsuba's ``measured`` plugin). A per-channel parameter may be a
spectrum, ``[params.diffuse_reflectance]`` with ``wavelengths = [...]`` (nm) and ``values =
[...]``: kept under ``spectra``, rendered by the RGB simulator as its linear sRGB under D65
(gonio.fitting.colour). A transmitting one may have a ``[slab]`` (thickness_mm,
absorption_per_mm, back = "smooth"): a polished back face. Either becomes the plain dict the simulator takes (docs/interfaces.md
section 4), ``{"model", "options", "params"}`` or ``{"bsdf_file"}``; parameters are checked
against the model's declarations before any stage moves.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import gonio.models as gm
from gonio.core.preflight import check_input_file
from gonio.core.sides import Side
from gonio.core.tomlfile import read_toml
from gonio.fitting.formats import check_rgl_file

from gonio.core.errors import GonioError

__all__ = ["DEMO_SAMPLE", "load_sample", "check_sample"]

#: The demo's known sample: a glossy orange plastic.
DEMO_SAMPLE = {
    "model": "roughplastic",
    "options": {"distribution": "ggx"},
    "params": {"diffuse_reflectance": [0.55, 0.3, 0.12], "alpha": 0.15, "int_ior": 1.5},
}


def check_sample(spec: dict) -> dict:
    """Validate a model-based sample spec against gonio.models; return it normalised."""
    name = spec.get("model")
    if not isinstance(name, str):
        raise GonioError("sample needs `model = \"NAME\"` (one of: " + ", ".join(gm.names()) + ")")
    options = dict(spec.get("options", {}))
    try:
        model = gm.get(name, **options)
    except (KeyError, ValueError, TypeError) as exc:
        raise GonioError(f"sample: {exc}; known models: {', '.join(gm.names())}") from None
    declared = {p.name for p in model.parameters}
    params = dict(spec.get("params", {}))
    unknown = sorted(set(params) - declared)
    if unknown:
        raise GonioError(f"sample: unknown parameter(s) {', '.join(unknown)} for {name}; "
                         f"it takes {', '.join(sorted(declared))}")
    spectra = {}
    for par in model.parameters:
        if isinstance(params.get(par.name), dict):      # [params.NAME] wavelengths = [...] values = [...]
            spectra[par.name], params[par.name] = _spectrum(par, params[par.name])
    full = {p.name: params.get(p.name, p.default) for p in model.parameters}
    try:
        model.validate(full)
    except ValueError as exc:
        raise GonioError(f"sample: {exc}") from None
    to_list = {k: (np.asarray(v, dtype=float).tolist()) for k, v in full.items()}
    out = {"model": name, "options": options, "params": to_list}
    if spectra:
        out["spectra"] = spectra
    if "slab" in spec:
        out["slab"] = _check_slab(spec["slab"], model)
    return out


_SLAB_KEYS = ("thickness_mm", "absorption_per_mm", "back")


def _check_slab(table, model) -> dict:
    """A ``[slab]`` table (the polished back face of a transmitting sample, to first order:
    gonio.sim.physics.sample.slab_exit), checked; it used to be dropped without a word."""
    if Side.TRANSMIT not in tuple(model.structure.sides) or "int_ior" not in {p.name for p in model.parameters}:
        raise GonioError(f"sample: [slab] needs a model that transmits through an interface (roughdielectric), "
                         f"not {model.name}")
    if not isinstance(table, dict) or set(table) - set(_SLAB_KEYS):
        raise GonioError(f"sample: [slab] takes {', '.join(_SLAB_KEYS)} only")
    if table.get("back", "smooth") != "smooth":
        raise GonioError("sample: [slab] back must be \"smooth\" (a polished back face)")
    out = {"back": "smooth"}
    for key in _SLAB_KEYS[:2]:
        v = table.get(key, 1.0 if key == "thickness_mm" else 0.0)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
            raise GonioError(f"sample: [slab] {key} must be a finite number >= 0, not {str(v)[:20]!r}")
        out[key] = float(v)
    return out


def _spectrum(par, table: dict):
    """A parameter given as a spectrum (``wavelengths`` in nm, ``values``): the checked table,
    and the value the RGB simulator renders (its linear sRGB under D65, colour-science)."""
    from gonio.core.channels import spectral
    from gonio.fitting.colour import reflectance_to_linear_srgb

    where = f"sample: [params.{par.name}]"
    if not par.per_channel:
        raise GonioError(f"{where}: {par.name} is one number, not a spectrum")
    if set(table) != {"wavelengths", "values"}:
        raise GonioError(f"{where} takes wavelengths = [...] (nm) and values = [...], not {', '.join(sorted(table))}")
    try:
        w = np.asarray(table["wavelengths"], dtype=float)
        v = np.asarray(table["values"], dtype=float)
        spectral(w)
    except (TypeError, ValueError) as exc:
        raise GonioError(f"{where}: {' '.join(str(exc).split())[:200]}") from None
    if w.ndim != 1 or v.shape != w.shape or w.size < 3:
        raise GonioError(f"{where}: {v.size} values for {w.size} wavelengths (one each, at least 3)")
    if not np.all(np.isfinite(v)) or v.min() < par.lower or v.max() > par.upper:
        raise GonioError(f"{where}: values must be finite and in [{par.lower:g}, {par.upper:g}]")
    if w[0] > 450.0 or w[-1] < 650.0:
        raise GonioError(f"{where}: wavelengths {w[0]:g}-{w[-1]:g} nm do not cover the visible (450-650 nm at least)")
    rgb = np.clip(reflectance_to_linear_srgb(w, v), par.lower, par.upper)    # a saturated colour leaves sRGB
    return {"wavelengths": w.tolist(), "values": v.tolist()}, rgb.tolist()


def load_sample(source) -> dict:
    """Read a SAMPLE (TOML path, ``.bsdf`` path, or None for the demo sample)."""
    if source is None:
        return check_sample(DEMO_SAMPLE)
    path = Path(source)
    if not path.exists():
        raise GonioError(f"sample file {path} does not exist; give a sample TOML or a measured .bsdf file")
    if path.suffix.lower() == ".bsdf":
        check_input_file(path, "sample file")      # a regular file: a FIFO or device would block
        with open(path, "rb") as fh:
            head = fh.read(12)
        if not head.startswith(b"tensor_file"):
            raise GonioError(f"{path} is not an RGL-EPFL tensor .bsdf file (bad header)")

        try:
            check_rgl_file(path)       # the whole structure, before any stage moves
        except ValueError as exc:
            raise GonioError(f"sample {' '.join(str(exc).split())}") from None
        return {"bsdf_file": str(path.resolve())}
    spec = read_toml(path, "sample file")
    return check_sample(spec)
