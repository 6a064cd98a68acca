"""Model ``gratingpaint``: a flake paint whose flakes carry a diffraction grating (rings of colour).

    f_r = flakepaint's f_r + rho_g[c] R_c(q) / (4 (cos_i cos_o)^p),   q = |wi_perp + wo_perp|,
    R_c(q) = sum_lambda M_c(lambda) exp(-(q - lambda / period)^2 / (2 w^2))

Holographic flakes are mirrors embossed with a grating: order m leaves where the in-plane
momentum transfer q equals m lambda / period (the grating equation; Stam 1999, sec. 3); flakes
turned every way make it a ring about the mirror direction, blurred by their tilt and finite
size (width w). The first order only: a shallow sinusoidal phase grating puts J_m(phi)^2 into
order m (Goodman, Introduction to Fourier Optics, sec. 4.4). M_c: CIE 1931 2-degree CMFs to
linear sRGB (colour-science), negative lobes clipped (f_r >= 0), an equal-energy spectrum white.
``ring="table"``: rho_g R_c(q) read from the data, linear in q between knots. RGB only. Offered
by ``--model auto`` on goniochromic RGB data, the table as the chosen rings' refinement. Mitsuba
twin: ``gonio_gratingpaint``, flakepaint's Python BSDF with the rings (``*_rgb`` only)."""

from __future__ import annotations

import functools

import numpy as np

from gonio.models.base import Parameter, register, weighted_sample
from gonio.models.catalogue.flake_memo import geometry, memo, values
from gonio.models.catalogue.flakepaint import FlakePaint, _make_bsdf, half_vector_lobe

__all__ = ["GratingPaint", "RING_KNOTS", "hats", "rgb_weights", "rings"]

#: wavelengths (nm) of the spectral sum and the diffraction orders summed (the first: see the module)
WAVELENGTHS = np.arange(400.0, 701.0, 10.0)
ORDERS = (1,)
#: option ``ring="table"``: the knots in q (0 to 2, the largest |wi_perp + wo_perp|) of the
#: rings' colour, linear between them (see :class:`GratingPaint`)
RING_KNOTS = np.linspace(0.0, 2.0, 17)
#: :meth:`GratingPaint.data_start`'s grid: periods (um, 4 % apart; the first order's green
#: beyond q 0.23, outside the highlight's core), widths, and the lobes' spreads beside them
PERIODS = np.geomspace(0.32, 2.4, 52)
WIDTHS = (0.05, 0.1, 0.2)
LOBES = (0.02, 0.05, 0.1, 0.2, 0.4, 0.8)


def hats(q) -> np.ndarray:
    """(N, len(RING_KNOTS)): the piecewise-linear interpolation weights of q (hat functions on
    the knots, each row summing to 1 for q in [0, 2], 0 beyond)."""
    h = RING_KNOTS[1] - RING_KNOTS[0]
    return np.clip(1.0 - np.abs(np.asarray(q, float)[:, None] - RING_KNOTS[None, :]) / h, 0.0, None)


@functools.lru_cache(maxsize=1)
def rgb_weights() -> np.ndarray:
    """(len(WAVELENGTHS), 3): linear sRGB of each wavelength (CIE 1931 2-degree CMFs, the sRGB
    XYZ -> RGB matrix; colour-science), negatives clipped, each column summing to 1."""
    import colour

    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    xyz = np.array([cmfs[w] for w in WAVELENGTHS])
    m = np.clip(xyz @ np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB).T, 0.0, None)
    return m / m.sum(axis=0, keepdims=True)


def rings(q, period_um, width, grad=False):
    """R(q) (N, 3) for q (N,), with (grad) dR/dperiod and dR/dwidth."""
    q = np.asarray(q, float)[:, None]
    lam = WAVELENGTHS[None, :] * 1e-3 / period_um          # q of the first order, per wavelength
    R = dP = dW = 0.0
    for m in ORDERS:
        d = q - m * lam
        g = np.exp(-0.5 * (d / width) ** 2)
        R = R + g
        if grad:
            dP = dP + g * (-d / width ** 2) * (m * lam / period_um)
            dW = dW + g * d * d / width ** 3
    M = rgb_weights()
    return (R @ M, dP @ M, dW @ M) if grad else R @ M


@register
class GratingPaint(FlakePaint):
    """flakepaint plus diffraction rings (see the module).

    Parameters (``params`` keys, beyond flakepaint's with one shared flake spread)
    -------------------------------------------------------------------------------
    grating_reflectance : (3,)
        rho_g, weight of the diffraction orders, in [0, 1].
    grating_period : float
        Lambda, in micrometres, in [0.3, 5].
    grating_width : float
        w, width of an order in q, in [0.01, 0.5].

    Option ``ring="table"``: R_c(q) read from the data instead, rho_g R_c(q) replaced by
    T_c(q), linear between its values ``ring_k`` (C,) in [0, 5] at q = :data:`RING_KNOTS`
    (non-negative; q symmetric in wi, wo: reciprocal), where the spectrum, the orders' weights
    and the flakes' period spread are not known; nested: started from the ``ring="cie"`` fit.
    """

    name = "gratingpaint"
    OPTIONS = {"distribution": ("ggx", "beckmann"), "spread": ("shared",), "ring": ("cie", "table")}
    #: not screened by ``--model auto``: tried as the chosen ``ring="cie"`` fit's refinement
    REFINEMENTS = (("ring", "table"),)
    auto_candidate = False
    spectral_candidate = False
    #: offered on RGB data that shows goniochromism (fitting.selection.by_data)
    goniochromic_candidate = True
    mitsuba_twin = True

    def __init__(self, **options):
        super().__init__(**options)
        if self.options["ring"] == "table":      # nested: started from the spectral rings' fit
            self._layer = GratingPaint(distribution=self.options["distribution"], ring="cie")

    @property
    def table(self) -> bool:
        return self.options["ring"] == "table"

    def refinement(self, params=None):
        """The ring table of the same distribution (``--model auto`` tries it where these
        spectral rings were chosen, ``params`` their fit: gonio.fitting.selection.auto), None
        for the table itself."""
        return None if self.table else GratingPaint(distribution=self.options["distribution"], ring="table")

    def affine_colours(self) -> tuple:
        """flakepaint's colours and the rings' (their weight, or every knot of the ring table)."""
        rings = tuple(f"ring_{k}" for k in range(RING_KNOTS.size)) if self.table else ("grating_reflectance",)
        return super().affine_colours() + rings

    def _parameters(self):
        if self.table:
            return super()._parameters() + tuple(
                Parameter(f"ring_{k}", 0.0, 0.0, 5.0, "1", f"the rings' colour at q = {q:.3g}", per_channel=True)
                for k, q in enumerate(RING_KNOTS))
        return super()._parameters() + (
            Parameter("grating_reflectance", 0.01, 0.0, 1.0, "1", "weight of the diffraction orders", per_channel=True),
            Parameter("grating_period", 0.7, 0.3, 5.0, "um", "period of the flakes' grating"),
            Parameter("grating_width", 0.1, 0.01, 0.5, "1", "width of a diffraction order in q"),
        )

    def validate(self, params):
        p = super().validate(params)
        if self.n_channels(p) != 3:
            raise ValueError(f"gratingpaint takes RGB (3 channels), not {self.n_channels(p)}: its rings are "
                             "summed over wavelengths into sRGB")
        return p

    @staticmethod
    def _q_shape(wi, wo, p):
        """q, 1 / (4 (cos_i cos_o)^p) (N, 1; 0 below the horizon) and ln(cos_i cos_o) (N, 1)."""
        g = geometry(wi, wo)
        shape = memo(g, ("q_shape",) + values(p, ("flake_exponent",)),
                     lambda: np.where(g.q_ok, np.exp(-p["flake_exponent"] * g.q_logcc) / 4.0, 0.0))
        return g.q, shape, g.q_logcc

    def _grating(self, wi, wo, p, grad=False):
        """The rings' shape R(q) / (4 (cos_i cos_o)^p) (N, 3), with (grad) its derivatives in the
        period and width and ln(cos_i cos_o); remembered for these directions (flake_memo)."""
        g = geometry(wi, wo)

        def make():
            q, shape, logcc = self._q_shape(g.wi, g.wo, p)
            out = rings(q, p["grating_period"], p["grating_width"], grad)
            if not grad:
                return out * shape
            return tuple(x * shape for x in out) + (logcc,)
        key = ("grating", bool(grad), rings) + values(p, ("grating_period", "grating_width", "flake_exponent"))
        return memo(g, key, make)

    def _hat_shape(self, wi, wo, p):
        """hats(q) times the shape (N, len(RING_KNOTS)): the table's basis, remembered."""
        g = geometry(wi, wo)

        def make():
            q, shape, _ = self._q_shape(g.wi, g.wo, p)
            return hats(q) * shape
        return memo(g, ("hats", hats) + values(p, ("flake_exponent",)), make)

    def _table(self, p) -> np.ndarray:
        """(len(RING_KNOTS), C): the rings' colour at the knots."""
        return np.stack([np.broadcast_to(p[f"ring_{k}"], (self.n_channels(p),)) for k in range(RING_KNOTS.size)])

    def _ring(self, wi, wo, p):
        """The rings' f_r (N, C)."""
        if not self.table:
            return self._grating(wi, wo, p) * p["grating_reflectance"]
        q, shape, _ = self._q_shape(wi, wo, p)
        g = geometry(wi, wo)
        return (memo(g, ("hats", hats), lambda: hats(q)) @ self._table(p)) * shape

    def _eval_parts(self, wi, wo, p):
        g = geometry(wi, wo)        # its arrays: the calls below find it by identity
        wi, wo = g.wi, g.wo
        base, lobe = super()._eval_parts(wi, wo, p)
        return base, lobe + self._ring(wi, wo, p)

    def jacobian_reference(self, wi, wo, params):
        """flakepaint's (f, J) with the rings added: their colour's column exactly, the period's
        and width's analytically, and their share of d f / d p."""
        g = geometry(wi, wo)
        wi, wo = g.wi, g.wo
        p = self.validate(params)
        f, J = super().jacobian_reference(wi, wo, p)
        if self.table:      # linear in the table: column k is the knot's hat times the shape
            _, _, logcc = self._q_shape(wi, wo, p)
            B = self._hat_shape(wi, wo, p)
            ring = B @ self._table(p)
            for k in range(RING_KNOTS.size):
                J[f"ring_{k}"] = np.broadcast_to(B[:, k:k + 1], f.shape).copy()
            J["flake_exponent"] = J["flake_exponent"] - logcc * ring
            return f + ring, J
        g, dP, dW, logcc = self._grating(wi, wo, p, grad=True)
        rho = p["grating_reflectance"]
        J["grating_reflectance"] = g
        J["grating_period"], J["grating_width"] = dP * rho, dW * rho
        J["flake_exponent"] = J["flake_exponent"] - logcc * g * rho
        return f + g * rho, J

    def data_start(self, meas, fixed=None):
        """A start read from the data (``gonio.fitting.optimise.mle`` asks): the period and width
        of :data:`PERIODS` x :data:`WIDTHS` whose rings, beside the declared defaults' lobes (and
        half-vector lobes of spreads :data:`LOBES`), fit the colours best by non-negative least
        squares, each value weighted by 1 / sigma (at most 3000 samples, evenly picked; through
        the Gram matrix); the table's: those rings at its knots (:meth:`start_from`); None for
        other than RGB. ``fixed``: the fit's held parameters (a held period or width is the
        grid's only value; held declared defaults enter the terms)."""
        from scipy.optimize import nnls

        if meas.brdf.shape[1] != 3:
            return None
        if self.table:
            return self.start_from(self._layer.data_start(meas, fixed=fixed))
        fixed = dict(fixed or {})
        p = self.validate({k: v for k, v in fixed.items() if k in self.defaults()})
        wi, wo, y, w, _ = weighted_sample(meas)                              # w (N, 3): unused weight 0
        base, coat, haze, _ = self._terms(wi, wo, p)
        lobes = [half_vector_lobe(self.options["distribution"], a, p["flake_exponent"], wi, wo)[:, 0] for a in LOBES]
        L = np.column_stack([base[:, 0], coat[:, 0], haze[:, 0]] + lobes)
        Lw = L[:, None, :] * w[:, :, None]                                     # (N, 3, K)
        q, shape, _ = self._q_shape(wi, wo, p)
        best = (np.inf, None)
        periods = [float(fixed["grating_period"])] if "grating_period" in fixed else PERIODS
        widths = [float(fixed["grating_width"])] if "grating_width" in fixed else WIDTHS
        for period in periods:
            for width in widths:
                r = rings(q, period, width) * shape * w                        # (N, 3)
                cost, colour = 0.0, []
                for c in range(3):
                    A = np.column_stack([Lw[:, c], r[:, c]])
                    G = A.T @ A
                    G[np.diag_indices_from(G)] += 1e-12 * np.trace(G) + 1e-300
                    R = np.linalg.cholesky(G).T                                # G = R^T R
                    d = np.linalg.solve(R.T, A.T @ y[:, c])
                    x, res = nnls(R, d)
                    cost, colour = cost + res * res + y[:, c] @ y[:, c] - d @ d, colour + [x[-1]]
                if cost < best[0]:
                    best = (cost, {"grating_period": float(period), "grating_width": float(width),
                                   "grating_reflectance": np.clip(colour, 1e-3, 1.0)})
        return {**p, **best[1]}

    def start_from(self, layer_params):
        """The ``ring="cie"`` fit (``layer_params``) as the table's start: its rings at the knots."""
        lp = dict(self._layer.validate(layer_params))
        ring = rings(RING_KNOTS, lp["grating_period"], lp["grating_width"]) * lp["grating_reflectance"]
        out = {k: v for k, v in lp.items() if not k.startswith("grating_")}
        out.update({f"ring_{k}": np.clip(ring[k], 0.0, 5.0) for k in range(RING_KNOTS.size)})
        return out

    def _bsdf_maker(self):
        return _make_grating_bsdf

    def to_mitsuba(self, params):
        """flakepaint's dict for ``gonio_gratingpaint``, with the rings' colour, period and width."""
        import mitsuba as mi

        from gonio.models.base import rgb
        from gonio.models.mitsuba import mitsuba_variant

        if "spectral" in (mi.variant() or mitsuba_variant()):
            raise ValueError(f"gratingpaint renders in an RGB variant, not {mi.variant() or mitsuba_variant()} "
                             "(its rings are summed into sRGB)")
        p = self.validate(params)
        d = super().to_mitsuba(p)
        if self.table:
            d.update({f"ring_{k}": rgb(p[f"ring_{k}"]) for k in range(RING_KNOTS.size)})
            return d
        d["grating_reflectance"] = rgb(p["grating_reflectance"])
        d["grating_period"], d["grating_width"] = float(p["grating_period"]), float(p["grating_width"])
        return d


def _make_grating_bsdf(mi, dr, base):
    """The Mitsuba twin: flakepaint's Python BSDF (its lobes, sampling and pdf) with
    :meth:`GratingPaint._grating` added in Dr.Jit, in an RGB variant (the rings' sRGB weights
    are fixed; a spectral variant is refused)."""
    flake = _make_bsdf(mi, dr, base)
    weights = rgb_weights()

    class GratingPaintBSDF(flake):
        def __init__(self, props):
            if mi.is_spectral:
                raise ValueError("gonio_gratingpaint renders in an RGB variant (its rings are summed into sRGB)")
            flake.__init__(self, props)
            self.table = "ring_0" in props
            if self.table:
                self.knots = [props.get_unbounded_texture(f"ring_{k}") for k in range(RING_KNOTS.size)]
                return
            self.rho_g = props.get_texture("grating_reflectance")
            self.period, self.width = mi.Float(float(props["grating_period"])), mi.Float(float(props["grating_width"]))
            dr.make_opaque(self.period, self.width)

        def _f(self, si, wo):
            value = flake._f(self, si, wo)
            wi_g, wo_g = wo, si.wi                 # gonio: wi toward the light, wo toward the detector
            cc = mi.Frame3f.cos_theta(wi_g) * mi.Frame3f.cos_theta(wo_g)
            q = dr.sqrt(dr.square(wi_g.x + wo_g.x) + dr.square(wi_g.y + wo_g.y))
            shape = dr.select(cc > 0.0, dr.exp(-self.p * dr.log(dr.select(cc > 0.0, cc, 1.0))) / 4.0, 0.0)
            if self.table:                         # :func:`hats`: linear between the knots
                step = float(RING_KNOTS[1] - RING_KNOTS[0])
                ring = mi.Color3f(0.0)
                for k, texture in enumerate(self.knots):
                    w = dr.maximum(1.0 - dr.abs(q - float(RING_KNOTS[k])) / step, 0.0)
                    ring += texture.eval(si) * w
                return value + ring * shape
            r, g, b = mi.Float(0.0), mi.Float(0.0), mi.Float(0.0)
            for k, w in enumerate(WAVELENGTHS):
                ring = mi.Float(0.0)
                for m in ORDERS:
                    d = (q - m * float(w) * 1e-3 / self.period) / self.width
                    ring += dr.exp(-0.5 * d * d)
                r += float(weights[k, 0]) * ring
                g += float(weights[k, 1]) * ring
                b += float(weights[k, 2]) * ring
            return value + self.rho_g.eval(si) * mi.Color3f(r, g, b) * shape

        def to_string(self):
            return f"GonioGratingPaint[{self.kind}]"

    return GratingPaintBSDF
