"""Model ``tabulated``: an isotropic microfacet BRDF with a data-driven (tabulated) NDF.

    f_c(wi, wo) = rho_c / pi + F_c(cos theta_d) D_c(theta_h) G1_c(wi) G1_c(wo) / (4 cos_i cos_o)

per colour channel c (Dupuy et al. 2015), wh the half vector. D_c: piecewise linear in ln D on
:data:`N_KNOTS` warped knots theta_k = (pi/2) (k / (K-1))^2 (``ndf_k`` = ln(D(theta_k) / D(0)),
k >= 1, plus a colour tilt for red and blue), normalised per channel (Walter et al. 2007,
eq. 4); G1_c: Smith's, derived from D_c (Heitz 2014, eq. 43); F_c: piecewise linear on
:data:`N_FRESNEL` knots in 1 - cos theta_d (``fresnel_j`` in [0, 1]); ``width_j``: a lobe width
factor w(theta_d); rho_c: ``diffuse_reflectance`` (option ``body="table"``: rho_c g(theta_i)
g(theta_o) / pi, g a data-driven table, see the notes). Reciprocal and non-negative, not energy
conserving (``energy_conserving = False``: the fit enforces albedo <= 1). Not a ``--model auto``
candidate from its defaults (``auto_candidate = False``):
:func:`gonio.fitting.optimise.tabulated_start.fit_tabulated` starts it from the data. Rendered
by ``gonio_tabulated`` (:mod:`gonio.models.mitsuba.tabulated_plugin`); notes: the comment below.
"""

# Design notes (measured figures: docs/performance.md, gonio.models.catalogue.tabulated).
#
# Why: measured glossy paints have specular peaks that no analytic distribution follows, a sharp
# bright core on a wide halo. Dupuy et al. (2015) recover such a distribution from the data and
# derive the shadowing from it; this model does the same with an NDF whose knots are fit
# parameters. theta_h is the half vector's polar angle, cos theta_d = wi . wh.
#
# * D_c: K = N_KNOTS = 16 knots at 0, 0.4, 1.6, 3.6, 6.4, 10, ... 90 deg, so the core is
#   resolved. ln D(0) = 0 before normalisation, so that the scale, which the normalisation
#   fixes, is not a parameter. D_c is divided by Z_c = 2 pi int D cos(theta) sin(theta) d(theta),
#   so that the integral of D cos(theta_h) over the hemisphere is 1 (Walter et al. 2007, eq. 4).
#   The NDF differs per channel in measured data, so ln D_c = ln D + t_c(k) with a colour tilt
#   t_c for red and blue (t_g = 0), piecewise linear in the knot index through 0 at the normal
#   and three parameters at 6.4, 40 and 90 deg: 20 numbers, where 45 independent per-channel
#   knots left gonio's Levenberg-Marquardt stalled by the directions the data do not see. Each
#   channel is normalised on its own.
# * G1_c (Heitz 2014, eq. 43; Dupuy et al. 2015, sec. 4): G1(w) = cos(theta) / A(theta),
#   A(theta) = int max(0, w . m) D(m) dm, the projected area of the microsurface. The azimuthal
#   integral of max(0, a + b cos phi) is closed-form (2 (a phi_c + b sin phi_c),
#   cos phi_c = -a/b), the polar one is Gauss-Legendre on every knot interval (N_GAUSS nodes
#   each); A is tabulated at N_G directions (dense toward grazing) whenever the parameters
#   change and G1 is interpolated linearly in between. A(theta) >= cos(theta) for a normalised
#   D, so 0 <= G1 <= 1.
# * F_c: N_FRESNEL = 5 uniform knots in x = 1 - cos(theta_d) (theta_d = 0, 41.4, 60, 75.5,
#   90 deg), per channel, in [0, 1]: the colour change toward grazing (e.g. the whitening of a
#   clear coat).
# * w(theta_d): tabulated like F (width_j, j >= 1; w = 1 at theta_d = 0, shared by the
#   channels): D is evaluated at theta_h / w and divided by w^2 (its normalisation for narrow
#   lobes), because measured lobes broaden toward grazing. With w != 1 the lobe is no longer one
#   microsurface: G1 stays the Smith G1 of the base D (w = 1), an approximation the data-driven
#   term accepts.
# * Body (option body="table", issue 35): rho_c g(theta_i) g(theta_o) / pi, g piecewise linear in
#   theta on N_BODY = 5 knots (0, 20, 40, 60, 80 deg; g(0) = 1, so rho_c stays the reflectance at
#   normal incidence and view; held beyond 80 deg, where the RGL files have no data), shared by
#   the channels. A product of one factor per direction is reciprocal and non-negative; it is
#   the form of Burley's (2012) diffuse, (1 + (F_D90 - 1)(1 - cos)^5) per direction, and of
#   Wolff's (1994) Fresnel-transmission diffuse, here read from the data. Why: felt's body is
#   not Lambertian (pi f at normal incidence falls 0.78 -> 0.55 from theta_o = 0 to 75 deg)
#   and tabulated's broad lobe stood in for it. Knots to 80 deg, not to 90: a free g(90 deg)
#   is unseen, and its fitted value raised the albedo past 1 (docs/performance.md).
# * Energy: every factor is symmetric in wi, wo. With w = 1 the lobe's albedo is at most max F_c
#   (Smith's G1 and a normalised D), the body adds rho_c, so the sum can exceed 1 (and w != 1
#   moves the lobe's albedo too); gonio's fit applies its albedo <= 1 constraint
#   (enforce_energy).
# * Selection: selection fits candidates from their defaults (a GGX table), and this model's 42
#   numbers weigh 42 ln n in BIC, hence auto_candidate = False. --model auto fits it from the
#   data only where no candidate renders within CIEDE2000 1 of the measured file in the default
#   scene (gonio.fitting.selection.by_scene.data_driven, the fallback of
#   gonio.fitting.selection.by_scene.rendered_choice), and chooses it where it renders clearly
#   closer.
# * Rendering: the plugin uses the same tables and interpolation in Dr.Jit; it samples a mixture
#   of the channels' mean D and cosine-weighted directions.
#
# References
# Dupuy, J., Heitz, E., Iehl, J.-C., Poulin, P., Ostromoukhov, V. (2015). Extracting
# microfacet-based BRDF parameters from arbitrary materials with power iterations. Computer
# Graphics Forum 34(4) (EGSR), 21-30.
# Heitz, E. (2014). Understanding the masking-shadowing function in microfacet-based BRDFs.
# JCGT 3(2), 48-107.
# Walter, B., Marschner, S. R., Li, H., Torrance, K. E. (2007). Microfacet models for
# refraction through rough surfaces. EGSR.
# Burley, B. (2012). Physically-based shading at Disney. SIGGRAPH course notes, sec. 5.3.
# Wolff, L. B. (1994). Diffuse-reflectance model for smooth dielectric surfaces. JOSA A 11(11).

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from gonio.models.base import CHANNELS, Model, Parameter, register
from gonio.models.catalogue import tabulated_sheen
from gonio.models.structure import Structure
from gonio.core.geometry import half_vector

__all__ = ["Tabulated", "N_KNOTS", "N_FRESNEL", "THETA_KNOTS", "tables", "projected_area", "g1_table",
           "knot_index", "g_index", "ndf_from_function"]

#: NDF knots (ln D piecewise linear on theta_k = (pi/2) (k / (K-1))^2)
N_KNOTS = 16
#: the first knot that is a parameter: ln D(theta_0) = ln D(theta_1) = 0, a flat core of
#: 0.4 deg (a free ln D(theta_1) left a direction the data cannot see: the Gauss-Newton
#: matrix of vch had an eigenvalue 1e-11 of its largest along the core knots, measured)
FIRST_FREE = 2
THETA_KNOTS = 0.5 * math.pi * (np.arange(N_KNOTS) / (N_KNOTS - 1)) ** 2
#: Fresnel knots, uniform in x = 1 - cos(theta_d)
N_FRESNEL = 5
#: G1 table: theta = (pi/2) (1 - (1 - v)^2), v uniform on [0, 1] (dense toward grazing)
N_G = 129
#: Gauss-Legendre nodes per knot interval of the polar quadratures (normalisation, A)
N_GAUSS = 12
#: ln D bounds: exp(-25) ~ 1e-11 of the core is "nothing"; up to e^5 above it (a ring). The
#: parameters are the ratios D / D(0) in exp of these (positive, spanning more than 100x: the
#: fitter's unit box is logarithmic in them, so it moves ln D linearly)
LN_D_BOUNDS = (-25.0, 5.0)
D_BOUNDS = (math.exp(LN_D_BOUNDS[0]), math.exp(LN_D_BOUNDS[1]))
#: bounds of the lobe width factors (1 at theta_d = 0)
WIDTH = (0.25, 4.0)
#: bound of the colour tilts |ln ndf_tilt_<c>_<k>|, and the parameter's bounds (ratios)
TILT = 10.0
TILT_BOUNDS = (math.exp(-TILT), math.exp(TILT))
#: the knots where the colour tilts are parameters (0 at knot 0, linear in the knot index
#: in between): 6.4, 40 and 90 deg
TILT_KNOTS = (4, 10, 15)
#: option body="table": the body's angular factor g(theta) on N_BODY knots uniform in theta up to
#: BODY_MAX (0, 20, 40, 60, 80 deg: the measured range), held beyond; g(0) = 1; its bounds
N_BODY = 5
BODY_MAX = math.radians(80.0)
BODY = (0.01, 4.0)


def _tilt_basis():
    k = np.arange(N_KNOTS, dtype=np.float64)
    ctrl = np.array((0,) + TILT_KNOTS, dtype=np.float64)
    return tuple(np.interp(k, ctrl, np.eye(ctrl.size)[j]) for j in range(1, ctrl.size))


#: hat functions of the tilt knots on the NDF knots, one (N_KNOTS,) array per tilt knot
TILT_BASIS = _tilt_basis()


def _theta_g(n=N_G):
    v = np.linspace(0.0, 1.0, n)
    return 0.5 * math.pi * (1.0 - (1.0 - v) ** 2)


def knot_index(theta_h, n_knots=N_KNOTS):
    """Fractional knot index of polar angles on the warped grid: (K - 1) sqrt(theta / (pi/2))."""
    return (n_knots - 1) * np.sqrt(np.clip(theta_h, 0.0, 0.5 * math.pi) / (0.5 * math.pi))


def g_index(theta, n=N_G):
    """Fractional index into the G1 table: (n - 1) (1 - sqrt(1 - theta / (pi/2)))."""
    return (n - 1) * (1.0 - np.sqrt(np.clip(1.0 - theta / (0.5 * math.pi), 0.0, 1.0)))


def _interp(table, s):
    """Linear interpolation of table (C, n) at fractional indices s (N,) -> (N, C)."""
    n = table.shape[1]
    i = np.clip(np.floor(s), 0, n - 2).astype(np.int64)
    t = np.clip(s - i, 0.0, 1.0)[:, None]
    rows = np.ascontiguousarray(table.T)  # (n, C): gathering rows is ~5x faster than columns
    return rows[i] * (1.0 - t) + rows[i + 1] * t


def _polar_nodes(theta_knots, n_gauss=N_GAUSS):
    """Gauss-Legendre nodes and weights on every knot interval, and the fractional knot
    index of each node (ln D is linear in the index between knots)."""
    x, w = np.polynomial.legendre.leggauss(n_gauss)
    k = np.arange(theta_knots.size - 1)
    s = (k[:, None] + 0.5 * (x[None, :] + 1.0)).ravel()  # fractional index
    a, b = theta_knots[:-1, None], theta_knots[1:, None]
    # theta as a function of the index: the grid is (pi/2)(s/(K-1))^2, smooth in s on each piece
    kk = theta_knots.size - 1
    theta = 0.5 * math.pi * (s / kk) ** 2
    dtheta_ds = math.pi * s / kk**2
    ws = np.broadcast_to(0.5 * w[None, :], (kk, n_gauss)).ravel()
    del a, b
    return theta, ws * dtheta_ds, s


_NODES = _polar_nodes(THETA_KNOTS)


def _azimuthal(theta_o, theta_m):
    """int_0^{2 pi} max(0, cos(theta_o) cos(theta_m) + sin(theta_o) sin(theta_m) cos(phi)) dphi,
    shape (len(theta_o), len(theta_m)) (closed form)."""
    a = np.cos(theta_o)[:, None] * np.cos(theta_m)[None, :]
    b = np.sin(theta_o)[:, None] * np.sin(theta_m)[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(b > 0.0, np.clip(-a / np.where(b > 0.0, b, 1.0), -1.0, 1.0), np.where(a > 0.0, -1.0, 1.0))
    phi_c = np.arccos(c)
    return 2.0 * (a * phi_c + b * np.sin(phi_c))


_KERNEL = _azimuthal(_theta_g(), _NODES[0])  # (N_G, nodes): fixed, computed once


def projected_area(theta_o, theta_m, weights, d_m):
    """A(theta_o) = int max(0, w_o . m) D(m) dm for an isotropic D given at polar nodes
    ``theta_m`` with quadrature ``weights`` (d theta) and values ``d_m`` (..., nodes).
    Heitz 2014, eq. 43's denominator; equals cos(theta_o) (1 + Lambda(theta_o))."""
    K = _azimuthal(np.atleast_1d(theta_o), theta_m)
    return np.einsum("on,...n->...o", K, d_m * np.sin(theta_m) * weights)


def ndf_from_function(D, theta_knots=THETA_KNOTS):
    """ln(D(theta_k) / D(0)) at the knots: a table filled from an analytic D(theta)."""
    d = np.asarray(D(theta_knots), dtype=np.float64)
    return np.log(d / d[0])


def g1_table(ln_d, theta_knots=THETA_KNOTS, n=N_G, n_gauss=N_GAUSS):
    """(ln Z, G1 table) of knot tables ``ln_d`` (C, K): Z the normalisation of exp(ln D)
    (2 pi int D cos sin d theta) and G1 = cos(theta) / A(theta) at the :func:`g_index` grid
    (C, n), for any knot grid of the warped form."""
    if theta_knots is THETA_KNOTS and n == N_G and n_gauss == N_GAUSS:
        theta_m, w, s = _NODES
        kernel = _KERNEL
    else:
        theta_m, w, s = _polar_nodes(theta_knots, n_gauss)
        kernel = _azimuthal(_theta_g(n), theta_m)
    lnd_m = _interp(ln_d, s).T  # (C, nodes)
    top = lnd_m.max(axis=1, keepdims=True)  # scale out before exp: no overflow
    d_m = np.exp(lnd_m - top)
    z = 2.0 * math.pi * (d_m * np.cos(theta_m) * np.sin(theta_m) * w).sum(axis=1)
    area = (d_m * np.sin(theta_m) * w) @ kernel.T / z[:, None]  # A with the normalised D
    cos_t = np.cos(_theta_g(n))
    cos_t[-1] = 0.0
    g1 = np.clip(cos_t[None, :] / area, 0.0, 1.0)
    return np.log(z) + top[:, 0], g1


def table_derivatives(ln_d):
    """The derivatives of :func:`g1_table`'s outputs with respect to the knot table ``ln_d``
    (C, K): ``(dlnz (C, K), dg1 (C, N_G, K))``. ln Z and A are integrals of D = exp(ln D)
    over the polar nodes, so d/d ln D_k weighs each node by its interpolation weight of knot
    k; G1 = cos / A where 0 < G1 < 1 (0 where clipped)."""
    theta_m, w, s = _NODES
    basis = _interp(np.eye(N_KNOTS), s)                         # (nodes, K): d ln D(node) / d ln D_k
    lnd_m = _interp(ln_d, s).T
    d_m = np.exp(lnd_m - lnd_m.max(axis=1, keepdims=True))     # (C, nodes), the common scale cancels
    zw = d_m * (2.0 * math.pi * np.cos(theta_m) * np.sin(theta_m) * w)
    z = zw.sum(axis=1)
    dlnz = (zw @ basis) / z[:, None]                            # (C, K)
    aw = d_m * (np.sin(theta_m) * w)
    area = aw @ _KERNEL.T / z[:, None]                          # (C, N_G)
    darea = ((aw[:, None, :] * _KERNEL[None]) @ basis) / z[:, None, None] - area[:, :, None] * dlnz[:, None, :]
    cos_t = np.cos(_theta_g())
    cos_t[-1] = 0.0
    g1 = cos_t[None, :] / area
    inside = (g1 > 0.0) & (g1 < 1.0)
    dg1 = np.where(inside[:, :, None], -(g1 / area)[:, :, None] * darea, 0.0)
    return dlnz, dg1


def _lerp_parts(n, s):
    """The lower index, its weight split (1 - t, t) and whether s lies inside a segment
    (its derivative with respect to s is the segment's slope) of :func:`_interp`."""
    i = np.clip(np.floor(s), 0, n - 2).astype(np.int64)
    t = np.clip(s - i, 0.0, 1.0)
    return i, t


def tables(p):
    """The tables of a validated parameter dict: ``ln_d`` (C, K) (ln D(theta_k) / D(0)),
    ``ln_z`` (C,), ``g1`` (C, N_G), ``fresnel`` (C, N_FRESNEL), ``rho`` (C,)."""
    ln_d = np.zeros((CHANNELS, N_KNOTS))
    for k in range(FIRST_FREE, N_KNOTS):
        ln_d[:, k] = math.log(p[f"ndf_{k}"])
    for c, name in ((0, "r"), (2, "b")):
        ln_d[c] += sum(math.log(p[f"ndf_tilt_{name}_{k}"]) * b for k, b in zip(TILT_KNOTS, TILT_BASIS))
    ln_z, g1 = g1_table(ln_d)
    fresnel = np.stack([p[f"fresnel_{j}"] for j in range(N_FRESNEL)], axis=1)
    width = np.array([[1.0] + [p[f"width_{j}"] for j in range(1, N_FRESNEL)]])
    rho = np.asarray(p["diffuse_reflectance"])
    body = np.ones((1, N_BODY))      # g = 1: the Lambertian body
    if "body_1" in p:
        body[0, 1:] = [p[f"body_{j}"] for j in range(1, N_BODY)]
    sheen = p if "sheen_alpha" in p else None      # option sheen="ggx": its parameters (tabulated_sheen)
    return SimpleNamespace(ln_d=ln_d, ln_z=ln_z, g1=g1, fresnel=fresnel, width=width, rho=rho, body=body, sheen=sheen)


def body_index(cos_theta):
    """Fractional index of the body factor's knots: (N_BODY - 1) theta / BODY_MAX, at most N_BODY - 1."""
    return (N_BODY - 1) * np.minimum(np.arccos(np.clip(cos_theta, -1.0, 1.0)) / BODY_MAX, 1.0)


def _polar(v):
    """Polar angle of (N, 3) vectors (not necessarily unit) without acos's loss near 0."""
    return np.arctan2(np.hypot(v[:, 0], v[:, 1]), v[:, 2])


def _ggx_ratio(theta, alpha):
    c2 = np.cos(theta) ** 2
    return 1.0 / (c2 + (1.0 - c2) / alpha**2) ** 2


@register
class Tabulated(Model):
    """Isotropic microfacet BRDF with a tabulated NDF per channel (see the module).

    Parameters (``params`` keys)
    ----------------------------
    diffuse_reflectance : (3,)
        rho, Lambertian body in [0, 1].
    ndf_2 ... ndf_15 : float
        D(theta_k) / D(0) of the green channel at theta_k = (pi/2) (k / 15)^2, in
        [e^-25, e^5] (the core is flat: D(theta_1 = 0.4 deg) = D(0)).
    ndf_tilt_r_4, ndf_tilt_r_10, ndf_tilt_r_15, and the same for b : float
        The red and blue channels' D over green's at knots 4, 10, 15 (6.4, 40, 90 deg), in
        [e^-10, e^10]; the log ratio is 0 at the normal, piecewise linear in the knot index.
    width_1 ... width_4 : float
        The lobe's width factor w at the Fresnel knots (theta_d = 41.4 ... 90 deg; 1 at 0),
        in [0.25, 4]: D is evaluated at theta_h / w and divided by w^2.
    fresnel_0 ... fresnel_4 : (3,)
        F at 1 - cos(theta_d) = j / 4, in [0, 1].
    body_1 ... body_4 : float
        Option ``body="table"`` only: the body's angular factor g at theta = 20 j deg
        (g(0) = 1, shared by the channels), in [0.01, 1]; the body is rho_c g(theta_i) g(theta_o) / pi.

    Options
    -------
    body : "lambert" (default) or "table"
        The body rho_c / pi, or the reciprocal data-driven diffuse rho_c g(theta_i)
        g(theta_o) / pi (the module's notes).
    """

    name = "tabulated"
    lambert_smooth = "diffuse_reflectance"   # albedo: the body rho, the lobe on the compiled kernel
    OPTIONS = {"body": ("lambert", "table"), "sheen": ("none", "ggx")}
    energy_conserving = False
    #: not a ``--model auto`` candidate: it fits well only from a data-driven start
    #: (``fit_tabulated``), not from declared defaults (module notes)
    auto_candidate = False
    #: its Mitsuba plugin gathers tables, which Dr.Jit's scalar variants cannot: it renders in
    #: the vectorised ones (llvm_ad_rgb) only (gonio.fitting.render reads this)
    mitsuba_scalar = False
    #: ``model.eval`` stays on the numpy reference at every size: the compiled kernel
    #: (values only, :func:`gonio.models.catalogue.tabulated_kernel.kernel`) serves the fit's resident evaluations
    compiled_min_pairs = 1 << 62

    @property
    def structure(self):
        from gonio.models.catalogue import tabulated_kernel

        return Structure(kernel=tabulated_kernel.kernel, kernel_inputs=tabulated_kernel.inputs, derivatives=False)

    #: the default NDF: GGX with this alpha; the default Fresnel: Schlick's with F0 = 0.04
    DEFAULT_ALPHA = 0.15
    #: the sheen refinement (:meth:`refinement`) is fitted with this loss: a colour error relative
    #: to the pair's luminance, as the render weighs colour (gonio.fitting.likelihood.loss)
    REFINEMENT_LOSS = "luminance"
    #: the sheen refinement's start (:meth:`start_from`): the sheen's GGX width, its grazing
    #: amplitude (theta_d 75.5 deg, every channel), and the main lobe's tail handed to it, ln D / D(0)
    #: at most these from the knot at theta_h 25.6 deg on (module notes)
    SHEEN_START = (0.37, 0.4)
    TAIL_KNOT, TAIL_CAP = 8, (0.02, 1e-4, 1e-6, 1e-8, 1e-10, 1e-10, 1e-10, 1e-10)

    def refinement(self, params=None):
        """The same body with the grazing sheen lobe (``sheen="ggx"``), which ``--model auto``
        tries on its chosen plain fit ``params`` (gonio.fitting.selection.auto) of a matte
        surface: 60 deg gloss below ASTM D523's 10 GU, reckoned from the fit. None where the
        sheen is on already, the fit is glossy (a paint's colour error is not a sheen) or not
        of three colour channels (the gloss is a luminance)."""
        from gonio.models.physics.gloss import MATTE_BELOW_GU, specular_gloss

        if self.options["sheen"] == "ggx" or params is None:
            return None
        if np.size(self.validate(params)["diffuse_reflectance"]) != CHANNELS:
            return None
        if specular_gloss(lambda wi, wo: self.eval(wi, wo, params)) >= MATTE_BELOW_GU:
            return None
        return Tabulated(body=self.options["body"], sheen="ggx")

    def start_from(self, plain_params):
        """The plain fit's parameters as the sheen's start: the sheen at :data:`SHEEN_START`
        (grazing amplitude only) and the main lobe's tail from :data:`TAIL_KNOT` on capped at
        :data:`TAIL_CAP`, so the wide part starts on the sheen. From the plain fit's own tail the
        local fit stays where the main lobe carries it (leaf_maple rendered 1.07 against 0.99;
        docs/performance.md)."""
        out = {k: np.array(v, dtype=np.float64) for k, v in plain_params.items() if not k.startswith("sheen")}
        alpha, grazing = self.SHEEN_START
        out["sheen_alpha"] = np.array(alpha)
        for j in range(tabulated_sheen.N_SHEEN):
            out[f"sheen_{j}"] = np.full(3, grazing if j == tabulated_sheen.N_SHEEN - 1 else 0.0)
        for k, cap in zip(range(self.TAIL_KNOT, N_KNOTS), self.TAIL_CAP):
            out[f"ndf_{k}"] = np.minimum(out[f"ndf_{k}"], cap)
        return self.validate(out)

    def __init__(self, start=None, **options):
        """``start``: a parameter dict that replaces the declared defaults (a data-driven
        starting point, :func:`gonio.fitting.optimise.tabulated_start.data_start`)."""
        self._start = None if start is None else {k: np.array(v, dtype=np.float64) for k, v in start.items()}
        super().__init__(**options)
        if self.options["body"] == "table":     # albedo: body and lobe both on the compiled kernel
            self.lambert_smooth, self.smooth_off = None, {"diffuse_reflectance": 0.0}
        if start is not None:
            self.validate(start)

    def _default(self, name, value):
        if self._start is not None and name in self._start:
            return self._start[name]
        return value

    def _parameters(self):
        pars = [Parameter("diffuse_reflectance", self._default("diffuse_reflectance", 0.1), 0.0, 1.0, "1", "Lambertian body rho", per_channel=True)]
        lnd = ndf_from_function(lambda t: _ggx_ratio(t, self.DEFAULT_ALPHA))
        for k in range(FIRST_FREE, N_KNOTS):
            deg = math.degrees(THETA_KNOTS[k])
            pars.append(Parameter(f"ndf_{k}", self._default(f"ndf_{k}", float(np.exp(np.clip(lnd[k] - lnd[1], *LN_D_BOUNDS)))),
                                  *D_BOUNDS, "1", f"D / D(0) at theta_h = {deg:.2f} deg (green)"))
        for c in "rb":
            for k in TILT_KNOTS:
                deg = math.degrees(THETA_KNOTS[k])
                pars.append(Parameter(f"ndf_tilt_{c}_{k}", self._default(f"ndf_tilt_{c}_{k}", 1.0), *TILT_BOUNDS, "1",
                                      f"D_{c} / D_g at theta_h = {deg:.1f} deg (its log piecewise linear in the knot index)"))
        for j in range(N_FRESNEL):
            x = j / (N_FRESNEL - 1)
            f0 = 0.04 + 0.96 * x**5
            pars.append(Parameter(f"fresnel_{j}", self._default(f"fresnel_{j}", f0), 0.0, 1.0, "1",
                                  f"Fresnel factor at theta_d = {math.degrees(math.acos(1.0 - x)):.1f} deg",
                                  per_channel=True))
        for j in range(1, N_FRESNEL):
            x = j / (N_FRESNEL - 1)
            pars.append(Parameter(f"width_{j}", self._default(f"width_{j}", 1.0), WIDTH[0], WIDTH[1], "1",
                                  f"lobe width factor at theta_d = {math.degrees(math.acos(1.0 - x)):.1f} deg"))
        for j in range(1, N_BODY if self.options["body"] == "table" else 1):
            deg = math.degrees(BODY_MAX) * j / (N_BODY - 1)
            pars.append(Parameter(f"body_{j}", self._default(f"body_{j}", 1.0), *BODY, "1",
                                  f"body factor g at theta = {deg:.1f} deg (1 at the normal)"))
        if self.options["sheen"] == "ggx":
            pars.extend(tabulated_sheen.parameters(self._default, N_FRESNEL))
        return tuple(pars)

    # -- evaluation -----------------------------------------------------------------------
    def _eval_parts(self, wi, wo, p):
        t = tables(p)
        n = wi.shape[0]
        diffuse = np.broadcast_to(t.rho / math.pi, (n, np.size(t.rho)))
        if "body_1" in p:
            up = (wi[:, 2] > 0.0) & (wo[:, 2] > 0.0)
            g = _interp(t.body, body_index(wi[:, 2])) * _interp(t.body, body_index(wo[:, 2]))
            diffuse = np.where(up[:, None], diffuse * g, 0.0)
        return diffuse, self._lobe(wi, wo, t)

    def _lobe(self, wi, wo, t):
        ci, co = wi[:, 2], wo[:, 2]
        wh, valid = half_vector(wi, wo)
        cd = 0.5 * (np.einsum("ij,ij->i", wi, wh) + np.einsum("ij,ij->i", wo, wh))  # symmetric: reciprocal to rounding
        ok = valid & (ci > 0.0) & (co > 0.0) & (wh[:, 2] > 0.0) & (cd > 0.0)
        s_f = (N_FRESNEL - 1) * np.clip(1.0 - cd, 0.0, 1.0)
        w = _interp(t.width, s_f)  # (N, 1): the lobe's width factor at this theta_d
        D = np.exp(_interp(t.ln_d, knot_index(_polar(wh) / w[:, 0])) - t.ln_z[None, :]) / (w * w)
        G = _interp(t.g1, g_index(_polar(wi))) * _interp(t.g1, g_index(_polar(wo)))
        F = _interp(t.fresnel, s_f)
        den = np.where(ok, 4.0 * ci * co, 1.0)
        lobe = np.where(ok[:, None], F * D * G / den[:, None], 0.0)
        if t.sheen is not None:
            lobe = lobe + tabulated_sheen.value(t.sheen, ci, co, wh[:, 2], s_f, ok, _interp)
        return lobe

    def jacobian_reference(self, wi, wo, params):
        """(f_r, {parameter: d f_r / d parameter (N, 3)}) in numpy, exact for the piecewise
        linear tables (:func:`gonio.models.engine.fast.jacobian`'s layout: a per-channel
        parameter's column c is d f_c / d p_c; the tilts reach their own channel). The fit
        uses it where the compiled kernel gives values only (the parameters act through
        tables built here), instead of P + 1 differenced evaluations."""
        from gonio.core.sides import sides_mask
        from gonio.models.inputs import eval_inputs

        wi, wo, p = eval_inputs(self, wi, wo, params)
        fin = np.isfinite(wi).all(axis=1) & np.isfinite(wo).all(axis=1)
        if not fin.all():    # 0 at a non-finite pair, as eval; (0, 0, 1) keeps its lookups in range
            wi, wo = (np.where(fin[:, None], v, (0.0, 0.0, 1.0)) for v in (wi, wo))
        t = tables(p)
        n = wi.shape[0]
        ci, co = wi[:, 2], wo[:, 2]
        with np.errstate(all="ignore"):
            wh, valid = half_vector(wi, wo)
            cd = 0.5 * (np.einsum("ij,ij->i", wi, wh) + np.einsum("ij,ij->i", wo, wh))
            pair = fin & sides_mask(self.structure.sides, ci, co)
            ok = pair & valid & (ci > 0.0) & (co > 0.0) & (wh[:, 2] > 0.0) & (cd > 0.0)
            s_f = (N_FRESNEL - 1) * np.clip(1.0 - cd, 0.0, 1.0)
            w = _interp(t.width, s_f)[:, 0]
            th = _polar(wh)
            u = np.clip(th / w, 0.0, 0.5 * math.pi)
            s_h = knot_index(th / w)
            ih, th_t = _lerp_parts(N_KNOTS, s_h)
            L = _interp(t.ln_d - t.ln_z[:, None], s_h)                          # (N, C)
            slope = (t.ln_d[:, ih + 1] - t.ln_d[:, ih]).T                       # d L / d s_h
            ds_dw = np.where((u > 0.0) & (th / w < 0.5 * math.pi), -0.5 * s_h / w, 0.0)
            gi, go = g_index(_polar(wi)), g_index(_polar(wo))
            Gi, Go = _interp(t.g1, gi), _interp(t.g1, go)
            F = _interp(t.fresnel, s_f)
            den = np.where(ok, 4.0 * ci * co * w * w, 1.0)[:, None]
            D_over = np.where(ok[:, None], np.exp(L) / den, 0.0)               # D / (4 ci co), w^-2 in den
            lobe = F * D_over * Gi * Go
            body = np.where(pair, 1.0 / math.pi, 0.0)[:, None]                   # eval_reference's mask
            table = "body_1" in p
            if table:                                                            # g_c(theta_i) g_c(theta_o)
                body = body * (ci > 0.0)[:, None] * (co > 0.0)[:, None]
                s_bi, s_bo = body_index(ci), body_index(co)
                gi_b, go_b = _interp(t.body, s_bi), _interp(t.body, s_bo)
            f = t.rho[None, :] * body * (gi_b * go_b if table else 1.0) + lobe
            J = {"diffuse_reflectance": np.broadcast_to(body * (gi_b * go_b if table else 1.0), f.shape).copy()}
            for j in range(1, N_BODY if table else 1):
                hi, ho = (_interp(np.eye(N_BODY)[j:j + 1], s)[:, 0:1] for s in (s_bi, s_bo))
                J[f"body_{j}"] = t.rho[None, :] * body * (hi * go_b + gi_b * ho)
            i_f, t_f = _lerp_parts(N_FRESNEL, s_f)
            hats = [(np.where(i_f == j, 1.0 - t_f, 0.0) + np.where(i_f + 1 == j, t_f, 0.0))[:, None]
                    for j in range(N_FRESNEL)]                                   # the Fresnel knots' weights
            for j, hat in enumerate(hats):
                J[f"fresnel_{j}"] = (D_over * Gi * Go) * hat
                if j >= 1:                                                       # w moves theta_h / w and the w^-2
                    J[f"width_{j}"] = lobe * (slope * ds_dw[:, None] - 2.0 / w[:, None]) * hat
            dlnz, dg1 = table_derivatives(t.ln_d)
            dGi = np.stack([_interp(dg1[c].T, gi) for c in range(CHANNELS)], axis=1)   # (N, C, K)
            dGo = np.stack([_interp(dg1[c].T, go) for c in range(CHANNELS)], axis=1)
            hat_h = np.zeros((n, N_KNOTS))
            np.add.at(hat_h, (np.arange(n), ih), 1.0 - th_t)
            np.add.at(hat_h, (np.arange(n), ih + 1), th_t)
            dq = lobe[:, :, None] * (hat_h[:, None, :] - dlnz[None, :, :]) \
                + (F * D_over)[:, :, None] * (dGi * Go[:, :, None] + Gi[:, :, None] * dGo)      # d f_c / d ln D_{c,k}
            for k in range(FIRST_FREE, N_KNOTS):
                J[f"ndf_{k}"] = dq[:, :, k] / p[f"ndf_{k}"]
            for c, name in ((0, "r"), (2, "b")):
                for kk, basis in zip(TILT_KNOTS, TILT_BASIS):
                    col = np.zeros((n, CHANNELS))
                    col[:, c] = dq[:, c, :] @ basis / p[f"ndf_tilt_{name}_{kk}"]
                    J[f"ndf_tilt_{name}_{kk}"] = col
            if t.sheen is not None:     # the sheen's amplitudes sit on the same knots
                S, JS = tabulated_sheen.columns(p, ci, co, wh[:, 2], ok, hats, _interp, s_f)
                f = f + S
                J.update(JS)
        return f, J

    def affine_colours(self) -> tuple:
        """f_r = rho g(i) g(o) / pi + F(theta_d) D G1 G1 / (4 cos cos) (+ the sheen A(theta_d) S), F
        and A interpolated between their knots: affine in rho, the Fresnel knots and the sheen's
        amplitudes jointly (tests/fitting/test_affine_declared.py)."""
        sheen = tuple(f"sheen_{j}" for j in range(tabulated_sheen.N_SHEEN)) if self.options["sheen"] == "ggx" else ()
        return ("diffuse_reflectance",) + tuple(f"fresnel_{j}" for j in range(N_FRESNEL)) + sheen

    def jacobian_host(self, wi, wo, params):
        """:meth:`jacobian_reference`'s (f_r, J) by the chain rule through the tables, what the
        fit calls (:func:`gonio.models.catalogue.tabulated_jacobian.jacobian`)."""
        from gonio.models.catalogue.tabulated_jacobian import jacobian

        return jacobian(self, wi, wo, params)

    def _lobe_distribution(self, p):
        """Node placement for :func:`gonio.models.physics.albedo.albedo`'s lobe quadrature: the GGX
        width with the same median microfacet inclination under D cos(theta) dm (for GGX
        that CDF is tan^2 / (alpha^2 + tan^2), median at tan(theta) = alpha), narrowest
        channel; with the main lobe off (every Fresnel knot 0), the sheen's own GGX width."""
        t = tables(p)
        if t.sheen is not None and not np.any(t.fresnel):
            a = float(t.sheen["sheen_alpha"])
            return SimpleNamespace(alpha_u=a, alpha_v=a)
        edges = 0.5 * math.pi * np.linspace(0.0, 1.0, 2049) ** 2
        cos_e = np.cos(edges)
        mid = knot_index(0.5 * (edges[:-1] + edges[1:]))
        mass = np.exp(_interp(t.ln_d, mid) - t.ln_z[None, :]) * (0.5 * (cos_e[:-1] + cos_e[1:]) * (cos_e[:-1] - cos_e[1:]))[:, None]
        cdf = np.cumsum(mass, axis=0) / mass.sum(axis=0)
        median = edges[1:][np.argmax(cdf >= 0.5, axis=0)]
        alpha = float(np.clip(np.tan(median.min()), 1e-3, 1.0))
        return SimpleNamespace(alpha_u=alpha, alpha_v=alpha)

    def albedo(self, wo, params, **quadrature):
        """:meth:`Model.albedo`; with a sheen that is on, the main lobe and body (the sheen off) plus
        the sheen alone (rho and F 0), each integrated on nodes of its own width
        (:meth:`_lobe_distribution`): one set of nodes for a narrow main lobe misses a wide sheen."""
        p = self.validate(params)
        if self.options["sheen"] != "ggx" or not np.any(tabulated_sheen.amplitudes(p)) or not np.any(tables(p).fresnel):
            return super().albedo(wo, p, **quadrature)
        main = super().albedo(wo, {**p, **{f"sheen_{j}": 0.0 for j in range(tabulated_sheen.N_SHEEN)}}, **quadrature)
        off = {"diffuse_reflectance": 0.0, **{f"fresnel_{j}": 0.0 for j in range(N_FRESNEL)}}
        sheen = super().albedo(wo, {**p, **off}, **quadrature)
        if quadrature.get("return_error"):
            return main[0] + sheen[0], main[1] + sheen[1]
        return main + sheen

    # -- Mitsuba ----------------------------------------------------------------------------
    def to_mitsuba(self, params):
        import sys

        from gonio.models.mitsuba.plugins import add_plugin, ensure_registered, rgb_channels
        from gonio.models.mitsuba.tabulated_plugin import make_bsdf

        p = self.validate(params)
        this = sys.modules[__name__]
        add_plugin("tabulated", lambda mi, dr, base: make_bsdf(mi, dr, base, this))
        d = {"type": ensure_registered("tabulated")}
        for par in self.parameters:
            if par.per_channel:
                for c, v in rgb_channels(self.name, p[par.name]):
                    d[f"{par.name}_{c}"] = float(v)
            else:
                d[par.name] = float(p[par.name])
        return d
