"""A fitted model as a BSDF a plain Mitsuba 3 loads: its native twin, or the closest native family.

A model whose ``to_mitsuba`` names a Mitsuba plugin (``roughplastic``, ``principled``, ...) is
exported as is. One that needs gonio's Python plugin (``gonio_<name>``: ``cooktorrance``,
``orennayar``, ``tabulated``; Mitsuba 3 has no Oren-Nayar or Cook-Torrance plugin) is replaced by
the single-lobe native model (:data:`FAMILIES`) fitted to the model's own f_r on a grid, and the
difference is stated: :attr:`NativeBSDF.error`, the relative RMS difference of
f_r cos(theta_i) cos(theta_o) per channel over :data:`N_CHECK` seeded random direction pairs
(theta below 85 deg) that the fit did not use.
"""

# The fit: f_r of the model on a grid (theta_i, theta_o 2.5..82.5 deg by 5, phi_o by 15 deg,
# phi_i = 0: the models are isotropic), each value given the 1-sigma s / (cos_i cos_o) with s one
# hundredth of the channel's RMS of f_r cos_i cos_o, so that chi^2 is the stated error's square
# sum: the fit minimises what is reported. Two-lobe native models (roughplastic2,
# roughconductor2) are left out: a fit of one takes 5-40 s against < 1 s for a single lobe.

from __future__ import annotations

import dataclasses

import numpy as np

import gonio.models as gm
from gonio.core.channels import CHANNELS, of_values
from gonio.core.geometry import directions_deg
from gonio.fitting.formats.readback import ExportError

__all__ = ["FAMILIES", "N_CHECK", "NativeBSDF", "native_bsdf", "check_directions", "relative_error"]

#: (model, options) of the native families tried, in order (the first of equal errors wins).
FAMILIES = (("diffuse", {}), ("roughplastic", {"distribution": "beckmann"}), ("roughplastic", {"distribution": "ggx"}),
            ("principled", {"distribution": "ggx"}), ("roughconductor", {"distribution": "beckmann"}),
            ("roughconductor", {"distribution": "ggx"}))
#: Direction pairs the stated error is computed on.
N_CHECK = 4096


@dataclasses.dataclass(frozen=True)
class NativeBSDF:
    """What a plain Mitsuba 3 loads for a model.

    Attributes
    ----------
    source : str
        The model exported (``gonio.models`` name).
    name, options, params
        The native model written and its parameters (the source's own when ``exact``).
    mitsuba : dict
        ``mitsuba.load_dict`` dict of a native plugin.
    exact : bool
        True when the source model is a native plugin itself.
    error : ndarray, shape (channels,)
        Relative RMS difference of f_r cos_i cos_o per channel (:func:`relative_error`); 0 when exact.
    """

    source: str
    name: str
    options: dict
    params: dict
    mitsuba: dict
    exact: bool
    error: np.ndarray

    def note(self) -> str:
        """One line saying what was written and how far it is from the model."""
        if self.exact:
            return f"model {self.source} is Mitsuba's {self.mitsuba['type']} plugin: exact"
        opts = f" ({', '.join(f'{k}={v}' for k, v in self.options.items())})" if self.options else ""
        errs = "/".join(f"{100 * e:.1f}" for e in self.error)
        return (f"model {self.source} has no Mitsuba 3 plugin: written as {self.name}{opts} fitted to its f_r, "
                f"relative RMS difference of f_r cos_i cos_o {errs} % per channel over {N_CHECK} direction pairs")


def check_directions(n: int = N_CHECK, seed: int = 34):
    """``n`` seeded random direction pairs (wi, wo), theta uniform in [0, 85) deg, both azimuths random."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(0.0, 85.0, (2, n))
    p = rng.uniform(0.0, 360.0, (2, n))
    return directions_deg(t[0], p[0]), directions_deg(t[1], p[1])


def relative_error(f_model, f_other, wi, wo) -> np.ndarray:
    """Per channel: RMS of (f_other - f_model) cos_i cos_o over RMS of f_model cos_i cos_o
    (0 where both are 0, inf where only the model is)."""
    w = (np.asarray(wi)[:, 2] * np.asarray(wo)[:, 2])[:, None]
    diff = np.sqrt(np.mean(((np.asarray(f_other) - f_model) * w) ** 2, axis=0))
    scale = np.sqrt(np.mean((np.asarray(f_model) * w) ** 2, axis=0))
    return np.where(scale > 0, diff / np.where(scale > 0, scale, 1.0), np.where(diff > 0, np.inf, 0.0))


def _grid():
    t = np.arange(2.5, 85.0, 5.0)
    ti, to, po = (a.ravel() for a in np.meshgrid(t, t, np.arange(0.0, 360.0, 15.0), indexing="ij"))
    return directions_deg(ti, np.zeros_like(ti)), directions_deg(to, po)


def native_bsdf(model_name: str, options: dict | None, params: dict, *, seed: int = 0) -> NativeBSDF:
    """The native Mitsuba BSDF for a fitted model (module docstring).

    Parameters
    ----------
    model_name, options, params
        The fitted model, as a fit file holds it.
    seed : int
        Seeds the refit's starting points (the result is reproducible).

    Raises
    ------
    ExportError
        When no native family could be fitted (one line).
    """
    from gonio.fitting.measurements import Measurements
    from gonio.fitting.optimise.mle import fit

    model = gm.get(model_name, **(options or {}))
    params = model.validate(params)
    d = model.to_mitsuba(params)
    if not str(d["type"]).startswith("gonio_"):
        return NativeBSDF(model.name, model.name, dict(model.options), params, d, True, np.zeros(model.n_channels(params)))
    from gonio.core.sides import Side

    if Side.TRANSMIT in tuple(model.structure.sides):
        # the families below reflect only: fitted on the upper hemisphere they would stand for a
        # transmitter by a black reflector with a zero stated error
        raise ExportError(f"model {model.name} transmits and no native Mitsuba BSDF stands for it; "
                          "export gonio's plugin instead (--to mitsuba-xml-gonio)")
    wi, wo = _grid()
    f = np.asarray(model.eval(wi, wo, params), dtype=np.float64).reshape(len(wi), -1)   # a spectral fit: N channels
    w = (wi[:, 2] * wo[:, 2])[:, None]
    scale = np.sqrt(np.mean((f * w) ** 2, axis=0))
    sigma = 0.01 * np.where(scale > 0, scale, 1e-6) / w
    channels = of_values(f[0]) if f.shape[1] != CHANNELS else None
    meas = Measurements(wi, wo, f, sigma, np.ones(f.shape, bool), *(
        ({"wavelengths_nm": list(channels.wavelengths_nm)}, channels.names) if channels else ()))
    cwi, cwo = check_directions()
    f_check = np.asarray(model.eval(cwi, cwo, params), dtype=np.float64).reshape(len(cwi), -1)
    best = None
    for name, opts in FAMILIES:
        family = gm.get(name, **opts)
        try:
            result = fit(meas, family, rng=np.random.default_rng(seed), covariance=False)
        except (ValueError, ArithmeticError, RuntimeError):
            continue
        got = np.asarray(family.eval(cwi, cwo, result.params), dtype=np.float64).reshape(len(cwi), -1)
        err = relative_error(f_check, got, cwi, cwo)
        if np.all(np.isfinite(err)) and (best is None or err.max() < best[0].max()):
            best = (err, family, result.params)
    if best is None:
        raise ExportError(f"no native Mitsuba BSDF could be fitted to model {model.name}; "
                          "export gonio's plugin instead (--to mitsuba-xml-gonio)")
    err, family, fitted = best
    fitted = family.validate(fitted)
    return NativeBSDF(model.name, family.name, dict(family.options), fitted, family.to_mitsuba(fitted), False, err)
