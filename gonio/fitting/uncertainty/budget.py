"""The uncertainty budget carried into the fitted parameters (GUM, JCGM 100:2008).

A dataset's budget (docs/interfaces.md 5.1: ``u_<component>`` variables with ``gum_type``
and ``correlation``) is read by :func:`load_budget`; a dataset without one gets
:func:`budget_from_attrs` (type A = ``brdf_std`` and a fully correlated certificate term
brdf x ``scale_rel_std``). :func:`propagate` carries every component into the parameters by
linearised nuisance parameters: a shift d of the data moves the fit by G d with
G = -(J^T J)^+ J^T diag(dr/dy); a correlated component adds (G u_g)(G u_g)^T per group, an
independent one G diag(u^2) G^T (only P x M matrices are formed, never M x M). A fit's own
statistical covariance stands for the type-A independent components.

References: JCGM 100:2008 (GUM) 5.1-5.2 and 6.2 (k = 2); JCGM 102:2011 6.2 (propagation of
a multivariate covariance, U_y = C U_x C^T); Woodbury (1950), Hager (1989) for the inverse of
a diagonal plus low-rank matrix.
"""

# Method: the fit is the weighted least-squares estimate x(y) of its own loss (residuals
# r(x, y)); to first order a shift d of the data moves it by G d, J = dr/dx at the optimum
# (the implicit-function theorem applied to J^T r = 0). A correlated component is a shared
# error e ~ N(0, 1) per group with brdf shifted by e u_group (u signed): one group for full,
# three for channel, one per label for group:<var>.
# Why this and not a generalised least-squares refit with V = D + U U^T: the estimate the
# optimiser computes is the weighted one, and this is its covariance under V exactly to first
# order (the GLS covariance (J^T V^-1 J)^-1 belongs to another estimator); for the dominant
# term, a scale error that the model absorbs (u in the span of J), both coincide
# (gls_covariance, Woodbury, is kept to show it in the tests).
# The fit's own covariance is Laplace or sandwich, Birge-inflated where the model misses; the
# type-A components' propagated shares only split it in the budget.

from __future__ import annotations

import dataclasses

import numpy as np

from gonio.core.sides import side_of

from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.measurements import _SRGB_TO_XYZ, colour_transform
from gonio.fitting.likelihood.problem import Problem
from gonio.fitting.optimise.result import loss_jacobian
from gonio.fitting.statement import K_EXPANDED
from gonio.fitting.uncertainty.adequacy import adequacy_test, chi2_refiner
from gonio.fitting.uncertainty.angle_shifts import AXES, _angle_shifts, per_point, slope  # noqa: F401
from gonio.fitting.uncertainty.intervals import error_quantiles, gaussian_adequate
from gonio.fitting.uncertainty.second_order import second_order

__all__ = ["BudgetComponent", "Budget", "load_budget", "budget_from_attrs", "propagate", "gls_covariance", "K_EXPANDED"]

STATISTICAL = "statistical"
#: the budget line of the shared angle errors' second-order term (:func:`second_order`)
ANGLE_SECOND_ORDER = "angle_shared_second_order"


@dataclasses.dataclass
class BudgetComponent:
    """One component: ``value`` (N, C) in sr^-1 (signed where correlated), or (K, N, C) for K
    independent inputs of the same kind; its GUM type; its correlation (``none``: every value
    its own error; ``point``: one error per point, shared by its channels; ``full``,
    ``channel``, ``group``: shared across points) and, for ``group``, integer labels (N, C).
    ``mean``: a ``full`` line's input's expected value in its standard uncertainties (the
    dataset's ``input_mean``; a systematic of known sign left in the data): the parameters are
    corrected by ``mean`` times the line's effect (:func:`propagate`), u is about that mean."""

    name: str
    value: np.ndarray
    gum_type: str
    correlation: str
    source: str = ""
    groups: np.ndarray | None = None
    mean: float = 0.0

    @property
    def statistical(self) -> bool:
        """Type A and independent: represented by the fit's own statistical covariance."""
        return self.gum_type == "A" and self.correlation == "none" and np.ndim(self.value) == 2

    def covariance(self, G: np.ndarray, use: np.ndarray) -> np.ndarray:
        """Its covariance of the parameters, P x P, from G (P, N, C) (zero at unused values):
        a sum of g g^T over its shared errors, g = the parameters' shift for +1 sigma of one."""
        v = np.where(use, self.value, 0.0)
        v = v[None] if v.ndim == 2 else v
        P = G.shape[0]
        cov = np.zeros((P, P))
        for vk in v:                                    # K independent inputs
            g = self.input_sums(G * vk[None], use)
            cov += g @ g.T
        return cov

    def input_sums(self, X: np.ndarray, use: np.ndarray) -> np.ndarray:
        """X (R, N, C) summed over the values that share one error: (R, L), one column per
        error (L = N C for ``none``, N for ``point``, 1 for ``full``, C for ``channel``, the
        labels for ``group``)."""
        R = X.shape[0]
        if self.correlation == "none":
            return X.reshape(R, -1)
        if self.correlation == "point":
            return X.sum(axis=2)
        if self.correlation == "full":
            return X.sum(axis=(1, 2))[:, None]
        if self.correlation == "channel":
            return X.sum(axis=1)
        labels = np.broadcast_to(self.groups, X.shape[1:])
        keep = np.unique(labels[use])
        lab = np.searchsorted(keep, labels.reshape(-1))
        inside = (lab < keep.size) & (keep[np.minimum(lab, keep.size - 1)] == labels.reshape(-1))
        out = np.zeros((keep.size, R))
        np.add.at(out, lab[inside], X.reshape(R, -1)[:, inside].T)      # O(R M), one pass
        return out.T


@dataclasses.dataclass
class Budget:
    """The components, and where the dataset states its angles' uncertainty (degrees):
    ``angles = {"shared": (K, N, 4), "independent": (J, N, 4)}``, the change of each point's
    (theta_i, phi_i, theta_o, phi_o) for +1 sigma of each shared input (zero offsets, holder
    tilt: the same error at every point) and of each per-move input (repeatability, backlash).
    The fit turns them into f_r by its model's local slope (:func:`angle_components`)."""

    components: list
    source: str = "dataset"
    angles: dict | None = None
    #: how the fit's weights follow the data: d ln(brdf_std) / d ln|brdf| (0: sigma given, not
    #: measured). A bench dataset's type A is evaluated from each point's own signal (the HDR
    #: merge's noise model and pixel scatter, its exposures following the signal), so a shared
    #: error that moves a value moves its weight too (:func:`second_order`; :func:`sigma_elasticity`)
    sigma_elasticity: float = 0.0

    def describe(self) -> dict:
        return {c.name: {"gum_type": c.gum_type, "correlation": c.correlation, "source": c.source,
                         **({"input_mean": float(c.mean)} if getattr(c, "mean", 0.0) else {})}
                for c in self.components}


def _per_channel(value, n: int) -> np.ndarray:
    """``scale_rel_std`` as one relative 1-sigma per channel: absent 0, one number for all, or one
    per channel (a spectral certificate); ValueError (one line) for any other length or a value
    that is not finite and >= 0."""
    arr = np.zeros(1) if value is None else np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size not in (1, n) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError(f"scale_rel_std must be one number >= 0 or one per channel ({n}), not {value!r}"[:200])
    return np.broadcast_to(arr, (n,)).copy()


def budget_from_attrs(meas) -> Budget:
    """Type A = ``brdf_std``; type B = the certificate, brdf x ``scale_rel_std``, fully correlated.

    Both sides (:mod:`gonio.core.sides`): the reflectance reference's certificate scales the
    reflected points, the open beam's (``open_beam_rel_std``: its attenuator and beam solid
    angle, gonio.bench.measure.transmission) the transmitted ones; two independent lines, each
    fully correlated over its own side, and the open-beam frame's own error
    (``open_beam_frame_rel_u``, one per channel) shared by the transmitted points."""
    comps = [BudgetComponent(STATISTICAL, meas.brdf_std, "A", "none", "brdf_std (the fit's weights)")]
    through = (side_of(meas.wi[:, 2], meas.wo[:, 2]) == 1)[:, None]
    rel = _per_channel(meas.attrs.get("scale_rel_std"), meas.brdf.shape[1])
    if np.any(rel > 0) and not through.all():
        comps.append(BudgetComponent("reference_certificate", np.where(through, 0.0, meas.brdf * rel), "B", "full",
                                     "scale_rel_std (reference certificate)"))
    rel_t = float(meas.attrs.get("open_beam_rel_std", 0.0) or 0.0)
    if rel_t > 0 and through.any():
        comps.append(BudgetComponent("open_beam_certificate", np.where(through, meas.brdf * rel_t, 0.0), "B", "full",
                                     "open_beam_rel_std (attenuator and beam solid angle, ASTM E2387)"))
    frame = np.asarray(meas.attrs.get("open_beam_frame_rel_u", 0.0), dtype=float).reshape(-1)
    frame = np.broadcast_to(frame if frame.size == meas.brdf.shape[1] else frame[:1], (meas.brdf.shape[1],))
    if np.any(frame > 0) and through.any():     # the open-beam frame's error: one per channel, every point's
        comps.append(BudgetComponent("open_beam_frame", np.where(through, meas.brdf * frame[None, :], 0.0), "B",
                                     "channel", "open_beam_frame_rel_u (the open-beam frame's scatter)"))
    names = [n for n, used in (("scale_rel_std", np.any(rel > 0) and not through.all()),
                               ("open_beam_rel_std", rel_t > 0 and through.any()),
                               ("open_beam_frame_rel_u", np.any(frame > 0) and through.any())) if used]
    return Budget(comps, " and ".join(names) + (" attributes" if len(names) > 1 else " attribute") if names
                  else "brdf_std only")


def load_budget(path, meas) -> Budget:
    """The budget of ``dataset.nc`` at ``path`` (its ``u_`` variables), aligned with ``meas``;
    :func:`budget_from_attrs` when the file has none. ValueError (one line) when a
    component is malformed."""
    import xarray as xr

    with xr.open_dataset(path, engine="h5netcdf") as ds:
        names = [v for v in ds.data_vars if v.startswith("u_") and "gum_type" in ds[v].attrs]
        comps = []
        for v in names:
            var = ds[v]
            corr = str(var.attrs.get("correlation", ""))
            gtype = str(var.attrs.get("gum_type", ""))
            column = "wavelength" if "wavelength" in var.dims else "channel"     # a spectral dataset's lines
            extra = [d for d in var.dims if d not in ("point", column)]
            if len(extra) > 1 or (extra and not corr == "full") or column not in var.dims:
                raise ValueError(f"{path}: {v} has dimensions {var.dims!r:.60}: (point, channel), or (point, channel, "
                                 "input) for a fully shared line with several inputs (wavelength for channel in a "
                                 "spectral dataset); see docs/interfaces.md 5.1")
            value = np.asarray(var.transpose("point", column, *extra).values, float)
            if extra:                       # K independent inputs, each shared by every value: (K, N, C)
                value = np.moveaxis(value, -1, 0)
            groups = None
            if corr.startswith("group:"):
                gname = corr.split(":", 1)[1]
                if gname not in ds.variables:
                    raise ValueError(f"{path}: {v} names the group variable {gname!r:.40}, which is not in the dataset")
                groups = np.broadcast_to(np.asarray(ds[gname].values, np.int64).reshape(value.shape[0], -1),
                                         value.shape).copy()
                corr = "group"
            if gtype not in ("A", "B") or corr not in ("none", "point", "full", "channel", "group"):
                raise ValueError(f"{path}: {v} has gum_type {gtype!r:.10} and correlation {corr!r:.30}; "
                                 "see docs/interfaces.md 5.1")
            if value.shape[-2:] != meas.brdf.shape or not np.all(np.isfinite(value[..., meas.use])):
                raise ValueError(f"{path}: {v} must be finite at every used value, shape {meas.brdf.shape}")
            mean = var.attrs.get("input_mean", 0.0)
            try:
                mean = float(mean)
            except (TypeError, ValueError):
                mean = float("nan")
            if not np.isfinite(mean) or (mean != 0.0 and corr != "full"):
                raise ValueError(f"{path}: {v} has input_mean {var.attrs.get('input_mean')!r:.30}: a finite number, "
                                 "on a 'full' line only; see docs/interfaces.md 5.1")
            comps += _in_colour_space(BudgetComponent(v[2:], value, gtype, corr, str(var.attrs.get("source", "")),
                                                      groups, mean), colour_transform(meas), path)
        angles = _angle_shifts(ds, path, meas.n_points, meas.n_channels)
        colour = _colour_matrix_components(ds, meas)
        measured = "u_shot_read" in ds.variables      # the bench's type A: from each point's own signal
    budget = Budget(comps) if comps else budget_from_attrs(meas)
    return dataclasses.replace(budget, components=budget.components + colour, angles=angles,
                               sigma_elasticity=sigma_elasticity(meas) if measured and angles else 0.0)


def sigma_elasticity(meas) -> float:
    """d ln(brdf_std) / d ln|brdf| across the used values (least squares in log-log, clipped to
    [0, 1]): how a value's standard deviation grows with its signal when both come from the
    same observation (shot noise alone gives 1/2 at one exposure; an HDR bracket that follows
    the signal, or a fixed-pattern share, brings it towards 1). 0 where it cannot be judged."""
    ok = meas.use & (meas.brdf > 0) & (meas.brdf_std > 0) & np.isfinite(meas.brdf) & np.isfinite(meas.brdf_std)
    if ok.sum() < 3:
        return 0.0
    ly, ls = np.log(meas.brdf[ok]), np.log(meas.brdf_std[ok])
    var = float(np.var(ly))
    if not var > 1e-6:
        return 0.0
    k = float(np.mean((ly - ly.mean()) * (ls - ls.mean()))) / var
    return float(np.clip(k, 0.0, 1.0)) if np.isfinite(k) else 0.0


#: The dataset variable holding the colour matrix's budget lines (gonio/bench/measure/colour_matrix.py), in linear sRGB.
COLOUR_MATRIX_U = "brdf_srgb_u_colour_matrix"


def _colour_matrix_components(ds, meas) -> list:
    """The colour matrix's fully shared components (a ColorChecker fit's; one per independent
    input, signed, in linear sRGB), for a fit in sRGB or XYZ; none for a camera-RGB fit."""
    space = (meas.attrs.get("colour") or {}).get("space", "camera")
    if space == "camera" or COLOUR_MATRIX_U not in ds.variables:
        return []
    values = np.asarray(ds[COLOUR_MATRIX_U].transpose("point", "channel", ...).values, float)
    to = _SRGB_TO_XYZ if space == "xyz" else np.eye(3)
    source = str(ds[COLOUR_MATRIX_U].attrs.get("source", "colour matrix"))
    return [BudgetComponent(f"colour_matrix_{k}", np.nan_to_num(values[..., k]) @ to.T, "B", "full", source)
            for k in range(values.shape[-1])]


def _in_colour_space(comp: BudgetComponent, s, path) -> list:
    """A camera-RGB component (the dataset's ``u_`` variables are per camera channel) in the
    fit's colour space through the 3x3 ``s`` (gonio/fitting/measurements.colour_transform): a signed shared
    error maps linearly (``s u``); an independent one by its variance (``sqrt(s^2 u^2)``); a
    per-channel shared one becomes one fully shared component per camera channel."""
    if s is None:
        raise ValueError(f"{path}: the fit's colour space needs the dataset's colour matrix to carry u_{comp.name}; "
                         "re-export the session or fit with --colour-space camera")
    if np.array_equal(s, np.eye(len(s))):
        return [comp]
    if comp.correlation == "none":
        # one error per camera channel and point: in the fit's space it moves the point's three
        # channels together (s[:, k] times it), so it is K = 3 inputs of correlation "point",
        # not three independent errors sqrt(s^2 u^2) (that would drop the channels' correlation,
        # brdf_srgb_corr, up to |r| 0.6 for a consumer camera)
        return [dataclasses.replace(comp, value=np.stack([comp.value[:, [k]] * s[:, k] for k in range(len(s))]),
                                    correlation="point")]
    if comp.correlation == "channel":
        return [dataclasses.replace(comp, name=f"{comp.name}_{c}", value=comp.value[:, [c]] * s[:, c], correlation="full")
                for c in range(len(s))]
    if comp.groups is not None and comp.groups.ndim == 2 and np.any(comp.groups != comp.groups[:, :1]):
        raise ValueError(f"{path}: u_{comp.name} has per-channel groups, which a colour matrix mixes; "
                         "fit with --colour-space camera")
    return [dataclasses.replace(comp, value=comp.value @ s.T)]


def _sensitivity(result, meas):
    """G = -(J^T J)^+ J^T diag(dr/dy) restricted to the used values: (P, M)."""
    J, drdy = _loss_sensitivities(result, meas)
    return -np.linalg.pinv(J, rcond=1e-10) * drdy[None, :]


def angle_components(result, meas, angles: dict) -> list:
    """``angle_shared`` (B, full, one input per shared angle error) and ``angle_repeatability``
    (B, point: one error per point, shared by its channels), or where the dataset labels each
    axis's moves (``angle_shift_independent_group``) ``angle_repeatability_<axis>`` (B, group:
    one error per move of that axis, shared by the points taken without moving it): the angles'
    shifts times the fitted model's local slope (GUM 5.1.3: c_i u(x_i) with c_i = d f_r / d angle).
    A shared input that also changes the sample's irradiance alone (``shared_irradiance``, the
    wedge's foreshortening: the bench's ratio to the reference then moves by that relative
    change) adds f_r times it."""
    S = slope(result.model, result.params, meas.wi, meas.wo)
    out = []
    for key, name, corr in (("shared", "angle_shared", "full"), ("independent", "angle_repeatability", "point")):
        d = np.asarray(angles.get(key, np.zeros((0, meas.n_points, 4))), float)
        if not d.size:
            continue
        value = np.einsum("nca,kna->knc", S, d) if d.ndim == 3 else np.einsum("nca,knca->knc", S, d)
        if key == "shared" and angles.get("shared_irradiance") is not None:
            f = result.model.eval(meas.wi, meas.wo, result.params)
            irr = np.asarray(angles["shared_irradiance"], float)
            value = value + (irr if irr.ndim == 3 else irr[:, :, None]) * f[None]
        groups = angles.get("independent_groups") if key == "independent" else None
        if groups is None:
            # per (point, wavelength) visits without move labels: every value its own error; the
            # shared inputs stay one error each, whatever cells they move ('full')
            out.append(BudgetComponent(name, value, "B", "none" if d.ndim == 4 and key == "independent" else corr,
                                       f"angle uncertainty ({key}) x the local slope of the fitted f_r"))
            continue
        # one error per move of each axis: the points taken without moving it share it
        for k, axis in enumerate(AXES if len(value) == len(AXES) else [str(k) for k in range(len(value))]):
            labels = np.asarray(groups[k])           # (N,), or (N, C) where each wavelength was its own visit
            out.append(BudgetComponent(f"{name}_{axis}", value[k], "B", "group",
                                       f"the {axis} axis's per-move error x the local slope of the fitted f_r",
                                       groups=labels if labels.ndim == 2 else
                                       np.repeat(labels[:, None], value.shape[-1], axis=1)))
    return out


def _point_independent(c: BudgetComponent) -> bool:
    """A component whose errors are independent from point to point (``none`` or ``point``)."""
    return c.correlation in ("none", "point")


def birge_against_budget(result, J, drdy, meas, comps, adequate: bool | None = None) -> dict:
    """The fit's chi^2 against what the whole budget makes it (:func:`expected_chi2`): where the
    adequacy test (:func:`adequacy_test`, ``adequate``) rejects the model, a factor
    sqrt(chi^2 / E) on the statistical covariance, else 1. The plain Birge ratio
    sqrt(chi^2/dof) would count again the scatter the type-B lines already carry (the angles'
    errors times a steep lobe's slope, the reference table's, the stray light's). E and its
    spread are reported beside the verdict; they are not the verdict (a few large shared inputs
    make chi^2 under the null a skewed sum of a few scaled chi^2_1 terms, whose mean + 4 sd
    passed a wrong family at chi^2/dof 50)."""
    mean, sd = expected_chi2(J, drdy, meas, comps)
    chi2 = float(result.chi2)
    if adequate is None:
        adequate = not (chi2 > mean + 4.0 * sd)
    factor = float(np.sqrt(chi2 / mean)) if mean > 0 and not adequate and chi2 > mean else 1.0
    return {"chi2": chi2, "chi2_expected": mean, "chi2_expected_sd": sd, "factor": factor}


def _loss_sensitivities(result, meas, residuals: bool = False):
    """(J, dr/dy): the loss's residual Jacobian at the optimum (M, P) and dr/dy at the used values
    (M,); with ``residuals`` also the residuals there (M,)."""
    loss = result.loss if result.loss in ("chi2", "robust") + _loss.PROFILED else "chi2"
    problem = Problem(meas, result.model, result.space, loss)
    J, r = loss_jacobian(problem, result.x, loss)
    drdy = -_loss.residual_derivative(loss, meas.brdf, meas)
    out = (J, np.broadcast_to(drdy, meas.brdf.shape)[meas.use])
    return out + (r,) if residuals else out


def expected_chi2(J, drdy, meas, comps) -> tuple[float, float]:
    """(mean, standard deviation) of the fit's chi^2 if the data scatter exactly as ``comps`` say.

    A data error d leaves the residual (I - P)(dr/dy d) after the fit, P = J J^+ the projector on
    J's columns (the part the parameters absorb). Each error a_l of a component (one value for
    ``none``, one point for ``point``, one group for the shared ones) adds
    e_l = ||a_l||^2 - ||Q^T a_l||^2 to the mean, Q an orthonormal basis of J's columns (M x P:
    nothing M x M is formed); the variance is taken as 2 sum e_l^2 (exact for type A alone,
    where the mean is M - P = dof and the rule is gonio/fitting/formats/fitfile.model_adequacy's)."""
    U, sv, _ = np.linalg.svd(J, full_matrices=False)
    Q = U[:, sv > sv.max() * 1e-10] if sv.size and sv.max() > 0 else U[:, :0]
    use = meas.use
    GQ = np.zeros((Q.shape[1],) + use.shape)
    GQ[:, use] = Q.T
    D = np.zeros(use.shape)
    D[use] = drdy
    mean = var = 0.0
    for c in comps:
        v = np.where(use, c.value, 0.0) * D
        for a in (v[None] if v.ndim == 2 else v):
            e = c.input_sums((a * a)[None], use)[0] - (c.input_sums(GQ * a[None], use) ** 2).sum(axis=0)
            mean, var = mean + float(e.sum()), var + 2.0 * float((e * e).sum())
    return mean, float(np.sqrt(var))


def propagate(result, meas, budget: Budget, u_stat: np.ndarray, cov_stat: np.ndarray | None = None,
              adequacy: dict | None = None) -> dict:
    """The fit file's ``uncertainty`` section (docs/interfaces.md 5.1): per parameter
    ``u_stat``, ``u_combined``, ``U`` (k = 2), ``k`` and ``budget`` (variance fractions).

    ``u_stat``: the fit's statistical 1-sigma of each parameter (Birge-inflated where so
    reported; ``cov_stat`` its covariance). Returns also ``covariance_statistical`` and
    ``cov_systematic`` (the propagated type-B and shared lines).

    The statistical covariance is the type-A components propagated through G (the estimator's
    own covariance, JCGM 102 6.2) wherever the dataset splits type A into ``u_`` lines: the
    fit's Laplace covariance assumes every value independent with sigma ``brdf_std``, which
    equals G diag(sigma^2) G^T, but after a colour matrix a camera channel's noise moves the
    point's three channels together (negatively correlated for a consumer camera: the Laplace
    sigma of a parameter shared by the channels, such as alpha and int_ior of a white specular
    lobe, is then 1.7 times the estimator's). The Birge factor that covers a misfit is taken
    against the budget's own point-wise covariance (type A with its channel correlation plus
    the point-independent type-B lines, :func:`birge_against_budget`): scatter the budget
    already carries as ``angle_repeatability`` is not counted again. For losses other than
    chi2 (sandwich covariances) the fit's ratio u_stat / sqrt(G diag(sigma^2) G^T) is kept.
    """
    use = meas.use
    P = result.space.size
    J, drdy, r = _loss_sensitivities(result, meas, residuals=True)
    G = np.zeros((P,) + use.shape)
    G[:, use] = -np.linalg.pinv(J, rcond=1e-10) * drdy[None, :]
    var, stat_share = {}, {}
    cov_b = np.zeros((P, P))
    cov_a = np.zeros((P, P))
    comps = list(budget.components) + (angle_components(result, meas, budget.angles) if budget.angles else [])
    type_a = [c for c in comps if c.gum_type == "A" and _point_independent(c)]
    split = bool(type_a) and not (len(type_a) == 1 and type_a[0].name == STATISTICAL)
    if adequacy is None and result.loss == "chi2":
        # a budget of systematic lines alone: the fit's own sigma stands for the type A
        pointwise = comps if type_a else [BudgetComponent(STATISTICAL, meas.brdf_std, "A", "none")] + comps
        adequacy = adequacy_test(result, meas, pointwise, J, r, drdy, refine=chi2_refiner(result, meas),
                                 angles=per_point(budget.angles))
    # lines of known mean (a systematic of known sign left in the data): the parameters' expected
    # shift, mean x G value, which the fit document's values are corrected by (GUM 3.2.4)
    known = np.zeros(P)
    for c in comps:
        if getattr(c, "mean", 0.0):
            known += c.mean * np.einsum("pnc,nc->p", np.where(use, G, 0.0), np.where(use, c.value, 0.0))
    for c in comps:
        cov = c.covariance(G, use)
        if split and c.gum_type == "A" and _point_independent(c):
            cov_a += cov
            stat_share[c.name] = np.diag(cov).copy()
            continue
        if c.statistical:
            stat_share[c.name] = np.diag(cov).copy()
            continue
        var[c.name] = np.diag(cov).copy()
        cov_b += cov
    bias2 = None
    shared = np.asarray((per_point(budget.angles) or {}).get("shared", np.zeros((0,) + use.shape[:1] + (4,))), float)
    if shared.size:
        # the shared angle errors' quadratic term (second_order): a narrow lobe's fit answers a
        # tilted normal by broadening whichever way it tilted, and a measured sigma reweighs the
        # values it moved. Its mean b is a known systematic effect: the fit document's values are
        # corrected by -b (GUM 3.2.4; 4.1.4 note: the estimate of a non-linear function is the mean
        # of its distribution) and the line carries what is left about it, tr(H_p H_q) / 2
        kappa = float(getattr(budget, "sigma_elasticity", 0.0) or 0.0) if result.loss == "chi2" else 0.0
        bias2, cov2, hess2 = second_order(result, meas, shared, G, use, elasticity=kappa)
        cov2 = cov2 - np.outer(bias2, bias2)
        var[ANGLE_SECOND_ORDER] = np.diag(cov2).copy()
        cov_b += cov2
    u_stat = np.asarray(u_stat, float)
    cov_stat = np.diag(u_stat ** 2) if cov_stat is None else np.asarray(cov_stat, float)
    birge = None
    if split:
        if result.loss == "chi2":
            birge = birge_against_budget(result, J, drdy, meas, comps,
                                         adequate=None if adequacy is None else adequacy["adequate"])
            scale = np.full(P, birge["factor"])
        else:
            naive = np.sqrt(np.einsum("pm,pm->p", G[:, use] * meas.brdf_std[use][None], G[:, use] * meas.brdf_std[use][None]))
            scale = np.where(naive > 0, u_stat / np.where(naive > 0, naive, 1.0), 1.0)
        cov_stat = cov_a * np.outer(scale, scale)
        u_stat = np.sqrt(np.clip(np.diag(cov_stat), 0.0, None))
    total = u_stat ** 2 + np.diag(cov_b)
    quantiles = None
    if bias2 is not None:
        # the error's distribution is not normal where the quadratic term counts: its coverage
        # intervals by Monte Carlo (gonio/fitting/uncertainty/intervals.py), the first-order
        # shared line per input beside the quadratic term, the rest of the budget normal
        lin = [c for c in comps if c.name == "angle_shared"]
        if lin and np.asarray(lin[0].value).shape[0] == hess2.shape[1]:
            L = np.einsum("pnc,knc->pk", np.where(use, G, 0.0), np.where(use, np.asarray(lin[0].value, float), 0.0))
            rest = total - var.get("angle_shared", np.zeros(P)) - var[ANGLE_SECOND_ORDER]
            quantiles = error_quantiles(L, hess2, bias2, rest)
    out = {}
    s_sum = sum(stat_share.values()) if stat_share else None
    for i, name in enumerate(result.space.names):
        t = float(total[i])
        frac = {}
        if s_sum is not None and s_sum[i] > 0:
            for k, v in stat_share.items():
                frac[k] = u_stat[i] ** 2 * v[i] / s_sum[i] / t if t > 0 else 0.0
        else:
            frac[STATISTICAL] = u_stat[i] ** 2 / t if t > 0 else 1.0
        for k, v in var.items():
            frac[k] = float(v[i]) / t if t > 0 else 0.0
        uc = float(np.sqrt(t))
        out[name] = {"u_stat": float(u_stat[i]), "u_combined": uc, "U": K_EXPANDED * uc, "k": K_EXPANDED,
                     "budget": {k: float(f) for k, f in sorted(frac.items(), key=lambda kv: -kv[1])}}
        if quantiles is not None:
            # the truth lies in [value - upper, value - lower] at each level (fit_document)
            out[name]["error_quantiles"] = {f"{lev:.4g}": [float(q[i, 0]), float(q[i, 1])] for lev, q in quantiles.items()}
            out[name]["gaussian"] = gaussian_adequate(quantiles[0.9545][i], uc)
        if bias2 is not None:
            # the estimate's expected shift from the shared angle errors' second-order term; the
            # fit document reports value = fitted - this (gonio/fitting/formats/fitfile.fit_document)
            out[name]["angle_second_order_mean"] = float(bias2[i])
        if known[i] != 0.0:
            # the estimate's expected shift from the lines of known mean; the fit document
            # reports value = fitted - this as well
            out[name]["systematic_mean"] = float(known[i])
    return {"parameters": out, "cov_systematic": cov_b, "cov_statistical": cov_stat, "birge": birge,
            "adequacy": adequacy}


def gls_covariance(J: np.ndarray, sigma: np.ndarray, U: np.ndarray) -> np.ndarray:
    """(J^T V^-1 J)^-1 for V = diag(sigma^2) + U U^T by the Woodbury identity
    V^-1 = D^-1 - D^-1 U (I + U^T D^-1 U)^-1 U^T D^-1 (J: M x P in data units, U: M x r);
    O(M P r), no M x M matrix."""
    Dinv = 1.0 / sigma ** 2
    DJ, DU = J * Dinv[:, None], U * Dinv[:, None]
    core = np.eye(U.shape[1]) + U.T @ DU
    A = J.T @ DJ - (DJ.T @ U) @ np.linalg.solve(core, U.T @ DJ)
    return np.linalg.inv(A)

