"""The simulated camera's colour: measured spectral sensitivities -> its matrices and its DNG tags.

The renderer works in linear sRGB; the simulator gives every sRGB triple rho one reflectance
spectrum, **linear** in it (Mallett & Yuksel 2019: ``R = sum_j rho_j B_j``), lit by D65, and a
camera with sensitivities ``S_k`` (colour-science ``MSDS_CAMERA_SENSITIVITIES``, default the
NPL-measured Nikon D5100) records ``raw = N A rho``: ``N = diag(neutral)`` its raw response to
white (max 1), ``A`` the white-balanced camera matrix (rows sum to 1). This 3x3 is *exact* for
every simulated surface: ``A^-1`` applied to white-balanced camera RGB gives the rendered sRGB
back to rounding; :func:`mallett_fidelity` and :func:`luther_error` measure what the model leaves
out. The DNG (Adobe DNG 1.4, chapter 6) declares ColorMatrix1 = ``N A M`` (XYZ -> camera, ``M``
colour-science's XYZ -> linear sRGB for D65), CalibrationIlluminant1 = 21 (D65), AsShotNeutral =
``neutral`` and ForwardMatrix1 = ``CAT(D65 -> D50) M^-1 A^-1`` (Bradford). References: Mallett &
Yuksel, EGSR 2019; Darrodi et al., JOSA A 32(3), 2015 (NPL sensitivities); Adobe DNG 1.4.0.0
(2012). Details: the comment below.
"""

# The colour model in full.
# The renderer works in linear sRGB (Mitsuba's rgb variants), so the virtual scene's radiance is
# an sRGB triple per pixel. A camera sees spectra, so the simulator gives every sRGB triple one
# reflectance spectrum, linear in it: Mallett and Yuksel's spectral primary decomposition (2019),
# R(lambda) = sum_j rho_j B_j(lambda) with their three basis spectra B_j (colour-science
# MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019; B_r + B_g + B_b = 1, so a grey of sRGB value v is the
# flat spectrum v). The scene is lit by a D65 source (the renderer's white), and a camera with
# sensitivities S_k records
#
#     raw_k = sum_j  [ integral S_k D65 B_j dlambda ]  rho_j  =  (N A rho)_k,
#
# N = diag(neutral) the camera's raw response to white (max 1: the DNG's AsShotNeutral) and A the
# white-balanced camera matrix (rows sum to 1: a neutral stays neutral). Because the spectra are
# linear in rho, this 3x3 is exact for every simulated surface.
#
# What the model leaves out (the error it makes): a Mallett spectrum's own sRGB under D65 is rho
# only to about 1 % (its basis reproduces the sRGB primaries to 0.85 % at most;
# mallett_fidelity measures it), and real surfaces are not Mallett spectra, so a real camera that
# misses the Luther condition maps metamers differently. luther_error measures the second for
# the 24 ColorChecker spectra (Ohta): the mean CIEDE2000 of A^-1 applied to the camera's spectral
# response against the patches' own sRGB.
#
# DNG: AsShotNeutral = neutral (ColorMatrix1 maps the D65 white, Y = 1, onto it); ForwardMatrix1
# maps white-balanced camera RGB to XYZ of the D50 PCS (Bradford). LibRaw turns ColorMatrix1
# into color_matrix = A^-1 (camera -> sRGB, rows summing to 1) by the same algebra (dcraw's
# cam_xyz_coeff).
#
# References
# Mallett, I., Yuksel, C. (2019). Spectral Primary Decomposition for Rendering with sRGB
# Reflectance. EGSR 2019 (DL-only track). doi:10.2312/sr.20191216
# Darrodi, M. M., Finlayson, G., Goodman, T., Mackiewicz, M. (2015). Reference data set for
# camera spectral sensitivity estimation. JOSA A 32(3), 381-391 (the NPL sensitivities).
# Adobe (2012). Digital Negative (DNG) Specification 1.4.0.0, "Mapping Camera Color Space to CIE
# XYZ Space".

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["CHART_BOX", "CHART_BORDER", "CHART_GRID", "CameraColour", "DEFAULT_CAMERA", "IDENTITY_CAMERA",
           "camera_colour", "chart_radiance", "luther_error", "mallett_fidelity", "srgb_matrices", "source_spd",
           "SOURCE_K"]

#: The camera whose NPL-measured sensitivities the simulator uses by default.
DEFAULT_CAMERA = "Nikon 5100 (NPL)"
#: Wavelength grid of every integral, nm (the sensitivities' own 380-780 nm at 5 nm).
_SHAPE = (380.0, 780.0, 5.0)


#: colour-science's numbers that every simulated capture needs (the sRGB matrix, the Bradford
#: D65 -> D50 adaptation, the default camera's ``A`` and ``N``), tabulated so that starting the
#: simulator does not import colour-science, which imports matplotlib (1.5 s of a 6 s quick
#: capture). Written by ``python -m gonio.sim.physics.colour --tabulate`` from colour-science itself
#: (:func:`computed_tables`); tests/sim/test_sim_colour.py checks that the stored values equal a
#: fresh computation with the installed colour-science.
TABLES = Path(__file__).parent / "data" / "colour_tables.json"


@functools.lru_cache(maxsize=1)
def _tables() -> dict:
    return json.loads(TABLES.read_text(encoding="utf-8"))


def computed_tables() -> dict:
    """What :data:`TABLES` holds, computed now with colour-science."""
    import colour

    to_xyz = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ, float)
    white = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]
    cat = colour.adaptation.matrix_chromatic_adaptation_VonKries(
        colour.xy_to_XYZ(white["D65"]), colour.xy_to_XYZ(white["D50"]), transform="Bradford")
    cam = _camera_colour_computed(DEFAULT_CAMERA)
    return {"colour_science": colour.__version__,
            "srgb_to_xyz": to_xyz.tolist(),
            "bradford_d65_to_d50": np.asarray(cat, float).tolist(),
            "cameras": {DEFAULT_CAMERA: {"balanced": cam.balanced.tolist(), "neutral": cam.neutral.tolist()}}}


def srgb_matrices() -> tuple[np.ndarray, np.ndarray]:
    """colour-science's linear sRGB -> XYZ matrix (D65, from the IEC 61966-2-1 primaries; tabulated
    in :data:`TABLES`) and its inverse."""
    to_xyz = np.array(_tables()["srgb_to_xyz"], float)
    return to_xyz, np.linalg.inv(to_xyz)        # the exact inverse (colour ships IEC's rounded one)


@dataclass(frozen=True)
class CameraColour:
    """A camera's colour response to the renderer's linear sRGB (module notes).

    Attributes
    ----------
    name : str
        Where the sensitivities come from (``"identity"``: the idealised camera of old).
    balanced : ndarray (3, 3)
        ``A``: white-balanced camera RGB per unit linear sRGB (rows sum to 1).
    neutral : ndarray (3,)
        Raw response to white (max 1): the DNG's AsShotNeutral.
    """

    name: str
    balanced: np.ndarray
    neutral: np.ndarray

    @property
    def cam_from_srgb(self) -> np.ndarray:
        """Raw camera RGB per unit linear sRGB radiance, ``N A``."""
        return self.neutral[:, None] * self.balanced

    @property
    def srgb_from_cam(self) -> np.ndarray:
        """White-balanced camera RGB -> linear sRGB, ``A^-1`` (what the bench must apply)."""
        return np.linalg.inv(self.balanced)

    @property
    def color_matrix(self) -> np.ndarray:
        """DNG ColorMatrix1: CIE XYZ (D65) -> raw camera RGB, ``N A M``."""
        return self.cam_from_srgb @ srgb_matrices()[1]

    @property
    def forward_matrix(self) -> np.ndarray:
        """DNG ForwardMatrix1: white-balanced camera RGB -> XYZ of the D50 PCS (Bradford, as
        colour-science computes it; tabulated in :data:`TABLES`)."""
        cat = np.array(_tables()["bradford_d65_to_d50"], float)
        return cat @ srgb_matrices()[0] @ self.srgb_from_cam

    def white_balanced(self, sd) -> np.ndarray:
        """White-balanced camera RGB of a reflectance spectrum (or a multi-spectral set) under D65,
        by spectral integration (no Mallett model): what the camera records of a real surface."""
        sens, illum = _spectral(self.name)
        values = _align(sd)
        raw = (values.T if values.ndim == 2 else values[None]) @ (sens * illum[:, None])
        return raw / (illum @ sens)


def _align(sd) -> np.ndarray:
    import colour

    shape = colour.SpectralShape(*_SHAPE)
    return np.asarray(sd.copy().align(shape).values, float)


@functools.lru_cache(maxsize=4)
def _spectral(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(sensitivities (n, 3), D65 (n,)) of a camera on the module's grid."""
    import colour

    if name not in colour.MSDS_CAMERA_SENSITIVITIES:
        raise ValueError(f"unknown camera {name!r}; colour-science has {', '.join(colour.MSDS_CAMERA_SENSITIVITIES)}")
    return _align(colour.MSDS_CAMERA_SENSITIVITIES[name]), _align(colour.SDS_ILLUMINANTS["D65"])


@functools.lru_cache(maxsize=4)
def camera_colour(name: str = DEFAULT_CAMERA) -> CameraColour:
    """The :class:`CameraColour` of a camera colour-science ships sensitivities of (or
    ``"identity"``); the default camera's from :data:`TABLES`."""
    if name == "identity":
        return IDENTITY_CAMERA
    stored = _tables()["cameras"].get(name)
    if stored is not None:
        return CameraColour(name, np.array(stored["balanced"], float), np.array(stored["neutral"], float))
    return _camera_colour_computed(name)


def _camera_colour_computed(name: str) -> CameraColour:
    import colour

    sens, illum = _spectral(name)
    basis = _align(colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019)
    raw = sens.T @ (illum[:, None] * basis)          # raw[k, j] = integral S_k D65 B_j
    white = raw.sum(1)                               # the basis sums to the flat spectrum 1
    return CameraColour(name, raw / white[:, None], white / white.max())


IDENTITY_CAMERA = CameraColour("identity", np.eye(3), np.ones(3))


def _delta_e(srgb_a, srgb_b) -> np.ndarray:
    import colour

    to_xyz = srgb_matrices()[0]
    white = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    lab = [colour.XYZ_to_Lab(np.asarray(v, float) @ to_xyz.T, white) for v in (srgb_a, srgb_b)]
    return np.asarray(colour.delta_E(*lab, method="CIE 2000"), float)


def mallett_fidelity(rho) -> float:
    """CIEDE2000 between linear sRGB ``rho`` and the D65 sRGB of its Mallett spectrum."""
    import colour

    basis = _align(colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019)
    cmfs = _align(colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"])
    illum = _spectral(DEFAULT_CAMERA)[1]
    spectrum = basis @ np.asarray(rho, float)
    xyz = cmfs.T @ (illum * spectrum) / (cmfs[:, 1] @ illum)
    return float(_delta_e(rho, srgb_matrices()[1] @ xyz))


def luther_error(camera: CameraColour) -> np.ndarray:
    """Per-patch CIEDE2000 of ``A^-1`` on the camera's spectral response to the 24 ColorChecker
    (Ohta) reflectances, against the patches' own sRGB under D65: the metamerism error of the
    3x3 (0 for the identity camera, which has no spectra)."""
    import colour

    if camera.name == "identity":
        return np.zeros(24)
    sds = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    cmfs = _align(colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"])
    illum = _spectral(camera.name)[1]
    refl = np.stack([_align(sd) for sd in sds.values()], 1)            # (n, 24)
    truth = (refl.T @ (cmfs * illum[:, None])) / (cmfs[:, 1] @ illum) @ srgb_matrices()[1].T
    est = camera.white_balanced(colour.MultiSpectralDistributions(
        refl, colour.SpectralShape(*_SHAPE).wavelengths)) @ camera.srgb_from_cam.T
    return _delta_e(est, truth)


#: Where the holder's ColorChecker slot puts the chart in the camera frame: the box (fractions of
#: width and height: left, top, right, bottom) holding its 6 x 4 patches; each patch is its grid
#: cell less a 15 % black border on every side (the bench reads the same declared geometry).
CHART_BOX = (0.1, 0.1, 0.9, 0.9)
CHART_GRID = (4, 6)
CHART_BORDER = 0.15
#: The chart's spectra: the 24 ColorChecker reflectances measured by Ohta (colour-science).
CHART_SPECTRA = "ColorChecker N Ohta"


def chart_radiance(camera: CameraColour, height: int, width: int) -> np.ndarray:
    """Raw camera RGB (H, W, 3) of the ColorChecker in its slot, lit at normal incidence by unit
    irradiance (Lambertian: reflectance / pi per sr), by spectral integration of the Ohta spectra
    (not through the Mallett model: the chart is a real surface). The borders and the
    surround are black (reflectance 0.03)."""
    import colour

    sds = colour.SDS_COLOURCHECKERS[CHART_SPECTRA]
    patches = camera.white_balanced(colour.MultiSpectralDistributions(
        np.stack([_align(sd) for sd in sds.values()], 1), colour.SpectralShape(*_SHAPE).wavelengths))
    img = np.full((height, width, 3), 0.03 / np.pi) * camera.neutral
    rows, cols = CHART_GRID
    x0, y0, x1, y1 = CHART_BOX
    ch, cw = (y1 - y0) * height / rows, (x1 - x0) * width / cols
    yy, xx = np.mgrid[0:height, 0:width] + 0.5
    for k in range(rows * cols):
        r, c = divmod(k, cols)
        top, left = y0 * height + r * ch, x0 * width + c * cw
        inside = ((yy > top + CHART_BORDER * ch) & (yy < top + (1 - CHART_BORDER) * ch)
                  & (xx > left + CHART_BORDER * cw) & (xx < left + (1 - CHART_BORDER) * cw))
        img[inside] = patches[k] * camera.neutral / np.pi
    return img


#: Colour temperature of the monochromator's source, K: a quartz-tungsten-halogen lamp
#: (Newport's Cornerstone systems' usual source; a 3200 K filament, invented figure).
SOURCE_K = 3200.0


def _planck(nm):
    x = 1.438776877e7 / (np.asarray(nm, float) * SOURCE_K)         # c2 / (lambda T), c2 in nm K
    return np.asarray(nm, float) ** -5.0 / np.expm1(x)


#: `source_spd` is 1 on average over 400-700 nm (1 nm steps)
_SPD_NORM = float(np.mean(_planck(np.arange(400.0, 701.0))))


def source_spd(nm: float) -> float:
    """The monochromator's output at ``nm`` relative to the LED's power (its mean over 400-700 nm
    is 1): Planck's law at :data:`SOURCE_K` (at 400 nm 0.23, at 550 nm 1.01, at 700 nm 1.75)."""
    return float(_planck(nm) / _SPD_NORM)


if __name__ == "__main__":  # python -m gonio.sim.physics.colour --tabulate: rewrite TABLES from colour-science
    import sys

    from gonio.core.atomic import atomic_open

    if sys.argv[1:] != ["--tabulate"]:
        sys.exit("usage: python -m gonio.sim.physics.colour --tabulate")
    with atomic_open(TABLES, "w") as fh:
        fh.write(json.dumps(computed_tables(), indent=1) + "\n")
