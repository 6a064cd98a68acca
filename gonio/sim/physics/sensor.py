"""Camera sensor physics (Bayer mosaic, noise, quantisation) and the DNG writer.

For a pixel of colour channel k under the RGGB mosaic (row 0: R G, row 1: G B):

    camera RGB      L_k = sum_j (N A)_kj rho_j      (gonio/sim/physics/colour.py)
    mean electrons  mu = L_k * P * t * S * PRNU + i_dark * t
    electrons       e  = Poisson(mu) + DSNU + Normal(0, sigma_read)
    raw value       DN = clip(round(black + e / gain), 0, white)

rho_j: rendered linear-sRGB radiance for unit irradiance (sr^-1, f_r cos(theta_i)); P lamp power
(W), t exposure (s), S sensitivity, PRNU a fixed per-pixel gain (mean 1), DSNU a fixed per-pixel
offset (e-), both drawn once from the instrument seed. In DN a flat, dark-subtracted patch has
variance ``mean / gain + (sigma_read / gain)^2`` (+ the 1/12 quantisation). The default
``sensitivity`` fills half the well in 10 ms for a white Lambertian at normal incidence at full
power in the green channel. The DNG carries the colour tags of gonio/sim/physics/colour.py.
"""

# Details: N A is the camera's raw response per unit sRGB (the camera's spectral response,
# identity for camera="identity"); S is in electrons per W s sr^-1-normalised radiance. The
# photon transfer curve has slope 1 / gain. The default sensitivity: a white Lambertian sample
# (f_r = 1/pi) at normal incidence fills half the well in 10 ms at the lamp's full power p_ref in
# the camera's most sensitive channel (green; red and blue reach neutral times that). The DNG's
# colour tags: ColorMatrix1, CalibrationIlluminant1, AsShotNeutral, ForwardMatrix1.

from __future__ import annotations

import hashlib
import io
import json
import math
import os
from dataclasses import dataclass, field

import numpy as np
import tifffile

from gonio.core.atomic import atomic_open

from gonio.sim.physics.colour import DEFAULT_CAMERA, CameraColour, camera_colour

__all__ = ["SensorModel", "write_dng", "encode_dng", "SENSOR_SIZES", "sensor_size", "camera_table", "monochrome_qe"]


def monochrome_qe(nm: float) -> float:
    """The sensor's response to monochromatic light at ``nm`` relative to its response to the
    white LED, the same at every site (a spectral capture's camera has no colour filters): a
    front-illuminated silicon sensor's quantum efficiency, smooth, 1 at its 600 nm peak, 0.53 at
    400 nm, 0.85 at 700 nm (invented, of the shape of Sony's IMX sensors' published curves)."""
    return float(np.exp(-((float(nm) - 600.0) / 250.0) ** 2))

CFA = "RGGB"
#: The sizes the simulated camera offers, by name: ``(width, height, bits)``, all RGGB. ``ci`` is
#: the small default the test suite runs fast on; ``24mp`` a real camera's sensor: 6000 x 4000
#: 14-bit, the 24-megapixel APS-C format of current mirrorless and DSLR bodies (issue 40).
SENSOR_SIZES = {"ci": (64, 48, 14), "24mp": (6000, 4000, 14)}


def sensor_size(spec: str) -> tuple[int, int, int]:
    """``(width, height, bits)`` of a name of `SENSOR_SIZES` or of ``WIDTHxHEIGHT`` (14-bit); even
    sides from 16 to 12000 pixels (a whole number of 2 x 2 RGGB tiles). ValueError otherwise."""
    text = str(spec).strip().lower()
    if text in SENSOR_SIZES:
        return SENSOR_SIZES[text]
    try:
        w, h = (int(v) for v in text.split("x"))
    except ValueError:
        w = h = 0
    if not (16 <= w <= 12000 and 16 <= h <= 12000 and w % 2 == 0 and h % 2 == 0):
        raise ValueError(f"camera size {str(spec)[:40]!r}: give {', '.join(SENSOR_SIZES)} or WIDTHxHEIGHT, even, "
                         "16 to 12000 pixels (e.g. 6000x4000)")
    return w, h, 14


def camera_table(spec: str, camera: dict) -> dict:
    """The settings' ``[camera]`` table for the size ``spec`` (`sensor_size`), keeping ``camera``'s
    field of view: the pixel size (holder units per pixel) scales with the width."""
    w, h, bits = sensor_size(spec)
    px = float(camera["pixel_size"]) * float(camera["width"]) / w
    return {**camera, "width": w, "height": h, "bits": bits, "pixel_size": px}
_CFA_CODES = {"R": 0, "G": 1, "B": 2}


@dataclass
class SensorModel:
    """Noise and response parameters of the simulated camera.

    Parameters
    ----------
    width, height : int
        Pixels.
    bits : int
        ADC depth (12 or 14).
    black : int
        Black level, DN.
    gain : float
        Electrons per DN (e-/DN).
    read_noise : float
        Read noise, e- rms.
    dark_current : float
        Dark current, e-/s per pixel.
    dsnu : float
        Dark signal non-uniformity: standard deviation of the fixed per-pixel offset, e-.
    prnu : float
        Photo-response non-uniformity: relative standard deviation of the per-pixel gain.
    sensitivity : float or None
        Electrons per (W of lamp power * s * unit-irradiance radiance in sr^-1); None picks the
        half-well-at-10-ms value (module notes).
    p_ref : float
        Lamp power the default sensitivity refers to, W.
    seed : int
        Instrument seed; the fixed patterns come from ``default_rng([seed, 0x5E45])``.
    camera : str
        Whose spectral sensitivities (a name in colour-science's ``MSDS_CAMERA_SENSITIVITIES``),
        or ``"identity"`` (camera RGB = linear sRGB, the idealised camera).
    """

    width: int = 64
    height: int = 48
    bits: int = 14
    black: int = 512
    gain: float = 2.0
    read_noise: float = 3.0
    dark_current: float = 20.0
    dsnu: float = 1.5
    prnu: float = 0.01
    sensitivity: float | None = None
    p_ref: float = 0.01
    seed: int = 0
    camera: str = DEFAULT_CAMERA
    prnu_map: np.ndarray = field(init=False, repr=False)
    dsnu_map: np.ndarray = field(init=False, repr=False)
    colour: CameraColour = field(init=False, repr=False)

    def __post_init__(self):
        if self.bits not in (12, 14, 16):
            raise ValueError("bits must be 12, 14 or 16")
        if self.sensitivity is None:
            # half the well for f_r = 1/pi, cos(theta_i) = 1, P = p_ref, t = 10 ms
            self.sensitivity = 0.5 * self.full_well / ((1 / math.pi) * self.p_ref * 0.01)
        self.colour = camera_colour(self.camera)
        rng = np.random.default_rng([int(self.seed) & 0xFFFFFFFF, 0x5E45])
        shape = (self.height, self.width)
        self.prnu_map = 1.0 + self.prnu * rng.standard_normal(shape)
        self.dsnu_map = self.dsnu * rng.standard_normal(shape)

    @property
    def white(self) -> int:
        """White level (saturation), DN."""
        return 2 ** self.bits - 1

    @property
    def full_well(self) -> float:
        """Electrons that reach the white level, e-."""
        return (self.white - self.black) * self.gain

    @property
    def channel_map(self) -> np.ndarray:
        """(height, width) int array: 0 = R, 1 = G, 2 = B under the RGGB mosaic."""
        ch = np.empty((self.height, self.width), dtype=np.intp)
        ch[0::2, 0::2] = 0
        ch[0::2, 1::2] = 1
        ch[1::2, 0::2] = 1
        ch[1::2, 1::2] = 2
        return ch

    def mosaic(self, radiance_rgb: np.ndarray) -> np.ndarray:
        """Sample an (H, W, 3) linear-sRGB radiance image through the camera's spectral response
        and the RGGB mosaic -> (H, W) raw camera RGB.

        One position of the 2 x 2 tile at a time, with that channel's row of N A: no (H, W, 3)
        weight map (576 MB at 6000 x 4000); the same values as the per-pixel weights' sum."""
        out = np.empty(radiance_rgb.shape[:2])
        rows = self.colour.cam_from_srgb
        for dr, dc, k in ((0, 0, 0), (0, 1, 1), (1, 0, 1), (1, 1, 2)):
            out[dr::2, dc::2] = np.einsum("hwj,j->hw", radiance_rgb[dr::2, dc::2], rows[k])
        return out

    def mean_electrons(self, radiance_rgb: np.ndarray, power: float, exposure: float,
                       camera_rgb: bool = False) -> np.ndarray:
        """Expected photo + dark electrons per pixel (before DSNU), e-. ``camera_rgb``: the
        radiance is already raw camera RGB (a spectrally computed scene, e.g. the colour chart)."""
        if camera_rgb:
            ch = self.channel_map
            mosaic = np.take_along_axis(radiance_rgb, ch[..., None], axis=2)[..., 0]
        else:
            mosaic = self.mosaic(radiance_rgb)
        signal = mosaic * (power * exposure * self.sensitivity)
        np.maximum(signal, 0.0, out=signal)          # in place: no frame-sized temporaries (same values)
        signal *= self.prnu_map
        signal += self.dark_current * exposure
        return signal

    def expose(self, radiance_rgb: np.ndarray, power: float, exposure: float,
               rng: np.random.Generator, camera_rgb: bool = False) -> np.ndarray:
        """Simulate one raw frame.

        Parameters
        ----------
        radiance_rgb : (H, W, 3) array
            Radiance for unit irradiance, sr^-1 (f_r cos(theta_i) on the sample).
        power : float
            Lamp power during the exposure, W (0: a dark frame).
        exposure : float
            Exposure time, s.
        rng : numpy.random.Generator
            Source of shot and read noise for this frame.
        camera_rgb : bool
            ``radiance_rgb`` is raw camera RGB already (not linear sRGB).

        Returns
        -------
        (H, W) uint16 array
            Raw mosaic, DN.
        """
        mu = self.mean_electrons(radiance_rgb, power, exposure, camera_rgb)
        e = rng.poisson(mu).astype(np.float64)
        del mu
        # in place, the same draws and values as dsnu + normal(0, read_noise), black + e / gain:
        # a 6000 x 4000 frame made seven 192 MB temporaries
        read = rng.standard_normal(e.shape)
        read *= self.read_noise
        read += self.dsnu_map
        e += read
        del read
        e /= self.gain
        e += self.black
        np.rint(e, out=e)
        np.clip(e, 0, self.white, out=e)
        return e.astype(np.uint16)


def _rationals(values, signed: bool) -> tuple:
    """(numerator, denominator) pairs of a TIFF (S)RATIONAL array, 1e-7 resolution."""
    den = 10_000_000
    out = []
    for v in np.ravel(np.asarray(values, float)):
        num = int(round(float(v) * den))
        if not (-2 ** 31 < num < 2 ** 31) or (num < 0 and not signed):
            raise ValueError(f"colour tag value {v!r} does not fit a TIFF rational")
        out += [num, den]
    return tuple(out)


def encode_dng(raw: np.ndarray, *, black: int, white: int, exposure: float | None = None,
               model: str = "gonio SimCamera", description: dict | None = None,
               colour: CameraColour | None = None) -> bytes:
    """Encode a uint16 RGGB mosaic as DNG bytes (tifffile, tags rawpy/LibRaw reads).

    ``colour`` (default the identity camera) gives ColorMatrix1, AsShotNeutral and
    ForwardMatrix1 (gonio/sim/physics/colour.py); CalibrationIlluminant1 is D65 (21).
    """
    colour = colour if colour is not None else camera_colour("identity")

    extratags = [
        (50706, "B", 4, (1, 4, 0, 0), True),           # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),           # DNGBackwardVersion
        (50708, "s", 0, model, True),                  # UniqueCameraModel
        (33421, "H", 2, (2, 2), True),                 # CFARepeatPatternDim
        (33422, "B", 4, tuple(_CFA_CODES[c] for c in CFA), True),   # CFAPattern
        (50714, "I", 1, (int(black),), True),          # BlackLevel
        (50717, "I", 1, (int(white),), True),          # WhiteLevel
        (50721, "2i", 9, _rationals(colour.color_matrix, True), True),      # ColorMatrix1 (XYZ -> camera)
        (50728, "2I", 3, _rationals(colour.neutral, False), True),          # AsShotNeutral
        (50778, "H", 1, (21,), True),                                       # CalibrationIlluminant1 = D65
        (50964, "2i", 9, _rationals(colour.forward_matrix, True), True),    # ForwardMatrix1 (camera -> XYZ D50)
    ]
    if exposure is not None:
        num = int(round(exposure * 1_000_000))
        extratags.append((33434, "2I", 1, (num, 1_000_000), True))   # ExposureTime
    buf = io.BytesIO()
    tifffile.imwrite(
        buf, np.ascontiguousarray(raw, dtype=np.uint16), photometric=32803,
        description=json.dumps(description, sort_keys=True) if description else None,
        metadata=None, software="gonio.sim", extratags=extratags,
    )
    return buf.getvalue()


def write_dng(path: str | os.PathLike, data: bytes) -> str:
    """Write bytes atomically, not durably (:func:`gonio.core.atomic.atomic_open`,
    ``durable=False``). Returns their sha256 (hex).

    A camera (its tethering software) does not fsync for the bench: the bench checks the file
    against the SHA-256 the camera reported, then fsyncs it, renames it to its final name and
    fsyncs the folder (`gonio.bench.drivers.camera.Delivery.finish`), and only then journals the
    point. The file's fsync there writes its data to disk whoever wrote it, so the simulator's
    own fsyncs (file and folder, two of the four per frame) bought nothing: after a power cut
    before the bench's commit, the frame is a reserved ``.tmp-`` name that a resume removes and
    takes again, with or without them. The rename stays: the protocol's ``OK`` promises a whole
    file at the path, which another client may read at once."""
    with atomic_open(path, "wb", durable=False) as fh:
        fh.write(data)
    return hashlib.sha256(data).hexdigest()
