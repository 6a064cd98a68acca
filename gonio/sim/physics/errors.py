"""Systematic errors of the virtual instrument: a seeded, documented error model.

Without it the simulator has only sensor noise. Each term is a frozen dataclass of
*distribution* parameters; :meth:`ErrorModel.draw` turns them, with the instrument's seed, into
one hidden truth (:class:`ErrorState`) that the instrument applies and a calibration tries to
recover. Terms (``[errors]`` of the instrument settings; ``preset`` then per-term tables
override it): ``stages`` (zero offsets, repeatability, backlash), ``alignment`` (holder tilt,
sample wedge), ``aperture`` (source and detector half-angles), ``stray`` (a stray-light floor),
``reference`` (the reference's true reflectance and non-Lambertian factor), ``linearity`` (the
detector's integral non-linearity). Presets: ``ideal`` switches every term off and reproduces
the error-free simulator bit for bit; ``typical`` is a well-built lab bench before its alignment
procedure; ``poor`` a hastily assembled one. They follow published figures for laboratory
goniometers (NIST STARR, PTB, Zaber data sheets, Spectralon, EMVA 1288). Each term's definition
and the sources: the comment below.
"""

# Why: without this model every stage sits exactly where commanded, the sample normal is exactly
# aligned, source and detector subtend zero solid angle, there is no stray light and the
# reference is what its certificate says. A real gonioreflectometer's budget is dominated by
# exactly those terms.
#
# Terms
# stages      zero offsets (1-sigma per axis, drawn once), repeatability (1-sigma per move, drawn
#             per move) and backlash (full lost motion; the load lags the motor by half of it in
#             the direction of the last move).
# alignment   the holder's normal tilted from the azimuth axis (tilt_deg, 1-sigma per component,
#             common to sample and reference) and the sample's own wedge (wedge_deg, its face
#             against its back; the sample square only).
# aperture    source and detector half-angles (uniform disks: a collimated LED with a field stop,
#             a camera lens pupil); the simulator integrates f_r cos(theta_i) over both (7-point
#             degree-5 disk rule each, Stroud 1971 S2 5-1, so 49 directions a pose); where f_r
#             jumps to 0 inside the cones (the rule's and six rim points of each disk, paired,
#             give both zero and non-zero values: a lobe's cutoff, a side's horizon) a 256-point
#             equal-weight sunflower rule on each disk instead (65 536 pairs).
# stray       a stray-light floor: radiance floor / pi per unit irradiance over the frame (light
#             scattered by the room and the lamp housing; the lamp-off darks miss it).
# reference   the reference's true reflectance drawn from its certificate
#             (rho_cert (1 + rel_std N(0, 1))) and its non-Lambertian factor (spectralon_factor
#             times non_lambertian).
# linearity   the detector's integral non-linearity: DN - black is compressed by
#             1 - gamma (DN - black) / (white - black) (gamma at full scale).
#
# Presets follow published figures for laboratory goniometers:
# * NIST STARR (Barnes, Early, Parr 1998, Appl. Opt. 37(28) 6655-6665; Proctor & Barnes 1996,
#   J. Res. NIST 101 619): angles set to about 0.01 deg, source and detector apertures of about
#   0.5-1 deg half-angle, combined reflectance uncertainty 0.1-0.6 % at k = 2.
# * PTB's robot gonioreflectometer (Huenerhoff, Grusemann, Hoepe 2006, Metrologia 43 S11-S16):
#   angular positioning to about 0.01-0.02 deg, alignment of the sample normal to a few
#   hundredths of a degree after a laser/mirror procedure (a few tenths before it), stray light
#   of order 1e-4.
# * Rotary stages of the Zaber X-RST/X-RSW class: repeatability < 0.02 deg, backlash < 0.05 deg,
#   home-sensor accuracy of about 0.1 deg (manufacturer data sheets).
# * Spectralon (Bruegge, Stiegman, Rainen, Springsteen 1993, Opt. Eng. 32(4) 805-814; Labsphere
#   technical guide "A guide to reflectance coatings and materials"): f_r departs from Lambertian
#   by about 1-2 % below 45 deg and up to several % at 70-75 deg; certificates state the
#   8 deg/hemispherical reflectance to about 0.5 % (k = 1).
# * Detector linearity: EMVA 1288 linearity errors of scientific CMOS/CCD of 0.1-0.5 %, consumer
#   sensors around 1 % near saturation.
#
# The lamp arm's zero offset defaults to 0 in every preset: a specular scan cannot separate it
# from the yaw offset (it finds yaw - lamp / 2); it is surveyed against the direct beam at
# assembly, and [errors.stages] zero_deg can set it to study that.

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

__all__ = ["StageErrors", "AlignmentErrors", "ApertureErrors", "StrayLight", "ReferenceErrors",
           "LinearityErrors", "ErrorModel", "ErrorState", "PRESETS", "spectralon_factor",
           "disk_rule", "error_model"]

_AXES = ("yaw", "tilt", "azimuth", "lamp")


@dataclass(frozen=True)
class StageErrors:
    """Stage angle errors, degrees.

    ``zero_deg``: 1-sigma of each axis's zero offset (yaw, tilt, azimuth, lamp), drawn once per
    instrument. ``repeat_deg``: 1-sigma of a move's end position, drawn per move.
    ``backlash_deg``: full lost motion on a reversal.
    """

    zero_deg: tuple = (0.0, 0.0, 0.0, 0.0)
    repeat_deg: float = 0.0
    backlash_deg: float = 0.0


@dataclass(frozen=True)
class AlignmentErrors:
    """Sample-normal misalignment, degrees, 1-sigma per component (two components each)."""

    tilt_deg: float = 0.0      # the holder's normal against the azimuth axis (sample and reference)
    wedge_deg: float = 0.0     # the sample's face against its back (sample square only)


@dataclass(frozen=True)
class ApertureErrors:
    """Finite source and detector solid angles: half-angles (deg) of uniform disks."""

    source_half_deg: float = 0.0
    detector_half_deg: float = 0.0
    profile: str = "uniform"


@dataclass(frozen=True)
class StrayLight:
    """Stray-light floor: added radiance ``floor / pi`` per unit irradiance (a white
    Lambertian's fraction) over the whole frame while the lamp is on."""

    floor: float = 0.0


@dataclass(frozen=True)
class ReferenceErrors:
    """The reference's truth: ``draw_certificate`` draws rho from the certificate's
    ``rel_std``; ``non_lambertian`` scales :func:`spectralon_factor`'s departure (0: Lambertian)."""

    draw_certificate: bool = False
    non_lambertian: float = 0.0


@dataclass(frozen=True)
class LinearityErrors:
    """Integral non-linearity of the detector: relative compression at full scale. ``gamma`` is
    the bound; ``drawn``: each instrument's own gamma is drawn uniformly in [0, gamma] (as the
    budget states it), else every instrument sits at the bound."""

    gamma: float = 0.0
    drawn: bool = False


_TERMS = {"stages": StageErrors, "alignment": AlignmentErrors, "aperture": ApertureErrors,
          "stray": StrayLight, "reference": ReferenceErrors, "linearity": LinearityErrors}


@dataclass(frozen=True)
class ErrorModel:
    """All error terms; ``preset`` names where they came from (overrides noted in ``overrides``)."""

    preset: str = "ideal"
    stages: StageErrors = StageErrors()
    alignment: AlignmentErrors = AlignmentErrors()
    aperture: ApertureErrors = ApertureErrors()
    stray: StrayLight = StrayLight()
    reference: ReferenceErrors = ReferenceErrors()
    linearity: LinearityErrors = LinearityErrors()

    @property
    def active(self) -> bool:
        """Whether any term is switched on (False: the error-free simulator, bit for bit)."""
        return self != replace(ErrorModel(), preset=self.preset)

    def to_dict(self) -> dict:
        """Plain tables (TOML-ready): ``preset`` and one table per term (``linearity.drawn`` only
        where true: the tables of files written before it existed stay equal)."""
        out = {"preset": self.preset}
        for name in _TERMS:
            d = asdict(getattr(self, name))
            out[name] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()
                         if not (name == "linearity" and k == "drawn" and v is False)}
        return out

    def draw(self, seed: int, rho_rel_std: float = 0.0) -> ErrorState:
        """The hidden truth of one instrument: ``default_rng([seed, 0xE770])``, fixed draw order."""
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0xE770])
        z = rng.standard_normal(4) * np.asarray(self.stages.zero_deg, float)
        tilt = rng.standard_normal(2) * self.alignment.tilt_deg
        wedge = rng.standard_normal(2) * self.alignment.wedge_deg
        n_rho = rng.standard_normal()
        rho_factor = 1.0 + rho_rel_std * n_rho if self.reference.draw_certificate else 1.0
        lin = self.linearity        # drawn last: the draws above stay those of a bound gamma
        gamma = lin.gamma * float(rng.random()) if lin.drawn else lin.gamma
        return ErrorState(model=self, seed=int(seed), zero_deg=tuple(float(v) for v in z),
                          tilt_deg=tuple(float(v) for v in tilt), wedge_deg=tuple(float(v) for v in wedge),
                          rho_factor=float(rho_factor), gamma=float(gamma))


PRESETS = {
    "ideal": ErrorModel(),
    "typical": ErrorModel(
        preset="typical",
        stages=StageErrors(zero_deg=(0.1, 0.1, 0.1, 0.0), repeat_deg=0.01, backlash_deg=0.02),
        alignment=AlignmentErrors(tilt_deg=0.2, wedge_deg=0.05),
        aperture=ApertureErrors(source_half_deg=0.5, detector_half_deg=0.5),
        stray=StrayLight(floor=1e-4),
        reference=ReferenceErrors(draw_certificate=True, non_lambertian=1.0),
        linearity=LinearityErrors(gamma=0.003)),
    "poor": ErrorModel(
        preset="poor",
        stages=StageErrors(zero_deg=(0.3, 0.3, 0.3, 0.0), repeat_deg=0.03, backlash_deg=0.1),
        alignment=AlignmentErrors(tilt_deg=0.5, wedge_deg=0.2),
        aperture=ApertureErrors(source_half_deg=1.5, detector_half_deg=1.5),
        stray=StrayLight(floor=1e-3),
        reference=ReferenceErrors(draw_certificate=True, non_lambertian=1.5),
        linearity=LinearityErrors(gamma=0.01)),
}


def _term(cls, base, table: dict, where: str):
    known = {f.name: f for f in fields(cls)}
    kw = {}
    for key, value in table.items():
        if key not in known:
            raise ValueError(f"{where}.{key} is not a setting of this term; use one of {', '.join(known)}")
        default = getattr(base, key)
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{where}.{key} must be true or false")
        elif isinstance(default, str):
            if value != "uniform":
                raise ValueError(f"{where}.{key}: only the uniform profile is simulated")
        elif isinstance(default, tuple):
            if (not isinstance(value, (list, tuple)) or len(value) != len(default)
                    or not all(_finite_nonneg(v) for v in value)):
                raise ValueError(f"{where}.{key} must be {len(default)} finite numbers >= 0 ({', '.join(_AXES)})")
            value = tuple(float(v) for v in value)
        else:
            if not _finite_nonneg(value):
                raise ValueError(f"{where}.{key} must be a finite number >= 0")
            value = float(value)
        kw[key] = value
    return replace(base, **kw)


def _finite_nonneg(v) -> bool:
    return (not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and v >= 0)


def error_model(spec=None) -> ErrorModel:
    """An :class:`ErrorModel` from a preset name, an ``[errors]`` table or None (ideal).

    A table holds ``preset`` (default ``ideal``) and per-term tables overriding the preset,
    e.g. ``{"preset": "typical", "stray": {"floor": 0.0}}``. Raises ValueError naming the bad key.
    """
    if spec is None:
        return PRESETS["ideal"]
    if isinstance(spec, ErrorModel):
        return spec
    if isinstance(spec, str):
        spec = {"preset": spec}
    if not isinstance(spec, dict):
        raise ValueError("[errors] must be a table or a preset name")
    name = spec.get("preset", "ideal")
    if name not in PRESETS:
        raise ValueError(f"[errors] preset {name!r} is unknown; use one of {', '.join(PRESETS)}")
    model = PRESETS[name]
    for key, table in spec.items():
        if key == "preset":
            continue
        if key not in _TERMS:
            raise ValueError(f"[errors] {key!r} is not an error term; use one of {', '.join(_TERMS)}")
        if not isinstance(table, dict):
            raise ValueError(f"[errors.{key}] must be a table")
        model = replace(model, **{key: _term(_TERMS[key], getattr(model, key), table, f"errors.{key}")})
    return model


# ----------------------------------------------------------------------------- physics pieces
def spectralon_factor(theta_i, theta_o, amplitude: float = 1.0):
    """Spectralon's f_r relative to a Lambertian of the same reflectance (angles in radians).

    ``1 + amplitude (-0.05 (sin^2 ti + sin^2 to) / 2 + 0.06 sin^2 ti sin^2 to)``: 1 at normal
    incidence and view, 0.99 at 40/0 deg, 0.978 at 70/0 deg, about 1.0 at 70/70 deg (the forward
    scatter at grazing angles), the size of the departures Bruegge et al. 1993 and Labsphere's
    BRDF data show. The functional form is gonio's smooth stand-in, not a published fit.
    """
    si2, so2 = np.sin(theta_i) ** 2, np.sin(theta_o) ** 2
    return 1.0 + amplitude * (-0.05 * 0.5 * (si2 + so2) + 0.06 * si2 * so2)


def disk_rule():
    """7-point degree-5 rule on the unit disk (Stroud 1971, S2 5-1): points (7, 2), weights (7,).

    Centre weight 1/4; six points at radius sqrt(2/3), weight 1/8 each; weights sum to 1 (the
    mean over the disk).
    """
    a = np.arange(6) * np.pi / 3
    r = math.sqrt(2.0 / 3.0)
    pts = np.vstack([[0.0, 0.0], np.stack([r * np.cos(a), r * np.sin(a)], -1)])
    return pts, np.array([0.25] + [0.125] * 6)


def _small_rotation(xy_deg) -> np.ndarray:
    """Rotation tilting +z by the small angles (about x, about y), degrees (Rx @ Ry)."""
    ax, ay = (math.radians(v) for v in xy_deg)
    cx, sx, cy, sy = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    return rx @ ry


def _cone(w: np.ndarray, half_rad: float, pts=None) -> np.ndarray:
    """Directions of the disk rule (or the unit-disk points ``pts``, (K, 2)) within ``half_rad``
    of the unit vector ``w``: (7, 3) or (K, 3)."""
    if half_rad <= 0.0:
        return w[None, :]
    t1 = np.cross(w, [1.0, 0.0, 0.0] if abs(w[0]) < 0.9 else [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(w, t1)
    pts = disk_rule()[0] if pts is None else pts
    d = w[None, :] + math.tan(half_rad) * (pts[:, :1] * t1 + pts[:, 1:] * t2)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


#: Six points on the rim of the unit disk: with the rule's seven they probe each cone for a cutoff.
_RIM = np.stack([np.cos(np.arange(6) * np.pi / 3 + np.pi / 6), np.sin(np.arange(6) * np.pi / 3 + np.pi / 6)], -1)
#: Points of the dense rule used where f_r jumps inside the cones (per disk; pairs = its square).
_DENSE_POINTS = 256


def _sunflower(n: int) -> np.ndarray:
    """``n`` equal-weight points on the unit disk, one per equal-area ring, turned by the golden
    angle (Vogel 1979, Math. Biosci. 44 179): a quasi-uniform rule for non-smooth integrands."""
    k = np.arange(n) + 0.5
    r, a = np.sqrt(k / n), k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(a), r * np.sin(a)], -1)


@dataclass(frozen=True)
class ErrorState:
    """One instrument's drawn errors (the hidden truth) and how to apply them."""

    model: ErrorModel
    seed: int
    zero_deg: tuple
    tilt_deg: tuple
    wedge_deg: tuple
    rho_factor: float
    #: the detector's integral non-linearity (None: the model's bound)
    gamma: float | None = None

    def to_dict(self) -> dict:
        """The truth as plain tables (for tests and the coverage study)."""
        return {"seed": self.seed, "zero_deg": list(self.zero_deg), "tilt_deg": list(self.tilt_deg),
                "wedge_deg": list(self.wedge_deg), "rho_factor": self.rho_factor, "gamma": self.linearity_gamma}

    @property
    def linearity_gamma(self) -> float:
        """This instrument's non-linearity: drawn (``LinearityErrors.drawn``) or the bound."""
        return self.model.linearity.gamma if self.gamma is None else self.gamma

    # ----------------------------------------------------------------- stages
    def axis_error_deg(self, i: int, moves: int, last_dir: int) -> float:
        """True minus commanded angle of axis ``i`` after its ``moves``-th move (deg)."""
        st = self.model.stages
        err = self.zero_deg[i] - 0.5 * st.backlash_deg * last_dir
        if st.repeat_deg > 0.0 and moves > 0:
            rng = np.random.default_rng([self.seed & 0xFFFFFFFF, 0xE771, i, int(moves)])
            err += st.repeat_deg * float(rng.standard_normal())
        return err

    @property
    def holder(self) -> np.ndarray | None:
        """Rotation of the holder's true frame in the azimuth stage's frame (None: aligned)."""
        return None if not any(self.tilt_deg) else _small_rotation(self.tilt_deg)

    # ----------------------------------------------------------------- squares
    def _aperture_mean(self, truth, wi, wo, frame=None):
        """Mean of f_r cos(theta_i) (3,) over the source and detector disks (square's face frame,
        ``frame`` its rotation in the holder), and the value the render shows (the point pair in
        the holder frame), from one evaluation of ``truth``."""
        ap = self.model.aperture
        hs, hd = math.radians(ap.source_half_deg), math.radians(ap.detector_half_deg)
        di, do = _cone(wi, hs), _cone(wo, hd)
        _, w = disk_rule()
        wa = w if len(di) > 1 else np.ones(1)
        wb = w if len(do) > 1 else np.ones(1)
        # the rule's pairs, then the rim probes (rule and rim points of both cones), then the point
        ri = np.vstack([di, _cone(wi, hs, _RIM)]) if len(di) > 1 else di
        ro = np.vstack([do, _cone(wo, hd, _RIM)]) if len(do) > 1 else do
        a = np.vstack([np.repeat(di, len(do), axis=0), np.repeat(ri, len(ro), axis=0), wi[None]])
        b = np.vstack([np.tile(do, (len(di), 1)), np.tile(ro, (len(ri), 1)), wo[None]])
        f = self._truth_cos(truth, a, b, frame)
        n = len(di) * len(do)
        probe = f[n:-1]
        if len(probe) > 1 and ((probe == 0.0).any(axis=0) & (probe != 0.0).any(axis=0)).any():
            # f_r jumps to 0 inside the cones (a lobe's cutoff, a side's horizon): the degree-5
            # rule weights a whole 1/64 of the pair space on each corner pair, so it is replaced
            # by the dense equal-weight rule (the mean over the two uniform disks)
            u = _sunflower(_DENSE_POINTS)
            si = _cone(wi, hs, u) if len(di) > 1 else di
            so = _cone(wo, hd, u) if len(do) > 1 else do
            fd = self._truth_cos(truth, np.vstack([np.repeat(si, len(so), axis=0), wi[None]]),
                                 np.vstack([np.tile(so, (len(si), 1)), wo[None]]), frame)
            return fd[:-1].mean(axis=0), f[-1]
        return np.einsum("k,kc->c", np.outer(wa, wb).ravel(), f[:n]), f[-1]

    @staticmethod
    def _truth_cos(truth, a, b, frame):
        """f_r cos(theta_i) of ``truth`` at the pairs (rows); all rows but the last (the point
        pair, in the holder frame) turned into the square's face frame (R.T @ v per row)."""
        if frame is not None:
            a = np.vstack([a[:-1] @ frame, a[-1:]])
            b = np.vstack([b[:-1] @ frame, b[-1:]])
        return np.asarray(truth(a, b), float) * np.maximum(a[:, 2], 0.0)[:, None]

    def sample_radiance(self, sample, wi, wo):
        """The sample square's true radiance per unit irradiance (3,) (wedge and apertures) and
        the rendered one (3,)."""
        frame = None if not any(self.wedge_deg) else _small_rotation(self.wedge_deg)
        return self._aperture_mean(sample.eval, wi, wo, frame)

    def reference_radiance(self, reference, wi, wo):
        """The reference square's (3,) (true rho, non-Lambertian factor, apertures) and the
        rendered one (3,)."""
        amp = self.model.reference.non_lambertian

        def truth(a, b):
            f = np.array(reference.eval(a, b), dtype=float)
            f[:-1] *= self.rho_factor
            if amp:
                ti = np.arccos(np.clip(a[:-1, 2], -1, 1))
                to = np.arccos(np.clip(b[:-1, 2], -1, 1))
                f[:-1] *= spectralon_factor(ti, to, amp)[:, None]
            return f
        return self._aperture_mean(truth, wi, wo)

    @property
    def squares_altered(self) -> bool:
        m = self.model
        return bool(any(self.wedge_deg) or m.aperture.source_half_deg or m.aperture.detector_half_deg
                    or self.rho_factor != 1.0 or m.reference.non_lambertian)

    def nonlinear(self, raw: np.ndarray, black: int, white: int) -> np.ndarray:
        """Apply the integral non-linearity to a raw frame (uint16 in, uint16 out)."""
        g = self.linearity_gamma
        if not g:
            return raw
        s = np.maximum(raw.astype(np.float64) - black, 0.0)
        out = black + s * (1.0 - g * s / (white - black))
        return np.clip(np.rint(np.where(raw > black, out, raw)), 0, white).astype(np.uint16)


def square_masks(geometry: dict, settings: dict) -> tuple[np.ndarray, np.ndarray]:
    """Pixels whose centre sees the sample / reference square (holder plane, orthographic).

    ``geometry``: ``wo``, ``right``, ``up`` in the holder frame; ``settings``: the instrument's
    ``camera`` and ``holder`` tables (``sim_pose`` moves the squares as the scene does).
    """
    cam, hold = settings["camera"], settings["holder"]
    W, H, s = int(cam["width"]), int(cam["height"]), float(cam["pixel_size"])
    r, c = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    wo, right, up = (np.asarray(geometry[k], float) for k in ("wo", "right", "up"))
    p = ((c - (W - 1) / 2) * s)[..., None] * right + (-(r - (H - 1) / 2) * s)[..., None] * up
    q = p - (p[..., 2] / wo[2])[..., None] * wo if abs(wo[2]) > 1e-9 else p
    dx, dy, ang = (float(v) for v in (hold.get("sim_pose") or (0.0, 0.0, 0.0)))
    ca, sa = math.cos(math.radians(ang)), math.sin(math.radians(ang))
    x, y = q[..., 0] - dx, q[..., 1] - dy
    x, y = ca * x + sa * y, -sa * x + ca * y          # into the holder's own frame
    half, off = float(hold["sample_half"]), float(hold["offset"])
    return ((np.abs(x + off) < half) & (np.abs(y) < half), (np.abs(x - off) < half) & (np.abs(y) < half))
