"""Helpers on fit documents (``fit.json``) shared by the fit runner, the report and the demo:
the truth of a simulated sample matched to a fit's parameter names, the energy constraint in
words, and the dataset at the geometry the fit's shared-angle estimate gave it. One place, so
the three say the same thing."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gonio.core.channels import RGB

__all__ = ["CHANNEL_NAMES", "as_fitted", "energy_text", "truth_by_name", "truth_for"]

#: The names of the colour channels in a fit vector's names (``diffuse_reflectance[R]``).
CHANNEL_NAMES = list(RGB.names)


def truth_by_name(truth, names):
    """Map fit-vector names (``diffuse_reflectance[R]``; ``[550nm]`` from the sample's ``spectra``,
    interpolated) to true values where the truth is known."""
    if not isinstance(truth, dict) or not isinstance(truth.get("params"), dict):
        return {}
    out = {}
    spectra = truth.get("spectra") if isinstance(truth.get("spectra"), dict) else {}
    for name in names:
        base, _, chan = str(name).partition("[")
        if base not in truth["params"]:
            continue
        try:
            if chan.endswith("nm]") and isinstance(spectra.get(base), dict):    # a spectrum at a fit's wavelength
                sp = spectra[base]
                out[name] = float(np.interp(float(chan[:-3]), np.asarray(sp["wavelengths"], float),
                                            np.asarray(sp["values"], float)))
                continue
            value = np.asarray(truth["params"][base], dtype=float).reshape(-1)
            if chan:
                c = CHANNEL_NAMES.index(chan.rstrip("]"))
                out[name] = float(value[c] if value.size > 1 else value[0])
            else:
                out[name] = float(value[0])
        except (ValueError, TypeError, IndexError):
            continue
    return out


def truth_for(truth, model_name, names):
    """:func:`truth_by_name` when ``truth`` describes the fitted model, else {}."""
    if isinstance(truth, dict) and truth.get("model") == model_name:
        return truth_by_name(truth, names)
    return {}


def energy_text(energy: dict) -> str:
    """The energy constraint of a fit document in words."""
    if energy.get("by_construction") and energy.get("max_albedo") is None:
        return "conserved by construction"
    state = "holds" if energy.get("holds") else "VIOLATED"
    return f"{state} (max albedo {energy['max_albedo']:.4f})" if energy.get("max_albedo") is not None else state


def as_fitted(meas, dataset_path, record, response=None):
    """``meas`` (the dataset at ``dataset_path`` as opened) at the directions and irradiance the
    fit file's ``shared_angles`` ``record`` gave it (gonio.fitting.uncertainty.shared_angles
    .as_estimated) and, with ``response`` (model, params, the fit file's ``instrument_response``
    source and detector half-angles in deg), divided by c = <f_r>/f_r there as the fit divided
    them (gonio/fitting/likelihood/aperture.py; c taken again at the fitted parameters): the data
    the fit's parameters were fitted to. Returns (Measurements, None), or (``meas`` as far as it
    could be taken, a note) where the record or the half-angles do not fit."""
    from gonio.bench.dataset.reader import open_budget
    from gonio.core.errors import GonioError
    from gonio.fitting.likelihood.aperture import aperture_ratio, corrected
    from gonio.fitting.uncertainty.shared_angles import as_estimated

    note = None
    if isinstance(record, dict) and record.get("applied"):
        try:
            meas = as_estimated(meas, getattr(open_budget(Path(dataset_path), meas), "angles", None), record)
        except (ValueError, GonioError) as exc:
            note = f"The data are drawn at their nominal directions: {' '.join(str(exc).split())[:200]}."
    if response is None:
        return meas, note
    model, params, *half = response
    try:
        src, det = (float(h or 0.0) for h in half)
    except (TypeError, ValueError):
        src = det = float("nan")
    if not (0.0 <= src <= 20.0 and 0.0 <= det <= 20.0):
        return meas, " ".join(filter(None, [note, f"The data are drawn without the apertures' correction: the fit "
                                                  f"file's half-angles {half!r:.60} are not in [0, 20] deg."]))
    if src > 0.0 or det > 0.0:
        meas = corrected(meas, None, aperture_ratio(model, meas.wi, meas.wo, params, src, det))[0]
    return meas, note
