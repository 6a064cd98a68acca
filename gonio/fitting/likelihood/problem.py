"""The general fit problem: f_r at fixed directions (compiled where possible), residuals
and their exact or differenced Jacobians, and variable projection of the parameters in
which f_r is affine (detected numerically, never listed by hand).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear

from gonio.models import fast
from gonio.core.geometry import directions

from gonio.fitting.likelihood import loss as _loss
from gonio.fitting.likelihood.channel_groups import ChannelGroups, groupable

__all__ = ["Evaluator", "Problem", "FAST_MIN_POINTS", "NORMAL_LOSSES", "TRIAL_NORMAL_MAX"]

#: Below this many points a fit that evaluates f_r itself (variable projection, the robust
#: and log losses: many calls, each handing N x 3 values to numpy) runs faster on numpy
#: (cooktorrance's variable projection at 100 points: 150 ms on numpy, 270 ms compiled).
#: A model whose parameter-dependent precomputation is much cheaper compiled declares it
#: (``model.structure.compile_always``: roughplastic's quadrature tables, ~4 ms in Dr.Jit
#: against ~50 ms in numpy) and is compiled at any size; so is every problem whose
#: Levenberg-Marquardt steps come from the compiled normal equations (:data:`NORMAL_LOSSES`
#: without variable projection: a few reduced sums per step, nothing per pair handed back;
#: roughconductor at 100 points: 20 ms compiled, 60 ms on numpy, and the numpy path's global
#: stage missed the basin of a Beckmann conductor the compiled default-first run finds).
FAST_MIN_POINTS = 500
#: Losses whose Levenberg-Marquardt normal equations the compiled kernel reduces
#: (:meth:`_Problem.lm_normal_u`): those whose residual is affine in f_r without a transform,
#: and ``log``, whose transform ln(1 + f_r cos_i) and its derivative the kernel applies
#: itself (:func:`gonio.models.fast.normal_equations` with ``log``). Principled on
#: colodur_napoli_4f (7592 pairs, 12 parameters): an iteration's Jacobian and J^T J from the
#: N x P Jacobian cost several kernel outputs handed to numpy and the products there; the
#: reduced sums hand back 91 numbers.
NORMAL_LOSSES = ("chi2", "cosine", "luminance", "log")
#: Up to this many points a Levenberg-Marquardt trial step is costed by the normal-equation
#: kernel itself, not the cheaper sum of squares: an accepted step (most of them) then
#: brings the next step's normal equations with it, one kernel call per iteration instead
#: of two. Below ~1e4 points a call costs its overhead (roughconductor, minimum of 300
#: calls: 100 points sum of squares 36 us, normal equations 46 us; 1e4: 63 and 146 us);
#: above, the normal equations' 36 sums dominate (1e5: 0.44 and 1.3 ms; 1e6: 5.5 and 26 ms)
#: and a rejected trial would waste them.
TRIAL_NORMAL_MAX = 20_000


class Evaluator:
    """f_r of one model at fixed directions, compiled where possible; counts evaluations."""

    def __init__(self, model, wi, wo, n_channels: int, use_fast: bool | None = None):
        self.model, self.wi, self.wo = model, wi, wo
        self.n_evals = 0
        self.fast = False
        self._dirs = None
        self._yw = None
        self.layer = None
        worth_it = len(wi) >= FAST_MIN_POINTS or model.structure.compile_always
        if use_fast is not False and n_channels == 3 and (use_fast or worth_it):
            self.fast = _fast_agrees(model)
            layer = getattr(model, "_layer", None)
            if not self.fast and hasattr(model, "layers") and layer is not None and layer.structure.derivatives:
                # a two-lobe model (gonio.models.catalogue.twolobe): its layer's kernel, twice
                self.layer = layer if _fast_agrees(layer) else None
        self.grouped = None
        if use_fast is not False and n_channels != 3 and (use_fast or worth_it) and groupable(model):
            three = Evaluator(model, wi, wo, 3, use_fast=True)    # a spectral fit: channels in threes
            if three.fast or three.layer is not None:
                self.grouped = ChannelGroups(model, three, n_channels)
        self.backend = ("drjit-llvm" if self.fast or self.layer is not None else
                        "drjit-llvm, channels in groups of 3" if self.grouped is not None else "numpy")

    def _resident(self):
        if self._dirs is None:  # directions loaded into Dr.Jit once per fit
            self._dirs = fast.Directions(self.wi, self.wo, np.float64)
        return self._dirs

    def __call__(self, params) -> np.ndarray:
        self.n_evals += 1
        if self.grouped is not None:
            return self.grouped.eval(params)
        if self.fast:
            return fast.eval_resident(self.model, self._resident(), params)
        if self.layer is not None:
            p1, p2, w = self.model.layers(self.model.validate(params))
            d = self._resident()
            return (1.0 - w) * fast.eval_resident(self.layer, d, p1) + w * fast.eval_resident(self.layer, d, p2)
        return np.asarray(self.model.eval_reference(self.wi, self.wo, params), dtype=np.float64)

    def normal(self, params, y, w, log=False):
        """(cost, g, A, entries) of :func:`gonio.models.fast.normal_equations` on the resident
        directions (one kernel, nothing stored per pair; counted as one evaluation), or None
        on the numpy path. ``y``, ``w``: (N, 3) data and weights, loaded once per fit;
        ``log``: the log loss's residuals (``y`` then the data's log values)."""
        if not self.fast:
            return None
        self.n_evals += 1
        return fast.normal_equations(self.model, self._resident(), params, *self._loaded(y, w), log=log)

    def _loaded(self, y, w):
        """``y`` and ``w`` as the resident directions' kernels take them, loaded once per fit."""
        if self._yw is None or self._yw[0] is not y:
            d = self._resident()
            self._yw = (y, d.channels(y, "y"), d.channels(w, "w"))
        return self._yw[1], self._yw[2]

    def sse(self, params, y, w, log=False):
        """sum w (f_r - y)^2 from one compiled kernel (counted as one evaluation), or None on
        the numpy path; ``y``, ``w``, ``log`` as for :meth:`normal`."""
        if not self.fast:
            return None
        self.n_evals += 1
        return fast.weighted_sse(self.model, self._resident(), params, *self._loaded(y, w), log=log)

    def jacobian(self, params):
        """(f_r, {parameter: d f_r / d parameter (N, C)}) from the compiled kernel's exact
        derivatives (:func:`gonio.models.fast.jacobian`; one call, counted as one
        evaluation), or the model's own exact numpy derivatives where its kernel gives values
        only (``jacobian_host``, else ``jacobian_reference``: tabulated, whose parameters act
        through host tables);
        None otherwise (the callers then difference). Channels beyond three: in groups of three."""
        if self.grouped is not None:
            self.n_evals += 1
            return self.grouped.jacobian(params)
        if self.layer is not None:
            self.n_evals += 1
            return self._layered_jacobian(params)
        if not self.fast or not self.model.structure.derivatives:
            host = getattr(self.model, "jacobian_host", None) or getattr(self.model, "jacobian_reference", None)
            if host is None:
                return None
            self.n_evals += 1
            return host(self.wi, self.wo, params)
        self.n_evals += 1
        return fast.jacobian(self.model, self._resident(), params)

    def _layered_jacobian(self, params):
        """A two-lobe model's (f, J) from its layer's kernel at each lobe: f = (1 - w) f1 + w
        f2, so d f / d(shared) = (1 - w) J1 + w J2, d f / d alpha = (1 - w) J1[alpha],
        d f / d alpha2 = w J2[alpha], d f / d weight = f2 - f1."""
        p1, p2, w = self.model.layers(self.model.validate(params))
        d = self._resident()
        f1, J1 = fast.jacobian(self.layer, d, p1)
        f2, J2 = fast.jacobian(self.layer, d, p2)
        J = {k: (1.0 - w) * J1[k] + w * J2[k] for k in J1 if k != "alpha"}
        J["alpha"], J["alpha2"], J["weight"] = (1.0 - w) * J1["alpha"], w * J2["alpha"], f2 - f1
        return (1.0 - w) * f1 + w * f2, J


_FAST_OK: dict = {}


def _fast_agrees(model) -> bool:
    """True when gonio.models.fast evaluates this model and matches model.eval (checked once)."""
    key = (model.name, tuple(sorted((k, str(v)) for k, v in model.options.items())))
    if key in _FAST_OK:
        return _FAST_OK[key]
    ok = False
    try:
        if model.structure.kernel and fast.available():
            rng = np.random.default_rng(12345)
            t = np.radians(rng.uniform(0, 80, (2, 16)))
            p = rng.uniform(-np.pi, np.pi, (2, 16))
            wi, wo = directions(t[0], p[0]), directions(t[1], p[1])
            params = {q.name: q.default for q in model.parameters}
            a = fast.eval(model, wi, wo, params)
            b = model.eval_reference(wi, wo, params)
            ok = bool(np.allclose(a, b, rtol=1e-8, atol=1e-12 * max(1.0, float(np.max(np.abs(b))))))
    except Exception:  # no compiled kernel for this model, or no working LLVM
        ok = False
    _FAST_OK[key] = ok
    return ok


def _residual_weight(loss, meas, cos_i):
    """d residual / d f_r of the loss, for its weighted linear least squares (the affine
    parameters: variable projection, or a start's albedos): 1 / sigma (chi2, robust), cos
    theta_i (cosine), the luminance loss's weight, and for the log loss its first-order
    expansion about the measured value, ln(1 + f c) - ln(1 + y c) ~ c (f - y) / (1 + y c)."""
    if loss in ("chi2", "robust"):
        return 1.0 / meas.brdf_std
    if loss == "log":
        return cos_i / (1.0 + np.maximum(meas.brdf * cos_i, -0.999))
    if loss in _loss.WEIGHTED_L2:
        return np.broadcast_to(_loss.fixed_weight(loss, meas), cos_i.shape)
    return cos_i


class _Problem:
    """Residuals of one fit, with the affine parameters projected out where the loss allows."""

    def __init__(self, meas, model, space, loss, evaluator=None, use_fast=None, linear=None):
        self.meas, self.model, self.space, self.loss = meas, model, space, loss
        self._residual_fns = {}
        self.eval = evaluator or Evaluator(model, meas.wi, meas.wo, meas.n_channels, use_fast)
        self.use = meas.use
        cos_i = np.broadcast_to(np.clip(meas.wi[:, 2:3], 0.0, 1.0), meas.brdf.shape)
        self.weight = _residual_weight(loss, meas, cos_i) * _loss.value_weight(meas)
        self.linear = []
        self.linear = _linear_groups(self) if linear is None else linear
        self.varpro = bool(self.linear) and loss in ("chi2",) + _loss.WEIGHTED_L2
        if (evaluator is None and use_fast is not False and not self.eval.fast and not self.varpro
                and loss in NORMAL_LOSSES):
            # the problem's shape decides (see FAST_MIN_POINTS): steps from the compiled
            # normal equations pay at any number of points
            compiled = Evaluator(model, meas.wi, meas.wo, meas.n_channels, use_fast=True)
            if compiled.fast:
                compiled.n_evals = self.eval.n_evals
                self.eval = compiled
        lin_idx = sorted(i for g in self.linear for i in g["index"]) if self.varpro else []
        self.nl_idx = np.array([i for i in range(space.size) if i not in lin_idx], dtype=int)
        self._lin_index = np.array(lin_idx, dtype=int)
        self._last = (None, None)
        self._normal_data = None
        self._normal_last = None
        self._normal_index = None
        self._fisher_last = None
        self._f_last = None

    @property
    def n_evals(self):
        return self.eval.n_evals

    # -- plain residuals
    def f_x(self, x, reuse=False):
        """f_r at x; with ``reuse``, the compiled Jacobian's f_r where the last one was taken
        at this x (:meth:`residual_jacobian_x`), without another evaluation."""
        if reuse and self._f_last is not None and np.array_equal(self._f_last[0], x):
            return self._f_last[1]
        return self.eval(self.space.to_params(x))

    def residuals_x(self, x, loss=None):
        fr = self.f_x(x)
        loss = loss or self.loss
        if loss not in self._residual_fns:  # the data's parts once per fit (bit for bit _loss.residuals)
            self._residual_fns[loss] = _loss.residual_function(loss, self.meas)
        r = self._residual_fns[loss](fr)
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
    def residual_jacobian_x(self, x, cols, loss=None, scale=None):
        """Residuals at x and their exact derivatives with respect to x[cols] (natural units;
        column k times ``scale[k]`` where given: the unit box's dx/du), shape (M, len(cols)),
        from the compiled kernel's Jacobian; None on the numpy path or where the derivatives
        are not finite (the callers then difference). A per-channel entry's column is
        nonzero on its channel's rows only: those alone are computed, and each column is
        built in a row of its own (contiguous), the products the same as a full column's."""
        loss = loss or self.loss
        out = self.eval.jacobian(self.space.to_params(x))
        if out is None:
            return None
        f, J = out
        self._f_last = (np.array(x, dtype=np.float64), f)
        meas, use = self.meas, self.meas.use
        r = _loss.residuals(loss, f, meas)
        drdf = np.broadcast_to(_loss.residual_derivative(loss, f, meas), f.shape)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(drdf[use]))):
            return None     # a full column times a non-finite d r / d f_r is not finite either
        rows, chans = np.nonzero(use)           # the order of r's values
        own = {}
        DT = np.zeros((len(cols), r.size))
        for k, j in enumerate(cols):
            e = self.space.entries[j]
            if e.channel < 0 or self.model.structure.coupling(e.param) is not None:
                at, v = slice(None), (fast.jacobian_column(self.model, J, e.param, e.channel) * drdf)[use]
            else:
                if e.channel not in own:
                    at = np.flatnonzero(chans == e.channel)
                    own[e.channel] = (at, rows[at], drdf[rows[at], e.channel])
                at, n, d = own[e.channel]
                v = np.asarray(J[e.param])[n, e.channel] * d
            if not np.all(np.isfinite(v)):
                return None
            DT[k, at] = v if scale is None else v * scale[k]
        return r, np.ascontiguousarray(DT.T)

    def lm_jacobian_u(self, u, _r=None):
        """Exact Jacobian of :meth:`lm_residuals_u` at u (None: difference instead); the
        residuals argument of ``levenberg_marquardt``'s ``jac(u, r)`` is not needed."""
        x = self.space.from_unit(u)
        out = self.residual_jacobian_x(x, range(self.space.size), scale=self.space.dx_du(x))
        if out is None:
            return None
        r, D = out
        if self.loss == "robust":  # rho(r) = r sqrt(2 / (s + 1)), s = sqrt(1 + r^2)
            s = np.sqrt(1.0 + r * r)
            D = D * (np.sqrt(0.5 * (s + 1.0)) / s)[:, None]  # d rho / dr
        return D

    @property
    def normal_available(self):
        """Whether :meth:`lm_normal_u` and :meth:`lm_cost_u` use the compiled kernel's sums."""
        return self.loss in NORMAL_LOSSES and self.eval.fast and self.model.structure.derivatives

    def lm_normal_u(self, u, _r=None):
        """(J^T r, J^T J) of :meth:`lm_residuals_u` at u in the unit box, reduced inside the
        compiled kernel (:meth:`Evaluator.normal`): the Levenberg-Marquardt step without an
        N x P Jacobian, in memory independent of N (a 1e6-point fit). For the losses whose
        residual is affine in f_r without a transform (chi2, cosine: r = weight (f - y))
        and the log loss (its transform in the kernel); None elsewhere, on the numpy path,
        for a kernel of values only or where a sum is not finite (the caller then asks
        :meth:`lm_jacobian_u`). Where :meth:`lm_cost_u` already reduced them at this u
        (:data:`TRIAL_NORMAL_MAX`), no kernel runs."""
        if not self.normal_available:
            return None
        return self._normal_u(u)[1]

    def _normal_u(self, u):
        """(cost, (g, A) or None) at u from one compiled kernel, the last one kept."""
        key = np.asarray(u, dtype=np.float64).tobytes()
        if self._normal_last is not None and self._normal_last[0] == key:
            return self._normal_last[1]
        x = self.space.from_unit(u)
        cost, g, A, entries = self.eval.normal(self.space.to_params(x), *self.normal_data(), log=self.loss == "log")
        if self._normal_index is None or self._normal_index[0] != entries:
            where = {e: i for i, e in enumerate(entries)}
            try:
                idx = np.array([where[(e.param, e.channel)] for e in self.space.entries])
                self._normal_index = (entries, idx, np.ix_(idx, idx))
            except KeyError:  # a space the kernel's entries do not span
                self._normal_index = (entries, None, None)
        _, idx, square = self._normal_index
        gA = fisher = None
        if idx is not None:
            sc = self.space.dx_du(x)
            fisher = A[square]
            g, A = g[idx] * sc, fisher * np.outer(sc, sc)
            if np.all(np.isfinite(g)) and np.all(np.isfinite(A)):
                gA = (g, A)
        self._normal_last = (key, (cost, gA))
        self._fisher_last = (np.array(x, dtype=np.float64), cost, fisher)
        return cost, gA

    def fisher_chi2(self, x):
        """(chi^2, J^T J) at x in natural units from the compiled normal equations (the
        Fisher information of the chi2 loss, without an N x P Jacobian), or None where they
        do not serve (another loss, the numpy path, a sum not finite). The last step's
        equations are reused where they were taken at this x (a converged fit: no kernel)."""
        if self.loss != "chi2" or not self.normal_available:
            return None
        last = self._fisher_last
        if last is None or not np.array_equal(last[0], x):
            self._normal_u(self.space.to_unit(x))
            last = self._fisher_last
            if not np.array_equal(last[0], x):  # x did not survive the unit box's round trip
                cost, _, A, entries = self.eval.normal(self.space.to_params(x), *self.normal_data())
                idx = self._normal_index[1]
                last = (x, cost, None if idx is None else A[np.ix_(idx, idx)])
        _, cost, fisher = last
        if fisher is None or not (np.isfinite(cost) and np.all(np.isfinite(fisher))):
            return None
        return float(cost), fisher

    def normal_data(self):
        """(y, W): the data and the squared residual weights, 0 where a value is not used;
        for the log loss the data's log values ln(1 + f cos_i) and the squared solid-angle
        weights (:func:`gonio.fitting.likelihood.loss.residuals`)."""
        if self._normal_data is None:
            meas, use = self.meas, self.meas.use
            if self.loss == "log":
                cos_i = np.clip(meas.wi[:, 2:3], 0.0, 1.0)
                y = np.log1p(np.maximum(meas.brdf * cos_i, -0.999))
                w = _loss.value_weight(meas)
            else:
                y, w = meas.brdf, self.weight
            self._normal_data = (np.where(use, y, 0.0), np.where(use, np.broadcast_to(w, use.shape) ** 2, 0.0))
        return self._normal_data

    def lm_cost_u(self, u):
        """sum of squares of :meth:`lm_residuals_u` at u from one compiled kernel (no residual
        vector), for the losses :meth:`lm_normal_u` serves; FloatingPointError where f_r is
        not finite, as :meth:`residuals_x`."""
        x = self.space.from_unit(u)
        if self.normal_available and self.meas.n_points <= TRIAL_NORMAL_MAX:
            cost = self._normal_u(u)[0]  # the next step's normal equations come with it
        else:
            cost = self.eval.sse(self.space.to_params(x), *self.normal_data(), log=self.loss == "log")
        if cost is None:  # numpy path: the residual vector
            r = self.lm_residuals_u(u)
            return float(r @ r)
        if not np.isfinite(cost):
            raise FloatingPointError(f"model {self.model.name} returned non-finite f_r at "
                                     f"{dict(zip(self.space.names, np.round(x, 6)))}")
        return cost

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
        exact = self.residual_jacobian_x(x, self.nl_idx, scale=self.space.dx_du(x)[self.nl_idx])
        if exact is not None:
            J = exact[1]
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
        # an affine column of channel c is zero off c's residuals: the span is block-diagonal,
        # so each channel's rows are projected off its own columns (the same projection as one
        # QR of all columns, on a third of the rows and columns)
        rows, chans = np.nonzero(self.use)          # the order of r's values
        J = np.array(J, dtype=np.float64)
        for c in range(self.use.shape[1]):
            own = [B[:, c] for g, B in zip(self.linear, cols)
                   if self.space.lower[g["index"][c]] < x[g["index"][c]] < self.space.upper[g["index"][c]]]
            if not own:
                continue
            at = np.flatnonzero(chans == c)
            Q, _ = np.linalg.qr(np.stack(own, axis=1)[rows[at]] * self.weight[rows[at], c][:, None])
            J[at] -= Q @ (Q.T @ J[at])
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


Problem = _Problem


def _linear_groups(problem, probe=False):
    """Per-channel parameters in which f_r is affine, jointly, channel by channel.

    Declared by the model (``model.affine_colours()``, names) where it can say, else tested
    numerically at two interior points: f(a) for three values of each group must lie on a line
    for every channel separately, and a random joint setting of all accepted groups must equal
    the sum of their effects (``probe=True`` always tests). Returns [{"param", "index" (per
    channel), "v0", "v1"}], in the space's order.
    """
    space = problem.space
    groups = {}
    for i, e in enumerate(space.entries):
        if e.channel >= 0:
            groups.setdefault(e.param, []).append(i)
    groups = {k: v for k, v in groups.items() if len(v) == space.n_channels}
    if not groups:
        return []
    declared = getattr(problem.model, "affine_colours", None)
    if declared is not None and not probe:      # the probes cost O(groups^2) evaluations (21 groups: ~500)
        names = set(declared())
        out = []
        for name, index in groups.items():
            if name in names:
                lo, hi = space.lower[index[0]], space.upper[index[0]]
                out.append({"param": name, "index": list(index), "v0": float(lo + 0.2 * (hi - lo)),
                            "v1": float(lo + 0.8 * (hi - lo))})
        return out
    test_u = (np.full(space.size, 0.37), np.full(space.size, 0.61))
    model = problem.model
    where = (model.name, tuple(sorted((k, str(v)) for k, v in model.options.items())), space.n_channels,
             tuple(space.names), tuple(sorted((k, str(v)) for k, v in space.fixed.items())))
    accepted = []
    for name, index in groups.items():
        lo, hi = space.lower[index[0]], space.upper[index[0]]
        v0, v1 = lo + 0.2 * (hi - lo), lo + 0.8 * (hi - lo)
        g = {"param": name, "index": list(index), "v0": float(v0), "v1": float(v1)}
        key = where + (tuple(a["param"] for a in accepted), name)
        if key in _NOT_AFFINE:
            continue
        verdicts = [_affine_ok(problem, u, accepted + [g]) for u in test_u]
        if all(v is True for v in verdicts):
            accepted.append(g)
        elif "clearly not" in verdicts:
            _NOT_AFFINE.add(key)
    return accepted


#: (model configuration, parameter space, groups accepted before, group) found clearly not
#: affine once: f_r is then not affine in that group as a function, whatever the directions,
#: so later fits skip its probe (roughconductor's eta and k: 8 of a 1000-point fit's ~30
#: evaluations). Only a clear failure is remembered (a deviation above 1e-6 of the scale,
#: a thousand times the test's tolerance); an affine verdict is data-dependent (data where
#: f_r = 0 pass any test) and is probed every time.
_NOT_AFFINE: set = set()


def _affine_ok(problem, u, gs):
    """True when f_r is affine in the groups ``gs`` jointly at unit point ``u`` (to 1e-9 of
    its scale); False otherwise, or the string "clearly not" where it deviates by more than
    1e-6 of the scale (a property of the function, not of these data)."""
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
    if not np.all(np.isfinite(f)):
        return False
    scale = max(float(np.max(np.abs(f))), 1e-300)
    dev = float(np.max(np.abs(f - pred)))
    if dev <= 1e-9 * scale:
        return True
    return "clearly not" if dev > 1e-6 * scale and np.all(np.isfinite(pred)) else False
