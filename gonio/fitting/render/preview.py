"""Preview renders: a sphere with the fitted model beside the same sphere with the measured data.

Two lightings, each a small Mitsuba 3 scene (a unit sphere seen by a 30-degree perspective
camera from 4.5 units, the ``direct`` integrator with MIS): ``env``, an analytic sky-like
environment with one soft bright "window"; ``area``, a small spherical area light up and to
the left plus a dim uniform fill. In both a white Lambertian surface facing the main light
has radiance of about 1, and linear sRGB 1 is the Lab reference white (Y = 1). Both sides
share the sampler seed, and the CIEDE2000 colour difference is computed per pixel on the
sphere only, on the linear images.

The measured side may be a :class:`~gonio.fitting.formats.MerlBRDF` (or a ``.binary`` path),
an RGL ``.bsdf`` path (or :class:`~gonio.fitting.formats.RGLBRDF`, through Mitsuba's
``measured`` plugin) or any Mitsuba BSDF dict. A Python BSDF is traced into the kernel in
``llvm_ad_rgb`` (fast); in ``scalar_rgb`` it is called per sample (slow).
"""

# env: a sky-like gradient, brighter above, and one soft bright window, built in numpy as a
# latitude-longitude envmap. Same seed on both sides: correlated noise. CIEDE2000 through
# colour-science: linear sRGB -> XYZ -> CIELAB under D65 -> colour.delta_E(method="CIE 2000");
# on the sphere only because the background is the same on both sides and would dilute the
# mean; on the linear images, not the clipped PNGs.
# A MERL table is rendered through a Python BSDF registered with mitsuba.register_bsdf that
# looks the table up with MERL's own index mapping; a BSDF dict may be of a BSDF the caller
# registered.

from __future__ import annotations

import contextlib
import errno
import itertools
import math
import threading
import time
from pathlib import Path

import numpy as np

import gonio.models as gm
from gonio.core.atomic import atomic_path
from gonio.models.mitsuba import bsdf_base, select_variant
from gonio.fitting.formats import MERL_SHAPE, RGLBRDF, MerlBRDF, check_rgl_file, read_merl

__all__ = ["BACKLIGHTS", "LIGHTINGS", "backlit_png", "delta_e_2000", "render_backlit", "matched_noise_floor", "measured_bsdf_dict", "panel_bsdf", "preview", "read_exr", "register_merl_bsdf", "render_sphere",
           "sphere_mask"]

LIGHTINGS = ("env", "area")
_FOV_DEG = 30.0
_DIST = 4.5
_RADIUS = 1.0
_AREA_DIST = 5.0
_AREA_RADIUS = 0.15
_AREA_DIR = np.array([-1.0, 1.0, 1.2]) / np.linalg.norm([-1.0, 1.0, 1.2])
_FILL = 0.03


# ---------------------------------------------------------------------------------------
# The MERL table as a Mitsuba BSDF (Python, Dr.Jit)
# ---------------------------------------------------------------------------------------
_MERL_TABLES: dict[str, np.ndarray] = {}
_MERL_REGISTERED: set[str] = set()
_MERL_PLUGIN = "gonio_merl_table"
_counter = itertools.count()


def _merl_class(mi, dr):
    n_th, n_td, n_pd = MERL_SHAPE
    half_pi = 0.5 * math.pi

    class MerlTableBSDF(bsdf_base(mi, dr)):
        """Nearest-bin look-up of a MERL table (BRDFRead.cpp's mapping), in gonio's convention:
        the light direction is Mitsuba's ``wo`` argument, the viewer's is ``si.wi``."""

        def __init__(self, props):
            super().__init__(props)
            key = props["table_key"]
            table = _MERL_TABLES[key]  # (3, n) f_r, 0 where the file has no data
            self.r = mi.Float(table[0].astype(np.float32))
            self.g = mi.Float(table[1].astype(np.float32))
            self.b = mi.Float(table[2].astype(np.float32))

        def _f(self, si, wo):
            wi_g, wo_g = wo, si.wi  # gonio: wi toward the light, wo toward the viewer
            h = dr.normalize(wi_g + wo_g)
            theta_h = dr.safe_acos(h.z)
            phi_h = dr.atan2(h.y, h.x)
            c, s = dr.cos(phi_h), dr.sin(phi_h)
            x = c * wi_g.x + s * wi_g.y
            y = -s * wi_g.x + c * wi_g.y
            z = wi_g.z
            ct, st = dr.cos(theta_h), dr.sin(theta_h)
            dx = ct * x - st * z
            dz = st * x + ct * z
            theta_d = dr.safe_acos(dz)
            phi_d = dr.atan2(y, dx)
            phi_d = dr.select(phi_d < 0, phi_d + dr.pi, phi_d)
            i_th = dr.clip(mi.Int32(dr.floor(n_th * dr.safe_sqrt(theta_h / half_pi))), 0, n_th - 1)
            i_td = dr.clip(mi.Int32(dr.floor(theta_d / half_pi * n_td)), 0, n_td - 1)
            i_pd = dr.clip(mi.Int32(dr.floor(phi_d / dr.pi * n_pd)), 0, n_pd - 1)
            idx = mi.UInt32(i_pd + n_pd * (i_td + n_td * i_th))
            return mi.Color3f(dr.gather(mi.Float, self.r, idx), dr.gather(mi.Float, self.g, idx),
                              dr.gather(mi.Float, self.b, idx))

        def to_string(self):
            return "MerlTableBSDF[]"

    return MerlTableBSDF


def _filled_table(merl) -> np.ndarray:
    """f_r (3, n) for rendering: a bin without data takes the value of the nearest bin with
    data at smaller theta_d (same theta_h, phi_d), 0 if there is none.

    Near grazing a bin whose centre lies below the horizon (no data) can still be reached by
    directions above it; without the fill the sphere's rim would render black.
    """
    table = merl.table  # (3, th, td, pd)
    valid = merl.valid  # (th, td, pd)
    td = np.arange(valid.shape[1])[None, :, None]
    last = np.where(valid, td, -1)
    last = np.maximum.accumulate(last, axis=1)  # index of the last valid theta_d so far
    src = np.clip(last, 0, None)
    filled = np.take_along_axis(table, np.broadcast_to(src, table.shape[1:])[None].repeat(3, 0), axis=2)
    filled = np.where((last >= 0)[None], filled, 0.0)
    return np.clip(filled, 0.0, None).reshape(3, -1).copy()


def register_merl_bsdf(merl, variant: str | None = None) -> dict:
    """Register (once per variant) the Python BSDF that evaluates MERL tables; return the
    ``mitsuba.load_dict`` dict of one that renders ``merl`` (a MerlBRDF or ``.binary`` path)."""
    import drjit as dr
    import mitsuba as mi

    if not isinstance(merl, MerlBRDF):
        merl = read_merl(merl)
    variant = select_variant(variant)
    with mi.scoped_set_variant(variant):
        if variant not in _MERL_REGISTERED:
            cls = _merl_class(mi, dr)
            mi.register_bsdf(_MERL_PLUGIN, lambda props: cls(props))
            _MERL_REGISTERED.add(variant)
    key = getattr(merl, "_gonio_preview_key", None)
    if key is None:
        key = f"merl{next(_counter)}"
        _MERL_TABLES[key] = _filled_table(merl)
        merl._gonio_preview_key = key
    return {"type": _MERL_PLUGIN, "table_key": key}


def measured_bsdf_dict(measured, variant: str | None = None) -> dict:
    """The Mitsuba dict for a measured-data argument of :func:`preview` (see module doc)."""
    if isinstance(measured, dict):
        return measured
    if isinstance(measured, MerlBRDF):
        return register_merl_bsdf(measured, variant)
    if isinstance(measured, RGLBRDF):
        return measured.mitsuba_dict()
    if isinstance(measured, (str, Path)):
        path = Path(measured)
        if not path.is_file():
            raise FileNotFoundError(f"measured data not found: {path}")
        if path.suffix.lower() == ".bsdf":
            check_rgl_file(path)
            return {"type": "measured", "filename": str(path)}
        if path.suffix.lower() == ".binary":
            return register_merl_bsdf(path, variant)
        raise ValueError(f"{path}: expected an RGL .bsdf or a MERL .binary file")
    raise TypeError(f"cannot render measured data of type {type(measured).__name__}:"
                    " give a MerlBRDF, an RGLBRDF, a .bsdf/.binary path or a Mitsuba BSDF dict")


# ---------------------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------------------
def _env_bitmap(width=256, height=128):
    """Analytic environment radiance on Mitsuba's latitude-longitude grid (Y up).

    Mitsuba's ``envmap`` looks a world direction v up at u = atan2(v.x, -v.z) / 2pi,
    v = acos(v.y) / pi; the same mapping is inverted here for the pixel centres.
    """
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    uu, vv = np.meshgrid(u, v)
    theta, phi = math.pi * vv, 2.0 * math.pi * uu
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], axis=-1)
    up = d[..., 1]
    sky = np.where(up > 0, 0.35 + 0.45 * up, 0.18 + 0.1 * up)[..., None] * np.array([0.9, 0.95, 1.05])
    window = np.array([-0.55, 0.6, 0.58])
    window /= np.linalg.norm(window)
    ang = np.arccos(np.clip(d @ window, -1, 1))
    lobe = 2.5 * np.exp(-0.5 * (ang / 0.18) ** 2)[..., None] * np.array([1.0, 0.97, 0.9])
    return (sky + lobe).astype(np.float32)


def _scene_dict(mi, lighting, bsdf, size, spp):
    to_cam = mi.ScalarTransform4f().look_at(origin=[0, 0, _DIST], target=[0, 0, 0], up=[0, 1, 0])
    scene = {
        "type": "scene",
        "integrator": {"type": "direct"},
        "sphere": {"type": "sphere", "radius": _RADIUS, "bsdf": bsdf},
        "camera": {"type": "perspective", "fov": _FOV_DEG, "fov_axis": "x", "to_world": to_cam,
                   "film": {"type": "hdrfilm", "width": size, "height": size, "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
    }
    if lighting == "env":
        scene["env"] = {"type": "envmap", "bitmap": mi.Bitmap(_env_bitmap())}
    elif lighting == "area":
        # radiance so that the irradiance on the sphere's point nearest the lamp (distance
        # d - R, facing it) is pi: E = L pi a^2 / (d - R)^2 -> a white Lambertian has
        # radiance ~1 there (plus the dim fill).
        radiance = ((_AREA_DIST - _RADIUS) / _AREA_RADIUS) ** 2
        scene["lamp"] = {"type": "sphere", "radius": _AREA_RADIUS,
                         "center": (_AREA_DIST * _AREA_DIR).tolist(),
                         "emitter": {"type": "area", "radiance": {"type": "rgb", "value": float(radiance)}}}
        scene["fill"] = {"type": "constant", "radiance": {"type": "rgb", "value": _FILL}}
    else:
        raise ValueError(f"lighting must be one of {LIGHTINGS}, got {lighting!r}")
    return scene


#: The backlights of :func:`render_backlit`: a checkered 6 x 6 one, or a uniform one of
#: radiance 1 that fills the panel's back hemisphere to 89 deg (200 x 200 at 1.5 units).
BACKLIGHTS = ("checks", "uniform")


def _backlit_dict(mi, bsdf, size, spp, backlight="checks"):
    """A transmitting panel (1.2 x 1.2, its lit face toward -z) 4 units in front of a 30-degree
    camera, lit from behind by a checkered backlight (6 x 6 at z = -1.5, radiance 1 and 0.1,
    facing the panel) that also shows around the panel; the ``path`` integrator (depth 4)
    follows light through smooth and rough interfaces alike."""
    T = mi.ScalarTransform4f
    if backlight == "uniform":
        lamp = {"type": "rectangle", "to_world": T().translate([0, 0, -1.5]) @ T().scale([100.0, 100.0, 1.0]),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}
    elif backlight == "checks":
        lamp = {"type": "rectangle", "to_world": T().translate([0, 0, -1.5]) @ T().scale([3.0, 3.0, 1.0]),
                "emitter": {"type": "area", "radiance": {
                    "type": "checkerboard", "color0": {"type": "rgb", "value": 0.1},
                    "color1": {"type": "rgb", "value": 1.0},
                    "to_uv": T().scale([6.0, 6.0, 1.0])}}}
    else:
        raise ValueError(f"backlight must be one of {BACKLIGHTS}, got {str(backlight)[:20]!r}")
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "panel": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], 180.0) @ T().scale([0.6, 0.6, 1.0]),
                  "bsdf": bsdf},
        "backlight": lamp,
        "camera": {"type": "perspective", "fov": _FOV_DEG, "fov_axis": "x",
                   "to_world": T().look_at(origin=[0, 0, 4.0], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
    }


def panel_bsdf(bsdf: dict) -> dict:
    """The backlit panel a BSDF dict stands for: a real panel is a plate in air, light entering
    its lit face and leaving its back into air on the camera's side. A single rough interface
    (``roughdielectric``) is rendered as that plate with its back polished (gonio's
    ``roughslab``, no absorption: the exit's Fresnel transmittance and the 1 / eta^2 of
    radiance leaving glass, Nicodemus 1963), a smooth one (``dielectric``) as Mitsuba's
    ``thindielectric`` (both faces polished); anything else as given (``thindielectric``,
    ``difftrans`` and ``roughslab`` are plates already). A single interface seen from the glass
    side shows radiance eta^2 too high (Veach 1997 eq. 5.9): 1.91 times the lamp for a GGX
    0.3, eta 1.5 panel, brighter than the lamp behind it."""
    if not isinstance(bsdf, dict):
        raise TypeError("the backlit panel is a Mitsuba BSDF dict")
    kind = bsdf.get("type")
    if kind not in ("roughdielectric", "dielectric"):
        return bsdf
    try:
        eta = float(bsdf.get("int_ior", 1.5)) / float(bsdf.get("ext_ior", 1.0))
    except (TypeError, ValueError, ZeroDivisionError):
        raise ValueError(f"backlit panel: a {kind}'s int_ior and ext_ior must be numbers (not a material's name)") from None
    if not (math.isfinite(eta) and eta > 1.0):
        raise ValueError(f"backlit panel: a {kind} with int_ior / ext_ior = {eta:.4g} is no plate in air; "
                         "give an index above the air's")
    if kind == "dielectric":
        return {"type": "thindielectric", "int_ior": eta, "ext_ior": 1.0}
    alpha = bsdf.get("alpha", 0.1)
    if not isinstance(alpha, (int, float)):
        raise ValueError("backlit panel: a roughdielectric with a textured alpha has no slab here; give a number")
    slab = gm.get("roughslab", distribution=bsdf.get("distribution", "beckmann"))
    return slab.to_mitsuba({"alpha": float(alpha), "int_ior": eta, "tau": 1.0})


def render_backlit(bsdf: dict, size: int = 128, spp: int = 64, seed: int = 0, variant: str | None = None,
                   backlight: str = "checks") -> np.ndarray:
    """The backlit scene (a lamp behind the sample, the camera in front: a diffuser, frosted
    glass or film as one sees it against a lit pattern); linear sRGB (size, size, 3). Seen
    through a clear panel the checks stay sharp; a rough one blurs and dims them by its
    transmittance. The panel's lit face (gonio's +z, a slab's frosted face) faces the lamp and
    the camera sees its back in air: :func:`panel_bsdf` renders a single interface as the plate
    it stands for. With ``backlight="uniform"`` the panel's radiance is its
    hemispherical-directional transmittance, the integral of f(wi, wo) cos theta_i over the
    lamp's side (tests/fitting/test_backlit_preview.py measures it)."""
    import mitsuba as mi

    variant = select_variant(variant)
    with mi.scoped_set_variant(variant):
        scene = mi.load_dict(_backlit_dict(mi, panel_bsdf(bsdf), int(size), int(spp), backlight))
        image = mi.render(scene, spp=int(spp), seed=int(seed))
        return np.array(image, dtype=np.float64).reshape(size, size, -1)[..., :3]


def backlit_png(models, path, size: int = 256, spp: int = 64, seed: int = 0, variant: str | None = None,
                titles=None) -> str:
    """A PNG of the backlit scene for each ``(model, params)`` in ``models``, side by side
    (:func:`render_backlit`, checkered backlight); with ``titles`` (one a model), a figure with
    each title above its panel."""
    images = [render_backlit(m.to_mitsuba(p), size, spp, seed, variant) for m, p in models]
    if titles is None:
        return _write_png(path, np.concatenate(images, axis=1))
    titles = [str(t) for t in titles]
    if len(titles) != len(images):
        raise ValueError(f"backlit_png: {len(titles)} titles for {len(images)} models; give one a model")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2.4 * len(images), 2.7), dpi=100)
    for k, (img, title) in enumerate(zip(images, titles)):
        ax = fig.add_subplot(1, len(images), k + 1)
        ax.imshow(_to_srgb8(img))
        ax.set_title(title, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    return _save_figure(fig, path)


def render_sphere(bsdf: dict, lighting: str = "env", size: int = 128, spp: int = 256, seed: int = 0,
                  variant: str | None = None) -> np.ndarray:
    """Render the preview sphere with a Mitsuba BSDF dict; linear sRGB image (size, size, 3)."""
    return _render_seeds(bsdf, lighting, size, spp, [seed], variant)[0]


def _render_seeds(bsdf, lighting, size, spp, seeds, variant=None):
    import mitsuba as mi

    variant = select_variant(variant)
    out = []
    with mi.scoped_set_variant(variant):
        scene = mi.load_dict(_scene_dict(mi, lighting, bsdf, int(size), int(spp)))
        for seed in seeds:
            image = mi.render(scene, spp=int(spp), seed=int(seed))
            out.append(np.array(image, dtype=np.float64).reshape(size, size, -1)[..., :3])
    return out


def matched_noise_floor(model_a, meas_a, model_b, meas_b) -> np.ndarray:
    """Per-pixel CIEDE2000 that Monte Carlo noise alone contributes to a matched-seed
    comparison (model and measured rendered with seed a; again with seed b).

    The difference image d = model - measured holds the BSDFs' true difference plus the
    noise that the matched seeds leave; (d_a - d_b) / sqrt(2) cancels the true difference
    and keeps one pair's noise. The floor is the CIEDE2000 between the measured render and
    the measured render plus that noise: comparing the model with itself at another seed (two
    independent renders) overstates it, so that "below the floor" would prove nothing."""
    e = ((model_a - meas_a) - (model_b - meas_b)) / np.sqrt(2.0)
    return delta_e_2000(meas_a, np.clip(meas_a + e, 0.0, None))


def sphere_mask(size: int) -> np.ndarray:
    """Pixels whose centre ray hits the sphere (the camera geometry of the preview scenes)."""
    t = math.tan(math.radians(_FOV_DEG) / 2)
    c = ((np.arange(size) + 0.5) / size - 0.5) * 2 * t
    x, y = np.meshgrid(c, c)
    return np.sqrt(x * x + y * y) < math.tan(math.asin(_RADIUS / _DIST))


# ---------------------------------------------------------------------------------------
# Colour difference and images
# ---------------------------------------------------------------------------------------
def delta_e_2000(rgb_a, rgb_b) -> np.ndarray:
    """Per-pixel CIEDE2000 between two linear-sRGB images (value 1 = reference white)."""
    import colour

    cs = colour.RGB_COLOURSPACES["sRGB"]

    def lab(rgb):
        xyz = colour.RGB_to_XYZ(np.clip(np.asarray(rgb, dtype=np.float64), 0.0, None), cs)
        return colour.XYZ_to_Lab(xyz, cs.whitepoint)

    return np.asarray(colour.delta_E(lab(rgb_a), lab(rgb_b), method="CIE 2000"), dtype=np.float64)


def _to_srgb8(rgb):
    x = np.clip(np.asarray(rgb, dtype=np.float64), 0.0, 1.0)
    x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(x * 255).astype(np.uint8)


def _save_figure(fig, path) -> str:
    """Lay ``fig`` out and write it to ``path`` atomically; the path as a string."""
    fig.tight_layout()
    with _atomic_image(path) as tmp:
        fig.savefig(tmp)
    return str(path)


@contextlib.contextmanager
def _atomic_image(path):
    """A temporary name beside ``path`` (same extension, for the writers that go by it),
    renamed to ``path`` when the block succeeds, removed when it fails: no half-written image."""
    try:
        with atomic_path(path, keep_suffix=True) as tmp:
            yield tmp
    except RuntimeError as exc:             # Mitsuba's Bitmap.write on a full disk
        raise OSError(errno.EIO, f"cannot write the image ({' '.join(str(exc).split())[:160]})", str(path)) from None


def _write_png(path, rgb):
    import matplotlib.image as mpimg

    with _atomic_image(path) as tmp:
        mpimg.imsave(tmp, _to_srgb8(rgb))
    return str(path)


_EXR_LOCK = threading.Lock()


@contextlib.contextmanager
def _exr_threads():
    """Mitsuba's OpenEXR reader and writer wait on a pool that has no worker when Dr.Jit's pool
    has a single thread (``GONIO_THREADS=1``, as the suite's xdist workers have): ``writePixels``
    and ``readPixels`` then wait forever (drjit 1.5, mitsuba 3.9.1, measured 2026-12-02). The
    pool has at least two threads inside this block."""
    import drjit as dr

    with _EXR_LOCK:
        threads = dr.thread_count()
        if threads < 2:
            dr.set_thread_count(2)
        try:
            yield
        finally:
            if threads < 2:
                dr.set_thread_count(threads)


def read_exr(path) -> np.ndarray:
    """An OpenEXR image written by the previews (or any RGB EXR), float32 (H, W, C), through
    Mitsuba's Bitmap, safe with any Dr.Jit thread count."""
    import mitsuba as mi

    with mi.scoped_set_variant(select_variant(None)), _exr_threads():
        return np.array(mi.Bitmap(str(path)))


def _write_exr(mi, path, rgb):
    """``rgb`` as an OpenEXR file through Mitsuba's Bitmap (:func:`_exr_threads`)."""
    with _exr_threads(), _atomic_image(path) as tmp:
        mi.Bitmap(np.ascontiguousarray(rgb, dtype=np.float32)).write(tmp)
    return str(path)


def _side_by_side(path, rows, with_measured):
    from matplotlib.figure import Figure

    ncols = 3 if with_measured else 1
    fig = Figure(figsize=(3.2 * ncols, 3.0 * len(rows)), dpi=100)
    axes = fig.subplots(len(rows), ncols, squeeze=False)
    for r, row in enumerate(rows):
        axes[r, 0].imshow(_to_srgb8(row["model"]))
        axes[r, 0].set_title(f"fitted model ({row['lighting']})", fontsize=9)
        if with_measured:
            axes[r, 1].imshow(_to_srgb8(row["measured"]))
            axes[r, 1].set_title(f"measured ({row['lighting']})", fontsize=9)
            im = axes[r, 2].imshow(row["delta_e"], cmap="magma", vmin=0, vmax=max(5.0, float(row["p95"])))
            axes[r, 2].set_title(f"CIEDE2000: mean {row['mean']:.2f}, p95 {row['p95']:.2f}", fontsize=9)
            fig.colorbar(im, ax=axes[r, 2], fraction=0.046, pad=0.04)
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    return _save_figure(fig, path)


def _delta_e_png(path, de, vmax):
    import matplotlib.image as mpimg

    with _atomic_image(path) as tmp:
        mpimg.imsave(tmp, de, cmap="magma", vmin=0.0, vmax=vmax)
    return str(path)


# ---------------------------------------------------------------------------------------
# The preview
# ---------------------------------------------------------------------------------------
def preview(model, params, out_dir, measured=None, size: int = 128, spp: int = 256, seed: int = 0,
            variant: str | None = None, lightings=LIGHTINGS, noise_floor: bool = True) -> dict:
    """Render the fitted model (and the measured data) on a sphere under two lightings.

    Parameters
    ----------
    model : gonio.models.Model
        The fitted model; ``model.to_mitsuba(params)`` is rendered.
    params : dict
        Its parameter values.
    out_dir : path
        Folder for the images (created).
    measured : MerlBRDF, RGLBRDF, path (.binary or .bsdf) or Mitsuba BSDF dict, optional
        The measured data, rendered the same way for comparison.
    size, spp, seed : int
        Image size (square), samples per pixel, sampler seed (the same on both sides).
    variant : str, optional
        Mitsuba variant (gonio's process choice when None).
    lightings : sequence of str
        Any of ``"env"``, ``"area"``.
    noise_floor : bool
        Render both sides again at ``seed + 1`` for the noise figures (half the time without;
        they are then None).

    Returns
    -------
    dict
        ``images[lighting]``: paths of ``model_exr``, ``model_png`` (and ``measured_exr``,
        ``measured_png``, ``delta_e_png`` with ``measured``); ``side_by_side_png``;
        ``delta_e[lighting] = {"mean", "p95", "noise_mean", "noise_p95"}`` (the noise
        figures: :func:`matched_noise_floor`, what Monte Carlo noise contributes to the
        comparison of model and measured rendered with the *same* seed) and overall ``delta_e_mean``, ``delta_e_p95``
        (over the sphere's pixels of all lightings; None without ``measured``); ``variant``,
        ``time_s``, ``size``, ``spp``, ``seed``.
    """
    import mitsuba as mi

    t0 = time.perf_counter()
    variant = select_variant(variant)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model_bsdf = model.to_mitsuba(params)
    measured_bsdf = None if measured is None else measured_bsdf_dict(measured, variant)
    mask = sphere_mask(size)
    images, stats, rows, all_de = {}, {}, [], []
    for lighting in lightings:
        entry = {}
        seeds = [seed, seed + 1] if noise_floor else [seed]
        img_model, *img_noise = _render_seeds(model_bsdf, lighting, size, spp, seeds, variant)
        entry["model_exr"] = _write_exr(mi, out_dir / f"{lighting}_model.exr", img_model)
        entry["model_png"] = _write_png(out_dir / f"{lighting}_model.png", img_model)
        row = {"lighting": lighting, "model": img_model}
        if measured_bsdf is not None:
            img_meas, *img_meas_noise = _render_seeds(measured_bsdf, lighting, size, spp, seeds, variant)
            entry["measured_exr"] = _write_exr(mi, out_dir / f"{lighting}_measured.exr", img_meas)
            entry["measured_png"] = _write_png(out_dir / f"{lighting}_measured.png", img_meas)
            de = np.where(mask, delta_e_2000(img_model, img_meas), 0.0)
            on = de[mask]
            stats[lighting] = {"mean": float(on.mean()), "p95": float(np.percentile(on, 95)), "noise_mean": None, "noise_p95": None}
            if noise_floor:
                noise = matched_noise_floor(img_model, img_meas, img_noise[0], img_meas_noise[0])[mask]
                stats[lighting].update(noise_mean=float(noise.mean()), noise_p95=float(np.percentile(noise, 95)))
            entry["delta_e_png"] = _delta_e_png(out_dir / f"{lighting}_delta_e.png", de,
                                                max(5.0, stats[lighting]["p95"]))
            all_de.append(on)
            row.update(measured=img_meas, delta_e=de, **stats[lighting])
        images[lighting] = entry
        rows.append(row)
    side = _side_by_side(out_dir / "side_by_side.png", rows, measured_bsdf is not None)
    every = np.concatenate(all_de) if all_de else None
    return {
        "images": images, "side_by_side_png": side, "delta_e": stats,
        "delta_e_mean": None if every is None else float(every.mean()),
        "delta_e_p95": None if every is None else float(np.percentile(every, 95)),
        "variant": variant, "time_s": time.perf_counter() - t0, "size": int(size), "spp": int(spp), "seed": int(seed),
    }
