"""Virtual samples: what the simulated instrument has on its holder.

A SAMPLE is either a TOML file::

    model = "roughplastic"
    [options]
    distribution = "ggx"
    [params]
    diffuse_reflectance = [0.5, 0.3, 0.2]
    alpha = 0.2
    int_ior = 1.5

or a measured RGL-EPFL ``.bsdf`` file (Mitsuba's ``measured`` plugin). Either becomes the plain
dict the simulator takes (docs/interfaces.md section 4), ``{"model", "options", "params"}`` or
``{"bsdf_file"}``; parameters are checked against the model's declarations before any stage moves.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import gonio.models as gm
from gonio.core.preflight import check_input_file
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
    full = {p.name: params.get(p.name, p.default) for p in model.parameters}
    try:
        model.validate(full)
    except ValueError as exc:
        raise GonioError(f"sample: {exc}") from None
    to_list = {k: (np.asarray(v, dtype=float).tolist()) for k, v in full.items()}
    return {"model": name, "options": options, "params": to_list}


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
