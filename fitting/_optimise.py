"""Constrained maximum-likelihood fit of a BRDF model, and its Laplace uncertainty.

Algorithm (choices measured in ``gonio bench fit``, :mod:`gonio.fitting.speed`):

* **Evaluation.** f_r comes from :mod:`gonio.models._fast` (Dr.Jit LLVM kernels, float64,
  the directions loaded once per fit; for ``roughplastic`` a new (alpha, eta) costs ~4 ms
  there against ~50 ms in the numpy reference) where it is available and agrees with
  ``model.eval``; otherwise from ``model.eval``. Derivatives are exact there: the kernels
  compute f_r and d f_r / d parameter together (:func:`gonio.models._fast.jacobian`, one
  call for all parameters, 3-5x an evaluation), chained through the loss and the unit box.
  On the numpy path they are forward differences.
* **Variable projection** (Golub & Pereyra 1973). Parameters in which f_r is affine
  (per-channel albedos, detected numerically from the model, never listed by hand) are
  solved exactly, by bounded weighted linear least squares, for every value of the
  nonlinear ones; the optimiser only sees the shared nonlinear parameters (roughplastic:
  alpha and eta, 2 instead of 5). This applies to the losses whose residual is affine in
  f_r (``chi2``, ``cosine``); ``robust`` and ``log`` fit all parameters jointly.
* **Global stage.** The defaults plus ``n_starts`` stratified (Latin hypercube, caller's rng)
  points of the nonlinear parameters' unit box, scored with the linear parameters set from
  the data, on at most 3000 data rows; the best ``n_local`` starts that lie in distinct
  basins (unit-box distance >= 0.15) are refined.
* **Local stage.** Levenberg-Marquardt (:mod:`gonio.fitting._lm`) on the residual vector.
* **Energy.** For models that can create energy, ``albedo(wo_k) <= 1`` (each channel, fixed
  outgoing directions) is a nonlinear inequality constraint: when the unconstrained optimum
  violates it, nlopt's SLSQP (Kraft 1988) polishes the full parameter vector under the
  constraint, its objective divided by its starting value (SLSQP throws on objectives of
  order 1e5 with nlopt 2.11).

Reciprocity needs no constraint: every gonio model is reciprocal by construction (tested in
tests/models); the data's reciprocal pairs are a measurement diagnostic, not a fit constraint.

At the optimum the Laplace approximation gives the covariance (J^T J)^-1 of the chi^2 loss
(Fisher information of the Gaussian noise model), with J in natural units (exact from the
compiled kernel; on the numpy path exact columns for the affine parameters, central
differences for the others). Parameters the data cannot
determine (a singular or near-singular Fisher matrix, or a 1-sigma wider than half the
parameter's range) are named, never returned as NaN; strongly correlated pairs
(|rho| >= 0.9) are listed in ``FitResult.correlated``.

References
----------
Golub, G. H., Pereyra, V. (1973). The differentiation of pseudo-inverses and nonlinear least
squares problems whose variables separate. SIAM J. Numer. Anal. 10(2), 413-432.
Kraft, D. (1988). A software package for sequential quadratic programming. DFVLR-FB 88-28.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from gonio.models.geometry import directions

from . import _affine, _loss
from ._lm import levenberg_marquardt
from ._space import ParameterSpace

__all__ = ["FitResult", "fit", "Evaluator"]

#: Rows used to score global-stage starts (the local stage always uses all data).
SCORE_ROWS = 3000
#: Starts closer than this (unit-box distance, max norm) count as one basin.
BASIN_DISTANCE = 0.15
#: Starts scoring worse than this factor times the best start are not refined.
START_RATIO = 30.0
#: Wall-time cap of the constrained SLSQP polish (each constraint gradient integrates the
#: albedo P + 1 times); a polish cut short is reported as not converged.
SLSQP_MAXTIME_S = 20.0


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
    def bic(self) -> float:
        """Bayesian information criterion, chi^2 + k ln n (Schwarz 1978)."""
        return self.chi2 + self.space.size * np.log(self.n_used)

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


# ---------------------------------------------------------------------------- evaluation
#: Below this many points the compiled kernels' fixed cost (~1 ms a call) exceeds numpy's.
FAST_MIN_POINTS = 500
#: Models whose parameter-dependent precomputation is much cheaper compiled (roughplastic's
#: quadrature tables: ~4 ms in Dr.Jit against ~50 ms in numpy): compiled at any size.
FAST_ALWAYS = frozenset({"roughplastic"})

class Evaluator:
    """f_r of one model at fixed directions, compiled where possible; counts evaluations."""

    def __init__(self, model, wi, wo, n_channels: int, use_fast: bool | None = None):
        self.model, self.wi, self.wo = model, wi, wo
        self.n_evals = 0
        self.fast = False
        self._dirs = None
        worth_it = len(wi) >= FAST_MIN_POINTS or model.name in FAST_ALWAYS
        if use_fast is not False and n_channels == 3 and (use_fast or worth_it):
            self.fast = _fast_agrees(model)
        self.backend = "drjit-llvm" if self.fast else "numpy"

    def _resident(self):
        from gonio.models import _fast
        if self._dirs is None:  # directions loaded into Dr.Jit once per fit
            self._dirs = _fast.Directions(self.wi, self.wo, np.float64)
        return self._dirs

    def __call__(self, params) -> np.ndarray:
        self.n_evals += 1
        if self.fast:
            from gonio.models import _fast
            return _fast.eval_resident(self.model, self._resident(), params)
        return np.asarray(self.model.eval(self.wi, self.wo, params), dtype=np.float64)

    def jacobian(self, params):
        """(f_r, {parameter: d f_r / d parameter (N, C)}) from the compiled kernel's exact
        derivatives (:func:`gonio.models._fast.jacobian`; one call, counted as one
        evaluation), or None on the numpy path."""
        if not self.fast:
            return None
        from gonio.models import _fast
        self.n_evals += 1
        return _fast.jacobian(self.model, self._resident(), params)


_FAST_OK: dict = {}


def _fast_agrees(model) -> bool:
    """True when gonio.models._fast evaluates this model and matches model.eval (checked once)."""
    key = (model.name, tuple(sorted((k, str(v)) for k, v in model.options.items())))
    if key in _FAST_OK:
        return _FAST_OK[key]
    ok = False
    try:
        from gonio.models import _fast
        if _fast.available():
            rng = np.random.default_rng(12345)
            t = np.radians(rng.uniform(0, 80, (2, 16)))
            p = rng.uniform(-np.pi, np.pi, (2, 16))
            wi, wo = directions(t[0], p[0]), directions(t[1], p[1])
            params = {q.name: q.default for q in model.parameters}
            a = _fast.eval(model, wi, wo, params)
            b = model.eval(wi, wo, params)
            ok = bool(np.allclose(a, b, rtol=1e-8, atol=1e-12 * max(1.0, float(np.max(np.abs(b))))))
    except Exception:  # no compiled kernel for this model, or no working LLVM
        ok = False
    _FAST_OK[key] = ok
    return ok


# ---------------------------------------------------------------------------- the problem
class _Problem:
    """Residuals of one fit, with the affine parameters projected out where the loss allows."""

    def __init__(self, meas, model, space, loss, evaluator=None, use_fast=None, linear=None):
        self.meas, self.model, self.space, self.loss = meas, model, space, loss
        self.eval = evaluator or Evaluator(model, meas.wi, meas.wo, meas.n_channels, use_fast)
        self.use = meas.use
        cos_i = np.broadcast_to(np.clip(meas.wi[:, 2:3], 0.0, 1.0), meas.brdf.shape)
        self.weight = 1.0 / meas.brdf_std if loss in ("chi2", "robust") else cos_i
        self.linear = []
        self.linear = _linear_groups(self) if linear is None else linear
        self.varpro = bool(self.linear) and loss in ("chi2", "cosine")
        lin_idx = sorted(i for g in self.linear for i in g["index"]) if self.varpro else []
        self.nl_idx = np.array([i for i in range(space.size) if i not in lin_idx], dtype=int)
        self._lin_index = np.array(lin_idx, dtype=int)
        self._last = (None, None)

    @property
    def n_evals(self):
        return self.eval.n_evals

    # -- plain residuals
    def f_x(self, x):
        return self.eval(self.space.to_params(x))

    def residuals_x(self, x, loss=None):
        fr = self.f_x(x)
        r = _loss.residuals(loss or self.loss, fr, self.meas)
        if not np.all(np.isfinite(r)):
            raise FloatingPointError(f"model {self.model.name} returned non-finite f_r at "
                                     f"{dict(zip(self.space.names, np.round(x, 6)))}")
        return r

    def lm_residuals_u(self, u):
        """Residuals whose sum of squares is the objective (robust loss: transformed)."""
        r = self.residuals_x(self.space.from_unit(u))
        if self.loss == "robust":  # rho^2 = 2 (sqrt(1 + r^2) - 1), without the cancellation
            return r * np.sqrt(2.0 / (np.sqrt(1.0 + r * r) + 1.0))
        return r

    # -- exact derivatives (compiled path)
    def residual_jacobian_x(self, x, cols, loss=None):
        """Residuals at x and their exact derivatives with respect to x[cols] (natural units),
        shape (M, len(cols)), from the compiled kernel's Jacobian; None on the numpy path
        or where the derivatives are not finite (the callers then difference)."""
        loss = loss or self.loss
        out = self.eval.jacobian(self.space.to_params(x))
        if out is None:
            return None
        f, J = out
        meas = self.meas
        r = _loss.residuals(loss, f, meas)
        drdf = np.broadcast_to(_loss.residual_derivative(loss, f, meas), f.shape)
        D = np.empty((r.size, len(cols)))
        for k, j in enumerate(cols):
            e = self.space.entries[j]
            dfdx = J[e.param]
            if e.channel >= 0:
                col = np.zeros_like(f)
                col[:, e.channel] = dfdx[:, e.channel] * drdf[:, e.channel]
            else:
                col = dfdx * drdf
            D[:, k] = col[meas.use]
        if not (np.all(np.isfinite(D)) and np.all(np.isfinite(r))):
            return None
        return r, D

    def lm_jacobian_u(self, u, _r=None):
        """Exact Jacobian of :meth:`lm_residuals_u` at u (None: difference instead); the
        residuals argument of ``levenberg_marquardt``'s ``jac(u, r)`` is not needed."""
        x = self.space.from_unit(u)
        out = self.residual_jacobian_x(x, range(self.space.size))
        if out is None:
            return None
        r, D = out
        D = D * self.space.dx_du(x)[None, :]
        if self.loss == "robust":  # rho(r) = r sqrt(2 / (s + 1)), s = sqrt(1 + r^2)
            s = np.sqrt(1.0 + r * r)
            D = D * (np.sqrt(0.5 * (s + 1.0)) / s)[:, None]  # d rho / dr
        return D

    # -- variable projection
    def basis(self, x):
        """f_r = base + sum_g a_g * B_g (per channel) at the nonlinear part of x."""
        x = np.array(x, dtype=np.float64)
        for g in self.linear:
            x[g["index"]] = g["v0"]
        base = self.f_x(x)
        cols = []
        for g in self.linear:
            x1 = x.copy()
            x1[g["index"]] = g["v1"]
            cols.append((self.f_x(x1) - base) / (g["v1"] - g["v0"]))
        base = base - sum(B * g["v0"] for B, g in zip(cols, self.linear))
        return base, cols

    def solve_linear(self, x):
        """x with its affine parameters at their bounded weighted least-squares values."""
        x = np.array(x, dtype=np.float64)
        base, cols = self.basis(x)
        self._cols = cols
        w, y, use = self.weight, self.meas.brdf, self.use
        for c in range(base.shape[1]):
            m = use[:, c]
            idx = [g["index"][c] for g in self.linear]
            A = (np.stack([B[m, c] for B in cols], axis=1)) * w[m, c][:, None]
            b = (y[m, c] - base[m, c]) * w[m, c]
            lo, hi = self.space.lower[idx], self.space.upper[idx]
            if A.shape[1] == 1:
                den = float(A[:, 0] @ A[:, 0])
                a = np.array([float(A[:, 0] @ b) / den if den > 0 else x[idx[0]]])
            else:
                a = np.linalg.lstsq(A, b, rcond=None)[0]
                if np.any(a < lo) or np.any(a > hi):
                    from scipy.optimize import lsq_linear
                    a = lsq_linear(A, b, bounds=(lo, hi), method="bvls").x
            x[idx] = np.clip(a, lo, hi)
        return x

    def reduced_residuals(self, v, x_template):
        """Residuals at nonlinear unit coordinates v, affine parameters projected out."""
        u = self.space.to_unit(x_template)
        u[self.nl_idx] = v
        x = self.solve_linear(self.space.from_unit(u))
        self._last = (v.copy(), x)
        return self.residuals_x(x)

    def kaufman_jacobian(self, v, r, x_template, h=1e-6):
        """Jacobian of the reduced residuals at v (Kaufman 1975): derivatives in the nonlinear
        coordinates at fixed affine parameters (exact from the compiled kernel; else forward
        differences, one evaluation per nonlinear parameter), projected off the span of the
        affine columns (those not held at a bound)."""
        x = self.x_of(v, x_template)
        cols = self._cols
        exact = self.residual_jacobian_x(x, self.nl_idx)
        if exact is not None:
            J = exact[1] * self.space.dx_du(x)[self.nl_idx][None, :]
        else:
            u = self.space.to_unit(x)
            J = np.empty((r.size, v.size))
            for k, j in enumerate(self.nl_idx):
                step = h if u[j] + h <= 1.0 else -h
                up = u.copy()
                up[j] += step
                xp = self.space.from_unit(up)
                xp[self._lin_index] = x[self._lin_index]
                J[:, k] = (self.residuals_x(xp) - r) / step
        lin_cols = []
        for g, B in zip(self.linear, cols):
            for c, i in enumerate(g["index"]):
                if self.space.lower[i] < x[i] < self.space.upper[i]:
                    Bc = np.zeros_like(B)
                    Bc[:, c] = B[:, c] * self.weight[:, c]
                    lin_cols.append(Bc[self.use])
        if lin_cols:
            Q, _ = np.linalg.qr(np.stack(lin_cols, axis=1))
            J = J - Q @ (Q.T @ J)
        return J

    def x_of(self, v, x_template):
        if self._last[0] is not None and np.array_equal(self._last[0], v):
            return self._last[1]
        u = self.space.to_unit(x_template)
        u[self.nl_idx] = v
        return self.solve_linear(self.space.from_unit(u))

    def albedo_excess(self, x, wo):
        a = self.model.albedo(wo, self.space.to_params(x))
        return np.asarray(a, dtype=np.float64).reshape(-1) - 1.0


def _linear_groups(problem):
    """Per-channel parameters in which f_r is affine, jointly, channel by channel.

    Tested numerically at two interior points: f(a) for three values of each group must lie
    on a line for every channel separately, and a random joint setting of all accepted groups
    must equal the sum of their effects. Returns [{"param", "index" (per channel), "v0", "v1"}].
    """
    space = problem.space
    groups = {}
    for i, e in enumerate(space.entries):
        if e.channel >= 0:
            groups.setdefault(e.param, []).append(i)
    groups = {k: v for k, v in groups.items() if len(v) == space.n_channels}
    if not groups:
        return []
    test_u = (np.full(space.size, 0.37), np.full(space.size, 0.61))
    accepted = []
    for name, index in groups.items():
        lo, hi = space.lower[index[0]], space.upper[index[0]]
        v0, v1 = lo + 0.2 * (hi - lo), lo + 0.8 * (hi - lo)
        g = {"param": name, "index": list(index), "v0": float(v0), "v1": float(v1)}
        if all(_affine_ok(problem, u, accepted + [g]) for u in test_u):
            accepted.append(g)
    return accepted


def _affine_ok(problem, u, gs):
    space = problem.space
    x = space.from_unit(u)
    try:
        saved = problem.linear
        problem.linear = gs
        base, cols = problem.basis(x)
        problem.linear = saved
        rng = np.random.default_rng(7)
        xt = x.copy()
        pred = base.copy()
        for g, B in zip(gs, cols):
            lo, hi = space.lower[g["index"][0]], space.upper[g["index"][0]]
            a = lo + (hi - lo) * rng.uniform(0.1, 0.9, space.n_channels)
            xt[g["index"]] = a
            pred = pred + B * a[None, :]
        f = problem.f_x(xt)
    except (ValueError, FloatingPointError):
        return False
    scale = max(float(np.max(np.abs(f))), 1e-300)
    return bool(np.all(np.isfinite(f)) and np.max(np.abs(f - pred)) <= 1e-9 * scale)


def _energy_directions(n=6):
    theta = np.deg2rad(np.linspace(0.0, 85.0, n))
    return np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1)


def _stratified(rng, n, d):
    """n Latin-hypercube points in [0, 1]^d."""
    if n <= 0 or d == 0:
        return np.zeros((0, d))
    cut = (np.arange(n)[:, None] + rng.random((n, d))) / n
    for j in range(d):
        cut[:, j] = cut[rng.permutation(n), j]
    return cut


# ---------------------------------------------------------------------------- global stage
def _channel_costs(problem, x):
    """Objective per colour channel at x (affine parameters projected out first)."""
    if problem.varpro:
        x = problem.solve_linear(x)
    r = problem.residuals_x(x)
    if problem.loss == "robust":
        r2 = 2.0 * (np.sqrt(1.0 + r * r) - 1.0)
    else:
        r2 = r * r
    full = np.zeros(problem.meas.brdf.shape)
    full[problem.use] = r2
    return full.sum(axis=0)


def _global_starts(problem, free, u_default, n_starts, rng):
    """Stratified starts over the searched coordinates ``free`` and their scores.

    Shared coordinates get a Latin hypercube. Per-channel nonlinear coordinates (conductor
    eta and k, Cook-Torrance f0) only change their own channel, so each channel picks its
    best candidate independently: K evaluations search K^C combinations.
    """
    space = problem.space
    shared = [int(i) for i in free if space.entries[i].channel < 0]
    block = [int(i) for i in free if space.entries[i].channel >= 0]
    pos = {int(i): k for k, i in enumerate(free)}
    if n_starts is None:
        n_starts = min(24, 4 + 4 * len(shared)) if block else min(24, 4 + 4 * int(free.size))
    if not free.size:
        return [u_default[free]], np.zeros(1)
    if not block:
        starts = [u_default[free]] + list(_stratified(rng, n_starts, free.size))
        scores = np.array([_safe_sum(_score(problem, u_default, free, v)) for v in starts])
        return starts, scores
    C = space.n_channels
    names = sorted({space.entries[i].param for i in block})
    by_channel = [[i for n in names for i in block if space.entries[i].param == n and space.entries[i].channel == c]
                  for c in range(C)]
    n_k = min(24, 4 + 4 * len(names))
    S = np.vstack([u_default[shared][None, :], _stratified(rng, n_starts, len(shared))]) if shared else np.zeros((1, 0))
    K = [np.vstack([u_default[idx][None, :], _stratified(rng, n_k, len(names))]) for idx in by_channel]
    starts, scores = [], []
    for s_row in S:
        costs = np.full((n_k + 1, C), np.inf)
        for k in range(n_k + 1):
            v = u_default[free].copy()
            for j, i in enumerate(shared):
                v[pos[i]] = s_row[j]
            for c, idx in enumerate(by_channel):
                for j, i in enumerate(idx):
                    v[pos[i]] = K[c][k, j]
            costs[k] = _score(problem, u_default, free, v)
        best_k = np.argmin(np.where(np.isfinite(costs), costs, np.inf), axis=0)
        v = u_default[free].copy()
        for j, i in enumerate(shared):
            v[pos[i]] = s_row[j]
        for c, idx in enumerate(by_channel):
            for j, i in enumerate(idx):
                v[pos[i]] = K[c][best_k[c], j]
        starts.append(v)
        scores.append(float(sum(costs[best_k[c], c] for c in range(C))))
    return starts, np.array(scores)


def _score(problem, u_default, free, v):
    u = u_default.copy()
    u[free] = v
    try:
        c = _channel_costs(problem, space_x(problem, u))
    except FloatingPointError:
        return np.full(problem.space.n_channels, np.inf)
    return np.where(np.isfinite(c), c, np.inf)


def space_x(problem, u):
    return problem.space.from_unit(u)


def _safe_sum(c):
    v = float(np.sum(c))
    return v if np.isfinite(v) else np.inf


def choose_starts(starts, scores, n_local, start_ratio=START_RATIO, basin_distance=BASIN_DISTANCE):
    """Indices of the best-scoring starts that lie in distinct basins (unit-box distance
    >= ``basin_distance``), at most ``n_local``, none worse than ``start_ratio`` x the best."""
    chosen = []
    for k in np.argsort(scores, kind="stable"):
        if chosen and not scores[k] <= start_ratio * scores[chosen[0]] + 10.0:
            break  # far worse than the best start: not worth a local run
        if all(np.max(np.abs(starts[k] - starts[j])) >= basin_distance for j in chosen):
            chosen.append(int(k))
        if len(chosen) >= max(1, n_local):
            break
    return chosen


# ---------------------------------------------------------------------------- the fit
def fit(meas, model, *, loss: str = "chi2", fixed: dict | None = None, rng=None,
        n_starts: int | None = None, n_local: int = 3, maxeval: int = 2000, enforce_energy: bool | None = None,
        use_fast: bool | None = None) -> FitResult:
    """Fit ``model`` to ``meas``.

    Parameters
    ----------
    meas : Measurements
        The data (f_r in sr^-1 with 1-sigma).
    model
        A gonio model (``gonio.models.get(...)``).
    loss : {"chi2", "robust", "cosine", "log"}
        See :mod:`gonio.fitting._loss`. Only ``chi2`` gives a calibrated covariance.
    fixed : dict, optional
        Parameters held fixed at the given values.
    rng : numpy.random.Generator
        Draws the global stage's starting points. Required: fits are reproducible.
    n_starts, n_local : int
        Stratified starting points scored (default 4 + 4 d for d parameters searched, at
        most 24), and how many of the best (in distinct basins) are refined locally.
    maxeval : int
        Model evaluations per local run.
    enforce_energy : bool, optional
        Constrain albedo <= 1; defaults to ``not model.energy_conserving``.
    use_fast : bool, optional
        Use the compiled Dr.Jit kernels (default: where available); False forces numpy.

    Returns
    -------
    FitResult
    """
    if rng is None or not isinstance(rng, np.random.Generator):
        raise TypeError("fit() needs rng=numpy.random.Generator (seeded) so the fit is reproducible")
    _loss.validate_loss(loss)
    space = ParameterSpace(model, meas.n_channels, fixed, meas.channels)
    if space.size == 0:
        raise ValueError("every parameter is fixed: nothing to fit")
    if enforce_energy is None:
        enforce_energy = not getattr(model, "energy_conserving", True)
    t0 = time.perf_counter()
    if _affine.applicable(meas, model, space, loss, enforce_energy, use_fast):
        res = _affine.fit_affine(meas, model, space, loss, rng, n_starts=n_starts, n_local=n_local,
                                 maxeval=maxeval, score_rows=SCORE_ROWS)
        if res is not None:
            return res
    problem = _Problem(meas, model, space, loss, use_fast=use_fast)
    energy_wo = _energy_directions()

    # ---- global stage: stratified starts over the nonlinear parameters (or all of them)
    free = problem.nl_idx if problem.varpro else np.arange(space.size)
    u_default = space.to_unit(space.default())
    if problem.varpro:
        u_default = space.to_unit(problem.solve_linear(space.default()))
    stride = max(1, int(np.ceil(meas.n_points / SCORE_ROWS)))
    scorer = problem if stride == 1 else _Problem(meas.subset(slice(None, None, stride)), model, space, loss,
                                                  use_fast=problem.eval.fast, linear=problem.linear)
    starts, scores = _global_starts(scorer, free, u_default, n_starts, rng)
    chosen = choose_starts(starts, scores, n_local)

    # ---- local stage: Levenberg-Marquardt from each chosen start
    atol = 1e-4 if loss in ("chi2", "robust") else 0.0
    best = None
    for k in chosen:
        n0 = problem.n_evals

        def budget(n0=n0):
            return problem.n_evals - n0 < maxeval

        def abandon(it, cost, best=best):  # race later starts against the best refined one
            return best is not None and ((it >= 1 and cost > START_RATIO * best[1] + 10.0)
                                         or (it >= 2 and cost > 1.5 * best[1] + 10.0))

        try:
            if problem.varpro and free.size == 0:
                x = problem.solve_linear(space.default())
                r = problem.residuals_x(x)
                res = (x, _loss.objective(loss, r), True, "linear least squares (exact)")
            elif problem.varpro:
                lm = levenberg_marquardt(lambda v: problem.reduced_residuals(v, space.default()), starts[k],
                                         atol=atol, budget=budget, abandon=abandon,
                                         jac=lambda v, r: problem.kaufman_jacobian(v, r, space.default()))
                x = problem.x_of(lm.u, space.default())
                res = (x, _loss.objective(loss, problem.residuals_x(x)), lm.converged, lm.message)
            else:
                u0 = u_default.copy()
                u0[free] = starts[k]
                lm = levenberg_marquardt(problem.lm_residuals_u, u0, atol=atol, budget=budget, abandon=abandon,
                                         jac=problem.lm_jacobian_u)
                x = space.from_unit(lm.u)
                res = (x, _loss.objective(loss, problem.residuals_x(x)), lm.converged, lm.message)
        except FloatingPointError as exc:
            res = (None, np.inf, False, str(exc))
        if best is None or res[1] < best[1]:
            best = res
    x, best_val, converged, message = best
    if x is None:
        raise FloatingPointError(f"no start gave finite residuals: {message}")
    method = ("variable projection + Levenberg-Marquardt" if problem.varpro else "Levenberg-Marquardt")

    # ---- energy: constrained polish with SLSQP where the optimum breaks albedo <= 1
    energy = {"enforced": bool(enforce_energy)}
    if enforce_energy and np.max(problem.albedo_excess(x, energy_wo)) > 1e-6:
        x, best_val, converged, message = _slsqp_energy(problem, x, energy_wo, maxeval)
        method += " + nlopt LD_SLSQP (albedo <= 1)"
    if enforce_energy:
        max_albedo = float(np.max(problem.albedo_excess(x, energy_wo)) + 1.0)
        energy.update(max_albedo=max_albedo, holds=bool(max_albedo <= 1.0 + 1e-4))
    else:  # the model conserves energy for every parameter in its bounds (tests/models)
        energy.update(max_albedo=None, holds=True, by_construction=True)

    # ---- Laplace uncertainty from the chi^2 residuals (Fisher information)
    J, r_chi = jacobian_chi2(problem, x)
    cov, undetermined = _laplace(J, space)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))

    fr = problem.f_x(x)
    diff = (fr - meas.brdf)[meas.use]
    cos_i = np.broadcast_to(np.clip(meas.wi[:, 2:3], 0, 1), fr.shape)[meas.use]
    n_evals = problem.n_evals + (scorer.n_evals if scorer is not problem else 0)
    return FitResult(
        model=model, space=space, x=x, std=std, cov=cov, loss=loss, objective=float(best_val),
        chi2=float(r_chi @ r_chi), n_used=meas.n_used, n_evals=int(n_evals),
        time_s=time.perf_counter() - t0, converged=bool(converged), message=message,
        at_bound=[n for n, b in zip(space.names, space.at_bound(x)) if b],
        undetermined=undetermined, energy=energy,
        rmse_fr=float(np.sqrt(np.mean(diff ** 2))),
        rmse_cos_fr=float(np.sqrt(np.mean((diff * cos_i) ** 2))),
        method=f"{method} [{problem.eval.backend}]",
        linear=[g["param"] for g in problem.linear] if problem.varpro else [],
    )


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
    J = np.empty((r0.size, space.size))
    lin = {}
    if problem.linear:
        _, cols = problem.basis(x)
        for g, B in zip(problem.linear, cols):
            for c, i in enumerate(g["index"]):
                Bc = np.zeros_like(B)
                Bc[:, c] = B[:, c]
                lin[i] = (Bc / meas.brdf_std)[meas.use]
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
        J[:, j] = ((fp - fm) / meas.brdf_std)[meas.use] / (hi - lo)
    if not np.all(np.isfinite(J)):
        raise FloatingPointError("non-finite Jacobian at the optimum")
    return J, r0


def _slsqp_energy(problem, x0, energy_wo, maxeval):
    """SLSQP on the full unit box with albedo(wo_k) <= 1 (each channel) as constraints."""
    import nlopt

    from ._lm import forward_jacobian

    space, loss = problem.space, problem.loss
    r_of = problem.lm_residuals_u
    u0 = np.clip(space.to_unit(x0), 1e-9, 1 - 1e-9)
    norm = max(float(np.sum(r_of(u0) ** 2)), 1e-300)

    def f(u, grad):
        r = r_of(u)
        if grad.size:
            J = problem.lm_jacobian_u(u)
            grad[:] = 2.0 * ((J if J is not None else forward_jacobian(r_of, u, r)).T @ r) / norm
        return float(r @ r) / norm

    quad = _AlbedoQuadrature(problem, energy_wo)
    margin = [0.0]  # grows by the gap between this quadrature and model.albedo, if any

    def cons(result, u, grad):
        c = quad(space.from_unit(u)) + margin[0]
        result[:] = c
        if grad.size:
            for j in range(u.size):
                step = 1e-6 if u[j] + 1e-6 <= 1.0 else -1e-6
                up = u.copy()
                up[j] += step
                grad[:, j] = (quad(space.from_unit(up)) + margin[0] - c) / step

    u = u0
    for _ in range(3):
        opt = nlopt.opt(nlopt.LD_SLSQP, space.size)
        opt.set_lower_bounds(np.zeros(space.size))
        opt.set_upper_bounds(np.ones(space.size))
        opt.set_min_objective(f)
        m = energy_wo.shape[0] * problem.meas.n_channels
        opt.add_inequality_mconstraint(cons, np.full(m, 1e-6))
        opt.set_ftol_rel(1e-12)
        opt.set_xtol_rel(1e-9)
        opt.set_maxeval(min(maxeval, 200))
        opt.set_maxtime(SLSQP_MAXTIME_S)
        try:
            u = opt.optimize(np.clip(u, 1e-9, 1 - 1e-9))
            status = opt.last_optimize_result()
        except nlopt.RoundoffLimited:
            status = nlopt.ROUNDOFF_LIMITED
        except (RuntimeError, ValueError) as exc:
            x = space.from_unit(u0)
            return x, _loss.objective(loss, problem.residuals_x(x)), False, f"nlopt SLSQP failed: {exc}"
        excess = float(np.max(problem.albedo_excess(space.from_unit(u), energy_wo)))
        if excess <= 1e-4:
            break
        margin[0] += excess + 1e-4
    x = space.from_unit(u)
    ok = status in (1, 2, 3, 4) or status == nlopt.ROUNDOFF_LIMITED
    if np.max(problem.albedo_excess(space.from_unit(u), energy_wo)) > 1e-4:
        ok = False
    return x, _loss.objective(loss, problem.residuals_x(x)), ok, _status_text(status)


class _AlbedoQuadrature:
    """albedo(wo_k) - 1 by a fixed product rule over wi (Gauss-Legendre in cos(theta_i),
    uniform in phi_i), evaluated with the fit's (compiled) evaluator: one batched evaluation
    instead of ``model.albedo``'s quadrature per call, so that SLSQP's constraint gradients
    stay cheap. The final albedo check uses ``model.albedo``."""

    def __init__(self, problem, wo, n_mu=64, n_phi=96):
        x, w = np.polynomial.legendre.leggauss(n_mu)
        mu, w_mu = 0.5 * (x + 1.0), 0.5 * w
        phi = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
        M, PHI = np.meshgrid(mu, phi, indexing="ij")
        s = np.sqrt(1.0 - M ** 2)
        wi = np.stack([s * np.cos(PHI), s * np.sin(PHI), M], axis=-1).reshape(-1, 3)
        self.weight = (w_mu[:, None] * M * (2.0 * np.pi / n_phi)).reshape(-1)
        self.k = wo.shape[0]
        self.n = wi.shape[0]
        self.space = problem.space
        self.eval = Evaluator(problem.model, np.tile(wi, (self.k, 1)), np.repeat(wo, self.n, axis=0),
                              problem.meas.n_channels, use_fast=problem.eval.fast)

    def __call__(self, x):
        f = self.eval(self.space.to_params(x)).reshape(self.k, self.n, -1)
        return (np.einsum("knc,n->kc", f, self.weight) - 1.0).reshape(-1)


def _laplace(J, space, cond_limit=1e12):
    """Covariance (J^T J)^-1 and the names of parameters the data does not determine."""
    fisher = J.T @ J
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


def _status_text(status) -> str:
    return {1: "success", 2: "stopval reached", 3: "ftol reached", 4: "xtol reached",
            5: "maxeval reached", 6: "maxtime reached", -1: "failure", -4: "roundoff limited"}.get(int(status), str(status))
