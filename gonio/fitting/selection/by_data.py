"""Model selection: model only what the data needs.

Every candidate is fitted with one loss and ranked by the Bayesian information criterion
BIC = -2 ln L + k ln n (Schwarz 1978) of that same loss (:attr:`FitResult.bic`: chi^2 for the
chi2 loss, the profiled Gaussian likelihood of the log or cosine residuals, the discrepancy
likelihood). Among the candidates whose BIC lies within ``delta`` of the best, the one with
the fewest parameters wins: by Kass & Raftery (1995, sec. 3.2) a BIC difference below 2 is
"not worth more than a bare mention".

Anisotropic candidates (a model's ``anisotropic`` option) are offered only where the data
shows azimuthal structure (:func:`azimuthal_structure`): points that an isotropic BRDF
makes equal (the same theta_i, theta_o and |phi_o - phi_i|, at different azimuths phi_i)
differ beyond their noise. The ``spectral_candidate`` models (flakepaint) join on spectral
data, and with the ``goniochromic_candidate`` ones (gratingpaint) on RGB data whose colours
are not a mixture of two (:func:`goniochromism`).
"""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np
from scipy.stats import chi2 as _chi2

import gonio.models as gm
from gonio.core.geometry import angles_deg
from gonio.core.sides import Side, side_of

from gonio.fitting.optimise.mle import fit

__all__ = ["CANDIDATES", "ANISOTROPIC", "SPECTRAL", "GONIOCHROMIC", "Azimuthal", "Goniochromism", "azimuthal_structure",
           "goniochromism", "Ranked", "candidate_rng", "option_candidates", "select", "candidates_for"]

#: (name, options) tried by ``--model auto``, simplest first (fewest parameters): every
#: registered model that does not declare ``auto_candidate = False`` (the model declares,
#: selection reads: a new model file in gonio.models is a candidate without edits here).
#: Every microfacet distribution a model declares (``OPTIONS["distribution"]``) is a
#: candidate of its own: a Beckmann conductor is not "explained" by another model.
def _candidates(names=None):
    out = []
    for name in names or gm.names():
        try:
            model = gm.get(name)
        except (KeyError, ValueError):
            continue
        cls = type(model)
        if names is None and not getattr(cls, "auto_candidate", True):
            continue
        k = sum(3 if p.per_channel else 1 for p in model.parameters)
        for dist in cls.OPTIONS.get("distribution", (None,)):
            out.append((k, name, {} if dist is None else {"distribution": dist}))
    return tuple((name, opts) for _, name, opts in sorted(out, key=lambda t: (t[0], t[1])))


CANDIDATES = _candidates()


def _transmission_candidates():
    """Every registered model that scatters through the surface (``Structure.sides`` holds
    transmission) with a finite f (``delta`` models, the smooth dielectrics, are left out),
    one per declared distribution: roughdielectric beckmann and ggx, difftrans, roughslab
    beckmann and ggx (a plate: frosted front, polished back)."""
    names = []
    for name in gm.names():
        try:
            model = gm.get(name)
        except (KeyError, ValueError):
            continue
        if Side.TRANSMIT in tuple(model.structure.sides) and not getattr(type(model), "delta", False):
            names.append(name)
    return _candidates(names) if names else ()


def _anisotropic_candidates():
    """Every auto candidate model that declares an ``anisotropic`` option, with it on, one per
    declared distribution (roughconductor beckmann and ggx)."""
    out = []
    for name, opts in CANDIDATES:
        cls = type(gm.get(name))
        if True in cls.OPTIONS.get("anisotropic", ()):
            out.append((name, {**opts, "anisotropic": True}))
    return tuple(out)


ANISOTROPIC = _anisotropic_candidates()


def _spectral_candidates(flag="spectral_candidate"):
    """Every registered model that declares ``flag`` (``spectral_candidate``: a colour that
    changes with angle needs a spectrum to be told from a fixed colour: flakepaint), one per
    declared option combination, simplest first."""
    out = []
    for name in gm.names():
        cls = type(gm.get(name))
        if not getattr(cls, flag, False):
            continue
        combos = [{}]
        for key, values in cls.OPTIONS.items():     # a ``REFINEMENTS`` value: auto's refinement only
            values = [v for v in values if (key, v) not in getattr(cls, "REFINEMENTS", ())]
            combos = [{**c, key: v} for c in combos for v in values]
        for opts in combos:
            model = gm.get(name, **opts)
            out.append((sum(3 if p.per_channel else 1 for p in model.parameters), name, opts))
    return tuple((name, opts) for _, name, opts in sorted(out, key=lambda t: t[0]))


#: the candidates ``--model auto`` adds on spectral data (``attrs["wavelengths_nm"]``)
SPECTRAL = _spectral_candidates()
#: ... and on goniochromic RGB data: SPECTRAL and the RGB-only ``goniochromic_candidate`` models
#: (gratingpaint: diffraction rings)
GONIOCHROMIC = SPECTRAL + _spectral_candidates("goniochromic_candidate")

#: :func:`azimuthal_structure`'s false-alarm probability on isotropic data whose sigma is
#: right (the chi^2 test's size; the relative floor below only lowers it)
FALSE_ALARM = 1e-3
#: relative floor added in quadrature to each point's sigma: systematics an uncertainty
#: budget may leave out (angle jitter on a lobe's flank), so that only a clear azimuthal
#: change counts (a brushed metal's lobe changes by factors, not per cent)
REL_FLOOR = 0.05


@dataclasses.dataclass(frozen=True)
class Azimuthal:
    """The outcome of :func:`azimuthal_structure`: chi^2 of the groups about their means, its
    degrees of freedom, the p-value under isotropy, the groups compared, and the verdict."""

    chi2: float
    dof: int
    p_value: float
    groups: int
    anisotropic: bool


def azimuthal_structure(meas, tol_deg: float = 0.5, rel_floor: float = REL_FLOOR,
                        false_alarm: float = FALSE_ALARM) -> Azimuthal:
    """Does ``meas`` show azimuthal structure? An isotropic BRDF depends on theta_i, theta_o
    and |phi_o - phi_i| only, so the used reflected points are grouped on those three (to
    ``tol_deg``) and the groups holding more than one azimuth phi_i (mod 180, more than 1 deg
    apart) compared with their weighted means: chi^2 = sum (f - mean)^2 / (sigma^2 +
    (rel_floor f)^2) per channel, dof = sum (n - 1). Anisotropic where the chi^2 upper tail
    p < ``false_alarm``; data without such groups (one plane of incidence, random directions)
    shows none (an azimuthal plan has them: the ``azimuthal`` preset)."""
    wi, wo = np.asarray(meas.wi, float), np.asarray(meas.wo, float)
    use = np.asarray(meas.use, bool) & (wi[:, 2:3] > 0) & (wo[:, 2:3] > 0)
    f, s = np.asarray(meas.brdf, float), np.asarray(meas.brdf_std, float)
    ti, pi = angles_deg(wi)
    to, po = angles_deg(wo)
    pd = np.abs((po - pi + 180.0) % 360.0 - 180.0)
    rows = np.flatnonzero(use.any(axis=1))
    key = np.round(np.c_[ti, to, pd][rows] / tol_deg).astype(np.int64)
    total, dof, groups = 0.0, 0, 0
    if rows.size:
        _, inv = np.unique(key, axis=0, return_inverse=True)
        for g in np.flatnonzero(np.bincount(inv.ravel()) > 1):
            k = rows[inv.ravel() == g]
            az = pi[k] % 180.0
            if min(np.ptp(az), np.ptp((az + 90.0) % 180.0)) <= 1.0:
                continue                                  # one azimuth: nothing to compare
            groups += 1
            for c in range(f.shape[1]):
                kk = k[use[k, c]]
                if kk.size < 2:
                    continue
                var = s[kk, c] ** 2 + (rel_floor * np.abs(f[kk, c])) ** 2
                if not np.all(var > 0):
                    continue                              # exact zeros without an uncertainty
                w = 1.0 / var
                m = np.sum(w * f[kk, c]) / np.sum(w)
                total += float(np.sum(w * (f[kk, c] - m) ** 2))
                dof += kk.size - 1
    p = float(_chi2.sf(total, dof)) if dof else 1.0
    return Azimuthal(total, dof, p, groups, bool(dof and p < false_alarm))


@dataclasses.dataclass(frozen=True)
class Goniochromism:
    """The outcome of :func:`goniochromism`: chi^2 of the colours about the best plane through
    black, its degrees of freedom, the p-value under a two-colour mixture, the points used, and
    the verdict."""

    chi2: float
    dof: int
    p_value: float
    points: int
    goniochromic: bool


def goniochromism(meas, rel_floor: float = REL_FLOOR, false_alarm: float = FALSE_ALARM,
                  snr: float = 3.0) -> Goniochromism:
    """Does ``meas`` (RGB) show a colour that changes with angle beyond a mixture of two fixed
    colours? A dielectric paint or plastic is its body colour plus the coat's colour, a metal
    its Fresnel colour moving toward white (Schlick's F0 + (1 - F0)(1 - cos)^5): every f_r then
    lies in the plane through black that those two colours span, its chromaticity on one line
    (Grassmann's law of additive mixture). An interference or flake paint's hue wanders off it.
    The used points with every channel above ``snr`` sigma, as unit colour vectors x = f / |f|,
    are fitted with that plane (normal n: the weighted smallest principal axis, reweighted
    twice); chi^2 = sum (n . x)^2 / var, var = sum_c n_c^2 (sigma_c^2 + (rel_floor f_c)^2) /
    |f|^2 (first order), dof = points - 2. Goniochromic where p < ``false_alarm``. Only RGB
    data: a spectrum's candidates already hold the flake paint."""
    f, s = np.asarray(meas.brdf, float), np.asarray(meas.brdf_std, float)
    if f.ndim != 2 or f.shape[1] != 3:
        return Goniochromism(0.0, 0, 1.0, 0, False)
    ok = np.asarray(meas.use, bool).all(axis=1) & np.all(np.isfinite(f) & np.isfinite(s), axis=1)
    ok &= np.all(f > snr * s, axis=1) & np.all(f > 0.0, axis=1)
    f, s = f[ok], s[ok]
    keep = np.all(s * s + (rel_floor * f) ** 2 > 0.0, axis=1)      # exact values without an uncertainty
    f, s = f[keep], s[keep]
    if f.shape[0] < 3:
        return Goniochromism(0.0, 0, 1.0, int(f.shape[0]), False)
    norm2 = np.sum(f * f, axis=1)
    x = f / np.sqrt(norm2)[:, None]
    var_c = (s * s + (rel_floor * f) ** 2) / norm2[:, None]
    w = np.ones(x.shape[0])
    for _ in range(3):      # the plane's normal, then the points weighted by 1 / var along it
        n = np.linalg.eigh((x * w[:, None]).T @ x)[1][:, 0]
        var = var_c @ (n * n)
        w = 1.0 / var
    chi2 = float(np.sum((x @ n) ** 2 / var))
    dof = int(x.shape[0] - 2)
    p = float(_chi2.sf(chi2, dof))
    return Goniochromism(chi2, dof, p, int(x.shape[0]), bool(p < false_alarm))


def candidates_for(meas):
    """The ``--model auto`` candidates for ``meas``: `CANDIDATES` for a BRDF, with the
    anisotropic ones (`ANISOTROPIC`) where the data shows azimuthal structure
    (:func:`azimuthal_structure`; never for data from a format that holds an isotropic BRDF,
    ``attrs["isotropic"]``: RGL, MERL); on spectral data (``attrs["wavelengths_nm"]``) the
    ``spectral_candidate`` models too (`SPECTRAL`), and on RGB data that shows a colour changing
    with angle (:func:`goniochromism`) those and the RGB-only ``goniochromic_candidate`` ones
    (`GONIOCHROMIC`); the transmission models when any used point lies on the
    transmitted side (a reflection model predicts 0 there, so it cannot explain those points
    and is not offered)."""
    used = np.asarray(meas.use).any(axis=1)
    side = side_of(np.asarray(meas.wi)[used, 2], np.asarray(meas.wo)[used, 2])
    if np.any(side == 1):
        return _transmission_candidates()
    if meas.attrs.get("wavelengths_nm"):
        base = CANDIDATES + SPECTRAL
    else:
        base = CANDIDATES + GONIOCHROMIC if goniochromism(meas).goniochromic else CANDIDATES
    if meas.attrs.get("isotropic"):     # a format that holds an isotropic BRDF (RGL, MERL): only noise to see
        return base
    return base + ANISOTROPIC if azimuthal_structure(meas).anisotropic else base


def option_candidates(name, options=None):
    """The candidates a named model stands for: one per declared microfacet distribution
    when ``options`` does not choose one (so that ``--model roughplastic`` on a GGX sample
    is not silently fitted as Beckmann), else just ``(name, options)``."""
    options = dict(options or {})
    allowed = type(gm.get(name, **options)).OPTIONS.get("distribution")
    if not allowed or "distribution" in options:
        return ((name, options),)
    return tuple((name, {**options, "distribution": d}) for d in allowed)


@dataclasses.dataclass
class Ranked:
    name: str
    options: dict
    k: int
    chi2: float
    bic: float
    delta_bic: float
    chosen: bool
    result: object = dataclasses.field(repr=False, default=None)
    loss: str = "chi2"
    neg2_loglik: float = 0.0
    delta_e: float | None = None      # rendered difference in the default scene (fitting.scene.rendered_choice)
    noise: float | None = None        # ... and its noise floor

    def row(self) -> dict:
        row = {"model": self.name, "options": self.options, "k": self.k, "chi2": self.chi2, "loss": self.loss,
               "neg2_loglik": self.neg2_loglik, "bic": self.bic, "delta_bic": self.delta_bic, "chosen": self.chosen}
        if self.delta_e is not None:
            row.update(delta_e=self.delta_e, noise=self.noise)
        return row


def _nested_start(model, rows):
    """A model that contains a simpler candidate already fitted (a two-lobe model and its
    single layer, ``start_from``) starts from that fit: a nested model must fit at least as
    well as the model it contains."""
    layer = getattr(model, "_layer", None)
    if not hasattr(model, "start_from") or layer is None:
        return None
    for r in rows:
        if r.name == layer.name and dict(r.result.model.options) == dict(layer.options):
            return model.start_from(r.result.params)
    return None


def candidate_rng(base: int, name: str, options: dict) -> np.random.Generator:
    """The Generator of one candidate's fit: seeded by ``base`` (one draw of the caller's
    Generator) and the candidate's name and options (CRC-32), so that a candidate's starts do
    not depend on which candidates were fitted before it, nor on how many draws they took."""
    key = zlib.crc32(repr((name, sorted((str(k), str(v)) for k, v in dict(options).items()))).encode())
    return np.random.default_rng([int(base), int(key)])


def select(meas, *, rng, candidates=None, delta: float = 2.0, progress=None, nested_starts=None, exact_tables=True,
           **fit_kwargs):
    """Fit each candidate and pick the simplest one the data supports.

    ``progress``: called as ``progress(done, total, label)`` before each candidate's fit and
    once at the end (a terminal's bar: gonio/cli/progress.py); None says nothing.
    ``nested_starts``: the global stage's starts (``fit``'s ``n_starts``) of a nested candidate
    started from its contained model's fit (:func:`_nested_start`); None: as every other.
    Each candidate's fit draws from its own Generator (:func:`candidate_rng`; one draw of ``rng``).
    ``exact_tables=False``: a model that takes the constructor keyword ``exact_tables``
    (roughplastic) is fitted on its precomputed table grid (a screen; its refit takes them exact).

    Returns
    -------
    best : FitResult
    ranking : list of Ranked
        Sorted by BIC, the chosen one flagged.
    """
    if nested_starts is not None and not (isinstance(nested_starts, (int, np.integer)) and nested_starts >= 0):
        raise ValueError(f"nested_starts = {nested_starts!r}: give a whole number of starts >= 0, or None")
    rows = []
    todo = tuple(candidates or candidates_for(meas))
    base = int(rng.integers(2 ** 63))
    for k, (name, options) in enumerate(todo):
        if progress is not None:
            progress(k, len(todo), f"{name} {' '.join(map(str, options.values()))}".strip())
        try:
            model = gm.get(name, **options)
        except (KeyError, ValueError):
            continue  # a candidate this build of gonio.models does not provide
        if not exact_tables and getattr(model, "exact_tables", False):
            model = type(model)(exact_tables=False, **model.options)
        start = _nested_start(model, rows)
        kw = fit_kwargs if start is None or nested_starts is None else {**fit_kwargs, "n_starts": int(nested_starts)}
        result = fit(meas, model, rng=candidate_rng(base, name, options), start=start, **kw)
        rows.append(Ranked(name, dict(options), result.space.size, result.chi2, result.bic, 0.0, False, result,
                           result.loss, result.neg2_loglik))
    if progress is not None:
        progress(len(todo), len(todo), "candidates fitted")
    if not rows:
        raise ValueError("no candidate model could be fitted")
    best_bic = min(r.bic for r in rows)
    for r in rows:
        r.delta_bic = r.bic - best_bic
    supported = [r for r in rows if r.delta_bic <= delta]
    chosen = min(supported, key=lambda r: (r.k, r.bic))
    chosen.chosen = True
    rows.sort(key=lambda r: r.bic)
    return chosen.result, rows


