"""The uncertainty budget carried into the fitted parameters (GUM, JCGM 100:2008).

A dataset's budget (docs/interfaces.md 5.1: ``u_<component>`` variables with ``gum_type``
and ``correlation``) is read by :func:`load_budget`; a dataset without one gets
:func:`budget_from_attrs` (type A = ``brdf_std`` and a fully correlated certificate term
brdf x ``scale_rel_std``). :func:`propagate` carries every component into the parameters.

Method: linearised nuisance parameters. The fit is the weighted least-squares estimate
x(y) of its own loss (residuals r(x, y)); to first order a shift d of the data moves it by
G d with G = -(J^T J)^+ J^T diag(dr/dy), J = dr/dx at the optimum (the implicit-function
theorem applied to J^T r = 0). A correlated component is a shared error e ~ N(0, 1) per
group with brdf shifted by e u_group (u signed), so it adds (G u_g)(G u_g)^T per group
(one for ``full``, three for ``channel``, one per label for ``group:<var>``); an
independent component adds G diag(u^2) G^T. Only P x M matrices are formed, never M x M.
Why this and not a generalised least-squares refit with V = D + U U^T: the estimate the
optimiser computes is the weighted one, and this is its covariance under V exactly to first
order (the GLS covariance (J^T V^-1 J)^-1 belongs to another estimator); for the dominant
term, a scale error that the model absorbs (u in the span of J), both coincide
(:func:`gls_covariance`, Woodbury, is kept to show it in the tests). A fit's own statistical
covariance (Laplace or sandwich, Birge-inflated where the model misses) stands for the type-A
independent components; their propagated shares only split it in the budget.

References: JCGM 100:2008 (GUM) 5.1-5.2 and 6.2 (k = 2); JCGM 102:2011 6.2 (propagation of
a multivariate covariance, U_y = C U_x C^T); Woodbury (1950), Hager (1989) for the inverse of
a diagonal plus low-rank matrix.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gonio.models.geometry import angles as _angles_of, directions as _directions

from . import _loss
from ._data import _SRGB_TO_XYZ, colour_transform
from ._problem import Problem
from ._result import loss_jacobian

__all__ = ["BudgetComponent", "Budget", "load_budget", "budget_from_attrs", "propagate", "gls_covariance", "K_EXPANDED"]

#: coverage factor of the expanded uncertainty U = k u_c (about 95 % for a normal distribution, GUM 6.2.2)
K_EXPANDED = 2.0
STATISTICAL = "statistical"


@dataclasses.dataclass
class BudgetComponent:
    """One component: ``value`` (N, C) in sr^-1 (signed where correlated), or (K, N, C) for K
    independent inputs of the same kind; its GUM type; its correlation (``none``: every value
    its own error; ``point``: one error per point, shared by its channels; ``full``,
    ``channel``, ``group``: shared across points) and, for ``group``, integer labels (N, C)."""

    name: str
    value: np.ndarray
    gum_type: str
    correlation: str
    source: str = ""
    groups: np.ndarray | None = None

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
            contrib = G * vk[None]                      # (P, N, C)
            if self.correlation == "none":
                g = contrib.reshape(P, -1)
            elif self.correlation == "point":
                g = contrib.sum(axis=2)
            elif self.correlation == "full":
                g = contrib.sum(axis=(1, 2))[:, None]
            elif self.correlation == "channel":
                g = contrib.sum(axis=1)
            else:
                labels = np.broadcast_to(self.groups, vk.shape)
                flat, lab = contrib.reshape(P, -1), labels.reshape(-1)
                g = np.stack([flat[:, lab == k].sum(axis=1) for k in np.unique(labels[use])], axis=1)
            cov += g @ g.T
        return cov


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

    def describe(self) -> dict:
        return {c.name: {"gum_type": c.gum_type, "correlation": c.correlation, "source": c.source}
                for c in self.components}


def budget_from_attrs(meas) -> Budget:
    """Type A = ``brdf_std``; type B = the certificate, brdf x ``scale_rel_std``, fully correlated."""
    comps = [BudgetComponent(STATISTICAL, meas.brdf_std, "A", "none", "brdf_std (the fit's weights)")]
    rel = float(meas.attrs.get("scale_rel_std", 0.0) or 0.0)
    if rel > 0:
        comps.append(BudgetComponent("reference_certificate", meas.brdf * rel, "B", "full",
                                     "scale_rel_std (reference certificate)"))
    return Budget(comps, "scale_rel_std attribute" if rel > 0 else "brdf_std only")


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
            value = np.asarray(var.transpose("point", "channel").values, float)
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
            if value.shape != meas.brdf.shape or not np.all(np.isfinite(value[meas.use])):
                raise ValueError(f"{path}: {v} must be finite at every used value, shape {meas.brdf.shape}")
            comps += _in_colour_space(BudgetComponent(v[2:], value, gtype, corr, str(var.attrs.get("source", "")),
                                                      groups), colour_transform(meas), path)
        angles = _angle_shifts(ds, path, meas.n_points)
        colour = _colour_matrix_components(ds, meas)
    budget = Budget(comps) if comps else budget_from_attrs(meas)
    return dataclasses.replace(budget, components=budget.components + colour, angles=angles)


#: The dataset variable holding the colour matrix's budget lines (bench/colour_matrix.py), in linear sRGB.
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


#: the dataset variables of the angles' uncertainty (docs/interfaces.md 5.1), degrees
ANGLE_SHIFTS = {"shared": "angle_shift_shared", "independent": "angle_shift_independent"}


def _angle_shifts(ds, path, n_points):
    """``{shared, independent}``: (K, N, 4) arrays from ``angle_shift_*`` (input, point, angle); None without."""
    out = {}
    for key, name in ANGLE_SHIFTS.items():
        if name not in ds.variables:
            continue
        v = ds[name]
        try:
            arr = np.asarray(v.transpose(v.dims[0], "point", "angle").values, float)
        except (ValueError, KeyError):
            raise ValueError(f"{path}: {name} must have dimensions (input, point, angle)") from None
        if arr.ndim != 3 or arr.shape[1:] != (n_points, 4) or not np.all(np.isfinite(arr)):
            raise ValueError(f"{path}: {name} must be finite, (inputs, {n_points} points, 4 angles) in degrees")
        out[key] = arr
    return out or None


def _in_colour_space(comp: BudgetComponent, s, path) -> list:
    """A camera-RGB component (the dataset's ``u_`` variables are per camera channel) in the
    fit's colour space through the 3x3 ``s`` (fitting/_data.colour_transform): a signed shared
    error maps linearly (``s u``); an independent one by its variance (``sqrt(s^2 u^2)``); a
    per-channel shared one becomes one fully shared component per camera channel."""
    if s is None:
        raise ValueError(f"{path}: the fit's colour space needs the dataset's colour matrix to carry u_{comp.name}; "
                         "re-export the session or fit with --colour-space camera")
    if np.array_equal(s, np.eye(len(s))):
        return [comp]
    if comp.correlation == "none":
        return [dataclasses.replace(comp, value=np.sqrt(comp.value ** 2 @ (s ** 2).T))]
    if comp.correlation == "channel":
        return [dataclasses.replace(comp, name=f"{comp.name}_{c}", value=comp.value[:, [c]] * s[:, c], correlation="full")
                for c in range(len(s))]
    if comp.groups is not None and comp.groups.ndim == 2 and np.any(comp.groups != comp.groups[:, :1]):
        raise ValueError(f"{path}: u_{comp.name} has per-channel groups, which a colour matrix mixes; "
                         "fit with --colour-space camera")
    return [dataclasses.replace(comp, value=comp.value @ s.T)]


def _sensitivity(result, meas):
    """G = -(J^T J)^+ J^T diag(dr/dy) restricted to the used values: (P, M), and the mask."""
    loss = result.loss if result.loss in ("chi2", "robust", "cosine", "log") else "chi2"
    problem = Problem(meas, result.model, result.space, loss)
    J, _ = loss_jacobian(problem, result.x, loss)
    drdy = -_loss.residual_derivative(loss, meas.brdf, meas)
    drdy = np.broadcast_to(drdy, meas.brdf.shape)[meas.use]
    return -np.linalg.pinv(J, rcond=1e-10) * drdy[None, :]


def slope(model, params, wi, wo, h_deg: float = 1e-3) -> np.ndarray:
    """d f_r / d (theta_i, phi_i, theta_o, phi_o) (N, C, 4), sr^-1 per degree, by central
    differences of the model at ``params``."""
    ti, pi_ = _angles_of(wi)
    to, po = _angles_of(wo)
    base = np.stack([ti, pi_, to, po], axis=-1)
    h = np.radians(h_deg)
    out = []
    for a in range(4):
        plus, minus = base.copy(), base.copy()
        plus[:, a] += h
        minus[:, a] -= h
        fp = model.eval(_directions(plus[:, 0], plus[:, 1]), _directions(plus[:, 2], plus[:, 3]), params)
        fm = model.eval(_directions(minus[:, 0], minus[:, 1]), _directions(minus[:, 2], minus[:, 3]), params)
        out.append((fp - fm) / (2 * h_deg))
    return np.stack(out, axis=-1)


def angle_components(result, meas, angles: dict) -> list:
    """``angle_shared`` (B, full, one input per shared angle error) and ``angle_repeatability``
    (B, point: one error per point, shared by its channels): the angles' shifts times the
    fitted model's local slope (GUM 5.1.3: c_i u(x_i) with c_i = d f_r / d angle)."""
    S = slope(result.model, result.params, meas.wi, meas.wo)
    out = []
    for key, name, corr in (("shared", "angle_shared", "full"), ("independent", "angle_repeatability", "point")):
        d = np.asarray(angles.get(key, np.zeros((0, meas.n_points, 4))), float)
        if d.size:
            out.append(BudgetComponent(name, np.einsum("nca,kna->knc", S, d), "B", corr,
                                       f"angle uncertainty ({key}) x the local slope of the fitted f_r"))
    return out


def propagate(result, meas, budget: Budget, u_stat: np.ndarray) -> dict:
    """The fit file's ``uncertainty`` section (docs/interfaces.md 5.1): per parameter
    ``u_stat``, ``u_combined``, ``U`` (k = 2), ``k`` and ``budget`` (variance fractions).

    ``u_stat``: the statistical 1-sigma of each parameter (Birge-inflated where so reported).
    Also ``covariance_combined``: the statistical covariance plus the propagated ones.
    """
    use = meas.use
    P = result.space.size
    G = np.zeros((P,) + use.shape)
    G[:, use] = _sensitivity(result, meas)
    var, stat_share = {}, {}
    cov_b = np.zeros((P, P))
    comps = list(budget.components) + (angle_components(result, meas, budget.angles) if budget.angles else [])
    for c in comps:
        if c.statistical:
            g = G[:, use] * c.value[use][None, :]
            stat_share[c.name] = np.einsum("pm,pm->p", g, g)
            continue
        cov = c.covariance(G, use)
        var[c.name] = np.diag(cov).copy()
        cov_b += cov
    u_stat = np.asarray(u_stat, float)
    total = u_stat ** 2 + np.diag(cov_b)
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
    return {"parameters": out, "cov_systematic": cov_b}


def gls_covariance(J: np.ndarray, sigma: np.ndarray, U: np.ndarray) -> np.ndarray:
    """(J^T V^-1 J)^-1 for V = diag(sigma^2) + U U^T by the Woodbury identity
    V^-1 = D^-1 - D^-1 U (I + U^T D^-1 U)^-1 U^T D^-1 (J: M x P in data units, U: M x r);
    O(M P r), no M x M matrix."""
    Dinv = 1.0 / sigma ** 2
    DJ, DU = J * Dinv[:, None], U * Dinv[:, None]
    core = np.eye(U.shape[1]) + U.T @ DU
    A = J.T @ DJ - (DJ.T @ U) @ np.linalg.solve(core, U.T @ DJ)
    return np.linalg.inv(A)

