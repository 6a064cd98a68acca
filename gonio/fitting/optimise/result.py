"""What a fit returns (:class:`FitResult`) and its Laplace uncertainty.

At the optimum the Laplace approximation gives the covariance (J^T J)^-1 of the chi^2 loss
(Fisher information of the Gaussian noise model), with J in natural units (exact from the
compiled kernel; on the numpy path exact columns for the affine parameters, central
differences for the others). Parameters the data cannot determine (a singular or
near-singular Fisher matrix, or a 1-sigma wider than half the parameter's range) are named,
never returned as NaN.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.display import fit_summary, table_html, text
from gonio.fitting.optimise.space import ParameterSpace
from gonio.fitting.statement import fit_to_xarray, result_document

__all__ = ["FitResult", "jacobian_chi2", "laplace"]


@dataclasses.dataclass
class FitResult:
    """What a fit found and how sure it is.

    ``x`` and ``std`` are in natural units, ordered as ``space.names``.
    """

    model: object
    space: ParameterSpace
    x: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    loss: str
    objective: float
    chi2: float
    n_used: int
    n_evals: int
    time_s: float
    converged: bool
    message: str
    at_bound: list
    undetermined: list
    energy: dict
    rmse_fr: float
    rmse_cos_fr: float
    method: str = "levenberg-marquardt"
    linear: list = dataclasses.field(default_factory=list)
    #: the model-discrepancy term fitted with the model (loss ``discrepancy``): ``rel``,
    #: ``abs`` (sr^-1), ``neg2_loglik``, ``iterations``; None for the other losses
    discrepancy: dict | None = None
    #: the instrument's angular response applied (gonio/fitting/likelihood/aperture.py): apertures, the largest
    #: correction, the point model's parameters; None where the dataset declares no apertures
    response: dict | None = None
    #: the factor c the data and budget were divided by for that response (N, C; the last
    #: refit's), so the fit document can be built from the dataset as opened; None: none applied
    response_factor: np.ndarray | None = dataclasses.field(default=None, repr=False)
    #: the shared angle inputs estimated with the fit (gonio/fitting/uncertainty/shared_angles.py):
    #: estimates and posteriors in units of their stated sigma; None where not estimated
    shared_angles: dict | None = None
    #: (shift (N, C) taken from the data, L (K, K) the posterior's Cholesky factor), so the fit
    #: document can be built from the dataset as opened; None: none applied
    shared_angles_fix: tuple | None = dataclasses.field(default=None, repr=False)
    #: CPU seconds of the fit (``time.process_time``: every thread of this process, Dr.Jit's
    #: pool included), counted over what ``time_s`` counts; None where not measured
    cpu_s: float | None = None

    @property
    def params(self) -> dict:
        return self.space.to_params(self.x)

    @property
    def dof(self) -> int:
        return max(self.n_used - self.space.size, 1)

    @property
    def chi2_dof(self) -> float:
        return self.chi2 / self.dof

    @property
    def neg2_loglik(self) -> float:
        """-2 ln L (up to a constant common to all models) of the loss that was minimised:

        * ``chi2``: chi^2 (Gaussian noise with the data's sigma);
        * ``robust``: its objective (pseudo-Huber on the sigma-scaled residuals);
        * ``cosine``, ``log``, ``luminance`` (``PROFILED``): n ln(objective / n), the Gaussian likelihood of the loss's
          residuals with their variance profiled out (one more parameter);
        * ``discrepancy``: sum r^2 / s^2 + ln s^2 with s^2 = sigma^2 + (rel f)^2 + abs^2.
        """
        if self.loss == "discrepancy" and self.discrepancy:
            return float(self.discrepancy["neg2_loglik"])
        if self.loss in _loss.PROFILED:
            return float(self.n_used * np.log(max(self.objective, 1e-300) / self.n_used))
        if self.loss == "robust":
            return float(self.objective)
        return float(self.chi2)

    @property
    def k_criterion(self) -> int:
        """Free parameters counted by the BIC: the model's, plus the noise parameters the
        loss estimates (one profiled variance for cosine/log/luminance, rel and abs for discrepancy)."""
        return self.space.size + (1 if self.loss in _loss.PROFILED else 2 if self.loss == "discrepancy" else 0)

    @property
    def bic(self) -> float:
        """Bayesian information criterion -2 ln L + k ln n (Schwarz 1978), from the likelihood
        of the loss that was minimised (:attr:`neg2_loglik`), never from chi^2 when another
        loss was."""
        return self.neg2_loglik + self.k_criterion * np.log(self.n_used)

    @property
    def correlation(self) -> np.ndarray:
        """Correlation matrix of the Laplace covariance."""
        d = np.sqrt(np.clip(np.diag(self.cov), 1e-300, None))
        return np.clip(self.cov / np.outer(d, d), -1.0, 1.0)

    @property
    def correlated(self) -> list:
        """Pairs (name_a, name_b, rho) with |rho| >= 0.9: the data constrains only a combination."""
        c = self.correlation
        names = self.space.names
        return [(names[i], names[j], float(c[i, j]))
                for i in range(len(names)) for j in range(i + 1, len(names)) if abs(c[i, j]) >= 0.9]

    # ---- how a fit shows itself (terminal, notebook) and leaves as a table ----
    def __repr__(self) -> str:
        """The model, the goodness of fit and each parameter as value ± 1-sigma; no raw arrays."""
        return text(*_with_header(fit_summary(self)))

    def _repr_html_(self) -> str:
        """Jupyter's rich display: the same table as :meth:`__repr__`, as escaped HTML."""
        caption, rows, notes = fit_summary(self)
        return table_html(caption, _HEADER, rows, notes)

    def to_xarray(self, doc=None):
        """The fit as an :class:`xarray.Dataset` in the fit file's one layout
        (:func:`gonio.fitting.statement.fit_to_xarray`: value, u_c, U, k, the 90 % interval,
        bounds, flags, correlation, colour space and budget).

        ``doc``: this fit's document (:func:`gonio.fitting.fit_document` of it and the data, which
        carries the dataset's budget): its statement. Without it the fit alone knows only its
        statistical uncertainty, and says so: u_c = std, budget ``statistical``."""
        if doc is not None and not isinstance(doc, dict):
            raise TypeError("to_xarray takes the fit document (gonio.fitting.fit_document(result, meas)), "
                            f"not a {type(doc).__name__}")
        return fit_to_xarray(doc if doc is not None else result_document(self), self.model)


_HEADER = ("parameter", "value ± 1-sigma", "unit", "flags")


def _with_header(summary):
    caption, rows, notes = summary
    return caption, _HEADER, rows, notes


def jacobian_chi2(problem, x, rel_step=1e-5):
    """chi^2 residuals at x and their Jacobian in natural units (M, P).

    Exact from the compiled kernel where it runs; otherwise columns of affine parameters are
    exact and the others central differences with a relative step (one-sided at a bound).
    """
    space, meas = problem.space, problem.meas
    exact = problem.residual_jacobian_x(x, range(space.size), loss="chi2")
    if exact is not None:
        return exact[1], exact[0]
    f0 = problem.f_x(x)
    r0 = _loss.residuals("chi2", f0, meas)
    sw = _loss.value_weight(meas)
    J = np.empty((r0.size, space.size))
    lin = {}
    if problem.linear:
        _, cols = problem.basis(x)
        for g, B in zip(problem.linear, cols):
            for c, i in enumerate(g["index"]):
                Bc = np.zeros_like(B)
                Bc[:, c] = B[:, c]
                lin[i] = (Bc * sw / meas.brdf_std)[meas.use]
    scale = np.maximum(np.abs(x), 1e-3 * (space.upper - space.lower))
    for j in range(space.size):
        if j in lin:
            J[:, j] = lin[j]
            continue
        h = rel_step * scale[j]
        hi, lo = min(x[j] + h, space.upper[j]), max(x[j] - h, space.lower[j])
        xp, xm = x.copy(), x.copy()
        xp[j], xm[j] = hi, lo
        fp = f0 if hi == x[j] else problem.f_x(xp)
        fm = f0 if lo == x[j] else problem.f_x(xm)
        J[:, j] = ((fp - fm) * sw / meas.brdf_std)[meas.use] / (hi - lo)
    if not np.all(np.isfinite(J)):
        raise FloatingPointError("non-finite Jacobian at the optimum")
    return J, r0


def laplace(J, space, cond_limit=1e12, fisher=None):
    """Covariance (J^T J)^-1 and the names of parameters the data does not determine
    (``fisher``: J^T J itself, where it was reduced without J)."""
    fisher = J.T @ J if fisher is None else fisher
    width = space.upper - space.lower
    # Scale to unit diagonal so the condition number measures correlation, not units.
    d = np.sqrt(np.clip(np.diag(fisher), 1e-300, None))
    corr = fisher / np.outer(d, d)
    w, v = np.linalg.eigh(corr)
    keep = w > w.max() / cond_limit
    inv_corr = (v[:, keep] / w[keep]) @ v[:, keep].T
    cov = inv_corr / np.outer(d, d)
    undetermined = set()
    for idx in np.where(~keep)[0]:  # null directions: the parameters that load on them
        undetermined.update(np.where(np.abs(v[:, idx]) > 0.3)[0].tolist())
        cov += np.outer(v[:, idx], v[:, idx]) * np.outer(width, width) / 12.0
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    undetermined.update(np.where(std > 0.5 * width)[0].tolist())
    return cov, [space.names[i] for i in sorted(undetermined)]


def loss_jacobian(problem, x, loss, rel_step=1e-5):
    """Residuals of ``loss`` at x and their Jacobian in natural units (M, P): exact from the
    compiled kernel where it runs, else central differences (one-sided at a bound)."""
    space, meas = problem.space, problem.meas
    exact = problem.residual_jacobian_x(x, range(space.size), loss=loss)
    if exact is not None:
        return exact[1], exact[0]
    r0 = _loss.residuals(loss, problem.f_x(x), meas)
    J = np.empty((r0.size, space.size))
    scale = np.maximum(np.abs(x), 1e-3 * (space.upper - space.lower))
    for j in range(space.size):
        h = rel_step * scale[j]
        hi, lo = min(x[j] + h, space.upper[j]), max(x[j] - h, space.lower[j])
        xp, xm = x.copy(), x.copy()
        xp[j], xm[j] = hi, lo
        J[:, j] = (_loss.residuals(loss, problem.f_x(xp), meas) - _loss.residuals(loss, problem.f_x(xm), meas)) / (hi - lo)
    if not np.all(np.isfinite(J)):
        raise FloatingPointError("non-finite Jacobian at the optimum")
    return J, r0


def objective_hessian(problem, x, loss, rel_step=1e-4, at=None, definite_only=False):
    """Hessian of (1/2) sum r^2 of ``loss`` at x in natural units, J^T J + sum_k r_k d^2 r_k,
    by forward differences of its exact gradient J^T r (:func:`loss_jacobian`; the step
    points into the box, so a parameter at a bound is differenced from inside), symmetrised:
    P more Jacobians. ``at``: (J, r) at x where the caller has them already.
    ``definite_only``: None as soon as a leading block is not positive definite by
    :func:`_positive_definite` (then neither is the whole: Cauchy interlacing), without the
    remaining columns."""
    space = problem.space
    J0, r0 = loss_jacobian(problem, x, loss) if at is None else at
    g0 = J0.T @ r0
    P = space.size
    H = np.empty((P, P))
    scale = np.maximum(np.abs(x), 1e-3 * (space.upper - space.lower))
    for j in range(P):
        h = rel_step * scale[j]
        if x[j] + h > space.upper[j]:
            h = -h
        xv = x.copy()
        xv[j] = x[j] + h
        Jv, rv = loss_jacobian(problem, xv, loss)
        H[:, j] = (Jv.T @ rv - g0) / (xv[j] - x[j])
        if definite_only and np.all(np.isfinite(H[:j + 1, :j + 1])):
            lead = H[:j + 1, :j + 1]
            if not _positive_definite(0.5 * (lead + lead.T)):
                return None
    if not np.all(np.isfinite(H)):
        raise FloatingPointError("non-finite Hessian at the optimum")
    return 0.5 * (H + H.T)


def _positive_definite(H):
    d = np.sqrt(np.abs(np.diag(H)))
    if not np.all(d > 0):
        return False
    w = np.linalg.eigvalsh(H / np.outer(d, d))
    return bool(w.min() > 1e-9 * w.max())


def sandwich(J, r, space, clusters, hessian=None):
    """Cluster-robust ("sandwich") covariance of a least-squares M-estimator:
    A^-1 B A^-1 with B = sum_g s_g s_g^T, s_g = sum over the residuals of cluster g of
    J_k r_k (Huber 1967; White 1980; Liang & Zeger 1986 for clusters), and A the Hessian of
    (1/2) sum r^2 at the optimum (``hessian``; J^T J, its Gauss-Newton part, without one).

    It needs no noise model: it is the covariance of the estimate when the geometry's
    independent units (``clusters``) are a random sample and the residuals (measurement
    noise and the model's own discrepancy) are whatever they are at them.

    The bread is the full Hessian, not J^T J: where the model misses the material the
    residuals are systematic and sum_k r_k d^2 r_k does not average out (White 1982: the
    misspecified model's A is the expected Hessian). On colodur_napoli_4f (roughplastic-GGX,
    log loss) it lowers the curvature along the albedo-alpha-int_ior valley by 22 %, and the
    refits on random geometries moved alpha 1.25-1.4x as far as the Gauss-Newton step from the
    reference predicted. Parameters the data cannot determine keep :func:`laplace`'s
    prior-width variance."""
    # the bread from the profiled-scale information A / s^2, s^2 = |r|^2 / (M - P):
    # :func:`laplace` judges what is undetermined on the scale of the residuals, not of 1
    s2 = max(float(r @ r) / max(r.size - J.shape[1], 1), 1e-300)
    fisher = (J.T @ J if hessian is None else hessian) / s2
    cov_a, undetermined = laplace(None, space, fisher=fisher)
    # leverage h_k = J_k A^-1 J_k^T; residuals divided by 1 - h_k (HC3, MacKinnon & White
    # 1985): a sample that pulls the fit onto itself shows a residual too small by that factor
    h = np.clip(np.einsum("kp,pq,kq->k", J, cov_a / s2, J), 0.0, 0.99)
    S = np.zeros((int(clusters.max()) + 1, J.shape[1]))
    np.add.at(S, clusters, J * (r / (1.0 - h))[:, None])
    cov = cov_a @ (S.T @ S) @ cov_a / (s2 * s2)
    width = space.upper - space.lower
    for name in undetermined:
        i = space.names.index(name)
        cov[i, i] = max(cov[i, i], cov_a[i, i], width[i] ** 2 / 12.0)
    return 0.5 * (cov + cov.T), undetermined


def robust_covariance(result, meas, problem):
    """``result`` with the sandwich covariance of its own loss's residuals (:func:`sandwich`)
    instead of the chi^2 Fisher matrix: for the ``log`` and ``cosine`` losses, whose
    residuals have no noise model.

    Clusters: ``meas.cluster`` where the data name their geometry's independent units (an
    RGL file's outgoing sample point, shared by every measured incident elevation and by
    both sample sets: the pairs of one draw are not independent), else one cluster per
    direction pair (the colour channels of one pair share their discrepancy). Bread: the
    objective's Hessian (:func:`objective_hessian`), or J^T J where that is not positive
    definite (a saddle or a bound); the method string says which."""
    J, r = loss_jacobian(problem, result.x, result.loss)
    rows = np.nonzero(meas.use)[0]
    clusters = rows if meas.cluster is None else np.unique(meas.cluster[rows], return_inverse=True)[1]
    try:
        H = objective_hessian(problem, result.x, result.loss, at=(J, r), definite_only=True)
    except FloatingPointError:
        H = None
    bread = "Hessian" if H is not None and _positive_definite(H) else "Gauss-Newton J^T J"
    cov, undetermined = sandwich(J, r, result.space, clusters, H if bread == "Hessian" else None)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    units = f"{int(clusters.max()) + 1} geometry draws" if meas.cluster is not None else "one per direction pair"
    return dataclasses.replace(result, cov=cov, std=std, undetermined=undetermined,
                               method=f"{result.method} + sandwich covariance of the {result.loss} residuals "
                                      f"({bread} bread; clusters: {units})")
