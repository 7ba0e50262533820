"""Fitting [parameters] to measurements by least squares with exact Jacobians.

For parameters θ (named [parameters]: lengths, damping, masses, initial angles…) minimize

    χ²(θ) = Σ_ij w_ij² (d_ij − y_j(t_i; θ))²,

d the measured values (constrained.fitting.measurements; missing ones left out), y the
observables of the run (constrained.fitting.observables) and w = 1/σ (given per value, or one
σ for all; without any σ, w = 1). SciPy's ``least_squares`` (trust-region reflective, bounds
allowed) takes the residuals and their Jacobian ∂y/∂θ from constrained.fitting.sensitivities
— CasADi AD through the run's replayed steps, never finite differences.

Uncertainties from the Jacobian W J at the optimum (Gauss–Newton): with σ given,
``cov = (Jᵀ W² J)⁻¹`` (the χ² then tells how well the σ fit: reduced χ² ≈ 1); without,
``cov = s² (Jᵀ J)⁻¹``, ``s² = χ² / (m − n)``, the noise estimated from the residuals.
Directions of θ the data do not determine (singular values of W J below 1e-10 of the largest)
are reported, not inverted.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ...errors import ConstrainedError, InputError, LinearRangeWarning
from ...model.structure import Model, assemble
from ...run.simulate import refuse_negative_damping
from .measurements import Measurements
from .observables import observables as observable_function
from .sensitivities import GROWN, MAX_STEPS, sensitivities

__all__ = ["FitResult", "fit"]

#: Singular values of the weighted Jacobian below this fraction of the largest: not identifiable.
IDENTIFIABLE_RTOL = 1e-10
#: A fit SciPy calls converged is not when a step along a free parameter would still remove more
#: than this fraction of the residual's norm at first order (|J_jᵀ r| / (|J_j| |r|)): at a least-
#: squares minimum r is orthogonal to every column (1e-7 on real fits); a chaotic double pendulum
#: over 30 s stopped at its start with 0.15 (its trust region had shrunk to 1e-11).
STALLED = 1e-3


@dataclass(frozen=True)
class FitResult:
    """A least-squares fit. ``names`` (n,) the fitted parameters, ``estimates``,
    ``standard_errors``, ``start`` (n,), ``covariance`` and ``correlation`` (n, n);
    ``t``, ``outputs``, ``data``, ``fitted``, ``residuals`` = data − fitted (T, k, NaN where
    missing); ``chi2``, ``dof`` = m − n, ``reduced_chi2``; ``sigma_given``; ``success``,
    ``message``, ``nfev``, ``njev``; ``unidentified``: parameter combinations the data do not
    determine (each a dict name -> weight)."""

    names: tuple[str, ...]
    estimates: np.ndarray
    standard_errors: np.ndarray
    start: np.ndarray
    covariance: np.ndarray
    correlation: np.ndarray
    t: np.ndarray
    outputs: tuple[str, ...]
    data: np.ndarray
    fitted: np.ndarray
    residuals: np.ndarray
    chi2: float
    dof: int
    sigma_given: bool
    success: bool
    message: str
    nfev: int
    njev: int
    unidentified: list = field(default_factory=list)
    formulas: tuple[str, ...] = ()

    @property
    def values(self) -> dict[str, float]:
        """name -> estimate (``simulate(..., parameters=result.values)`` runs the fitted model)."""
        return dict(zip(self.names, self.estimates.tolist(), strict=True))

    @property
    def reduced_chi2(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else math.nan

    @property
    def rms(self) -> np.ndarray:
        """(k,) root-mean-square residual of each output."""
        r = self.residuals
        return np.sqrt(np.nanmean(r * r, axis=0))

    def table(self) -> str:
        lines = [f"{'parameter':<14} {'estimate':>14} {'std. error':>12} {'start':>12}"]
        rows = zip(self.names, self.estimates, self.standard_errors, self.start, strict=True)
        for name, est, se, s0 in rows:
            lines.append(f"{name:<14} {est:>14.8g} {se:>12.3g} {s0:>12.6g}")
        fit = "σ given: χ²" if self.sigma_given else "no σ given: residual sum of squares"
        lines.append(f"{fit} = {self.chi2:.6g} over {self.dof} degrees of freedom "
                     f"(reduced {self.reduced_chi2:.4g}); "
                     f"{'converged' if self.success else 'NOT converged'}: {self.message} "
                     f"({self.nfev} runs, {self.njev} Jacobians)")
        if not self.sigma_given and self.dof <= 0:
            values = self.dof + len(self.names)
            lines.append(f"  standard errors unknown: {values} measured value{'s' * (values != 1)} for "
                         f"{len(self.names)} fitted parameter{'s' * (len(self.names) != 1)} leave no degree "
                         "of freedom to estimate σ from the residuals; give --sigma (or sigma_NAME "
                         "columns), or more measurements")
        for name, rms in zip(self.outputs, self.rms, strict=True):
            lines.append(f"  rms residual of {name}: {rms:.4g}")
        off = np.abs(self.correlation - np.eye(len(self.names)))
        off[~np.isfinite(off)] = -1.0  # (an undetermined parameter has no correlation)
        undetermined = ~np.isfinite(self.standard_errors)  # (its correlations are 0 by division by ∞)
        off[undetermined, :] = off[:, undetermined] = -1.0
        np.fill_diagonal(off, -1.0)  # (nor is a parameter's with itself a correlation to report)
        if len(self.names) > 1 and np.max(off) >= 0:
            k = np.unravel_index(np.argmax(off), off.shape)
            lines.append(f"  largest correlation: {self.names[k[0]]}–{self.names[k[1]]} "
                         f"{self.correlation[k]:+.3f}")
        for combo in self.unidentified:
            text = " + ".join(f"{w + 0.0:.3g}·{n}" for n, w in combo.items())  # (+ 0.0: no "-0")
            lines.append(f"  NOT determined by these data: {text} (held at its start; its standard error "
                         "is infinite: fix one of these parameters, or write the model with the combination "
                         "the data see)")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"parameters": [{"name": n, "estimate": float(e), "standard_error": _finite(s),
                                "start": float(s0)}
                               for n, e, s, s0 in zip(self.names, self.estimates, self.standard_errors,
                                                      self.start, strict=True)],
                "covariance": [[_finite(c) for c in row] for row in self.covariance],
                "correlation": [[_finite(c) for c in row] for row in self.correlation],
                "chi2": self.chi2, "dof": self.dof, "reduced_chi2": _finite(self.reduced_chi2),
                "sigma_given": self.sigma_given, "success": self.success, "message": self.message,
                "nfev": self.nfev, "njev": self.njev, "outputs": list(self.outputs),
                "formulas": list(self.formulas), "rms_residuals": [_finite(r) for r in self.rms],
                "unidentified": self.unidentified}


def unseen_directions(jac: np.ndarray) -> tuple[np.ndarray, float]:
    """(V (n, k), ρ): orthonormal directions of parameter space along which the weighted
    residuals do not change at the start (singular values of ``jac`` within IDENTIFIABLE_RTOL
    of the largest: two masses that enter only as their ratio, m₂/m₁, change nothing measured
    along (m₁, m₂)), and ρ, the largest singular value. Along such a direction the
    Gauss–Newton step is round-off divided by round-off: the fit wandered there (to m₁ = −1.2,
    m₂ = −1.4 kg, where the run fails). The fit holds them at the start instead: it minimizes
    ``|r(θ)|² + ρ² |Vᵀ(θ − θ₀)|²`` with the Jacobian ``[J (I − V Vᵀ); ρ Vᵀ]`` (exactly the
    fit within the hyperplane Vᵀ(θ − θ₀) = 0, which every such line crosses), and reports them
    as not determined."""
    _, sv, vt = np.linalg.svd(np.asarray(jac, float), full_matrices=False)
    if not sv.size or not sv[0] > 0:
        return np.eye(jac.shape[1]), 1.0
    hidden = vt[sv <= IDENTIFIABLE_RTOL * sv[0]]
    if len(sv) < jac.shape[1]:  # fewer measured values than parameters: refused before this
        hidden = np.vstack([hidden, vt[len(sv):]])
    return hidden.T, float(sv[0])


def _finite(value) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def _bounds(names, bounds: Mapping | None) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.full(len(names), -np.inf), np.full(len(names), np.inf)
    for key, pair in (bounds or {}).items():
        if key not in names:
            raise InputError(f"bounds name '{key}', which is not fitted ({', '.join(names)})", where="bounds")
        try:
            a, b = (float(v) for v in pair)
        except (TypeError, ValueError):
            raise InputError(f"the bounds of '{key}' must be two numbers (low, high), got {pair!r}",
                             where="bounds") from None
        if not a < b:
            raise InputError(f"the bounds of '{key}' must have low < high, got ({a:g}, {b:g})",
                             where="bounds")
        lo[names.index(key)], hi[names.index(key)] = a, b
    return lo, hi


def _weights(data: Measurements, sigma: float | None) -> tuple[np.ndarray, bool]:
    measured = np.isfinite(data.values)
    if sigma is not None:
        number = isinstance(sigma, int | float) and not isinstance(sigma, bool)
        if not (number and math.isfinite(sigma) and sigma > 0):
            raise InputError(f"sigma must be a positive number, got {sigma!r}", where="sigma")
        s = np.full(data.values.shape, float(sigma)) if data.sigma is None else \
            np.where(np.isfinite(data.sigma), data.sigma, float(sigma))
        return np.where(measured, 1.0 / s, 0.0), True
    if data.sigma is None:
        return measured.astype(float), False
    given = np.isfinite(data.sigma) & measured
    if np.any(measured & ~given):
        raise InputError("some measured values have a sigma and others not: give sigma_NAME for every column "
                         "(or a value for every row), or one sigma for the rest", where=data.source)
    return np.where(measured, 1.0 / np.where(given, data.sigma, 1.0), 0.0), True


def fit(system, data: Measurements, parameters: Sequence[str], *, observables: Mapping | None = None,
        start: Mapping | None = None, bounds: Mapping | None = None, sigma: float | None = None,
        t_start: float = 0.0, rtol: float = 1e-10, atol: float = 1e-12, base: str = "DOP853",
        max_nfev: int = 100, tolerance: float = 1e-10, model: Model | None = None,
        max_steps: int = MAX_STEPS) -> FitResult:
    """Fit the [parameters] ``parameters`` of ``system`` to ``data`` (see the module).

    ``observables``: column name -> formula for columns that are not formulas themselves;
    ``start``: initial values (default: the system's); ``bounds``: name -> (low, high);
    ``sigma``: one standard deviation for every value without its own; ``rtol``/``atol``/
    ``base``: the runs' dopri settings; ``max_nfev``: runs allowed; ``tolerance``: SciPy's
    ftol, xtol and gtol."""
    from scipy.optimize import least_squares

    if not isinstance(data, Measurements):
        raise InputError("data must be Measurements (read_measurements reads a CSV file)", where="data")
    if not hasattr(system, "particles"):
        raise InputError(f"expected a System, got {type(system).__name__} (for a Scene, pass scene.system)",
                         where="system")
    names = [parameters] if isinstance(parameters, str) else list(parameters)
    if not names:
        raise InputError("name at least one [parameter] to fit", where="parameters")
    model = model or assemble(system)
    unknown = [n for n in names if n not in model.parameter_names]
    if unknown:
        known = ", ".join(model.parameter_names) or "none"
        raise InputError(f"cannot fit {', '.join(unknown)}: not among the scene's [parameters] ({known}); "
                         "write the quantity as a [parameters] entry and use its name", where="parameters")
    if len(set(names)) != len(names):
        raise InputError("a parameter is named twice", where="parameters")
    extra = dict(observables or {})
    for key in extra:
        if key not in data.names:
            raise InputError(f"observable '{key}' names no column of the data ({', '.join(data.names)})",
                             where="observables")
    formulas = {n: extra.get(n, n) for n in data.names}
    observable_function(model, formulas)  # a formula that does not parse is refused here, named
    if data.t[0] < t_start:
        raise InputError(f"the first measurement (t = {data.t[0]:g} s) is before the start t = {t_start:g} s",
                         where=data.source)
    weights, sigma_given = _weights(data, sigma)
    measured = weights > 0
    m, n = int(measured.sum()), len(names)
    if m < n:
        raise InputError(f"{m} measured value(s) cannot determine {n} parameters", where=data.source)
    for key in start or {}:
        if key not in names:
            raise InputError(f"a start value for '{key}', which is not fitted ({', '.join(names)})",
                             where="start")
    values0 = {**model.parameters, **dict(start or {})}
    theta0 = np.array([float(values0[k]) for k in names])
    lo, hi = _bounds(names, bounds)
    if np.any(theta0 <= lo) or np.any(theta0 >= hi):
        k = int(np.argmax((theta0 <= lo) | (theta0 >= hi)))
        raise InputError(f"the start value {names[k]} = {theta0[k]:g} is not inside its bounds "
                         f"({lo[k]:g}, {hi[k]:g})", where="start")
    target = np.where(measured, data.values, 0.0)
    cache: dict = {}

    def evaluate(theta):
        key = theta.tobytes()
        if key not in cache:
            cache.clear()
            try:
                with warnings.catch_warnings():  # (said once, for the fitted values: below)
                    warnings.simplefilter("ignore", LinearRangeWarning)
                    s = sensitivities(system, data.t, outputs=formulas, parameters=names, t_start=t_start,
                                      values=dict(zip(names, theta.tolist(), strict=True)), rtol=rtol,
                                      atol=atol, base=base, model=model, max_steps=max_steps)
            except ConstrainedError as exc:
                where = ", ".join(f"{k} = {v:.6g}" for k, v in zip(names, theta, strict=True))
                raise type(exc)(f"the fit reached {where}, where the run fails: {exc}; start nearer the "
                                "solution, or give bounds") from None
            residual = (weights * (s.values - target))[measured]
            jac = (weights[:, :, None] * s.d_parameters)[measured]
            cache[key] = (residual, jac, s.values, s.stats["relative_growth"])
        return cache[key]

    njev = [0]

    def jacobian(theta):
        njev[0] += 1
        return evaluate(theta)[1]

    hidden, rho = unseen_directions(evaluate(theta0)[1])
    if hidden.shape[1]:  # hold them at the start: the fit would wander along them (see below)
        def held_residual(theta):
            return np.concatenate([evaluate(theta)[0], rho * (hidden.T @ (theta - theta0))])

        def held_jacobian(theta):
            return np.vstack([jacobian(theta) @ (np.eye(n) - hidden @ hidden.T), rho * hidden.T])
    else:
        def held_residual(theta):
            return evaluate(theta)[0]

        held_jacobian = jacobian
    sol = least_squares(held_residual, theta0, jac=held_jacobian, bounds=(lo, hi), method="trf",
                        x_scale="jac", ftol=tolerance, xtol=tolerance, gtol=tolerance, max_nfev=max_nfev)
    residual, jac, fitted, growth = evaluate(sol.x)
    fitted_values = dict(zip(names, sol.x.tolist(), strict=True))
    try:  # (the iterations may pass through negative damping; the answer should not end there)
        refuse_negative_damping(model.with_parameters(fitted_values), system.with_parameters(fitted_values),
                                float(t_start), float(data.t[-1]))
    except InputError as exc:
        warnings.warn(f"the fitted values make the damping an energy source: {exc}; give the fit "
                      "bounds that keep the coefficient ≥ 0", stacklevel=2)
    grown = {k: g for k, g in growth.items() if g > GROWN}
    if grown:
        warnings.warn(LinearRangeWarning(
            "at the fitted values the sensitivities grew by orders of magnitude ("
            + ", ".join(f"{k}: {g:.2g}" for k, g in grown.items()) + "): the standard errors and "
            "correlations, which are first-order, hold only for changes far below the inverse of that; "
            "fit over a shorter span"), stacklevel=2)
    success, message = bool(sol.success), str(sol.message)
    reducible = _first_order_reducible(sol, np.linalg.norm((weights * target)[measured]))
    if success and reducible > STALLED:
        success = False
        message = (f"the steps stopped ({message}) with the residual still {reducible:.2g} of its size along "
                   "the parameters at first order: the trust region shrank because the runs do not follow "
                   "their linearization over any step the fit tried")
        message += ("; the sensitivities grew by " + ", ".join(f"{k}: {g:.2g}" for k, g in grown.items())
                    + " over the span (chaotic): fit over a shorter span, where they stay below 1e6, then "
                    "extend it from that fit" if grown
                    else "; start nearer the solution, or fit a shorter span")
    chi2 = float(residual @ residual)
    dof = m - n
    U, sv, Vt = np.linalg.svd(jac, full_matrices=False)
    ok = sv > IDENTIFIABLE_RTOL * sv[0] if sv.size and sv[0] > 0 else np.zeros(sv.shape, bool)
    scale = 1.0 if sigma_given else (chi2 / dof if dof > 0 else math.nan)
    cov = (Vt[ok].T / sv[ok] ** 2) @ Vt[ok] * scale
    unidentified = [dict(zip(names, np.round(v, 6).tolist(), strict=True)) for v in Vt[~ok]]
    for v in Vt[~ok]:  # an undetermined direction: infinite variance along it
        cov = np.where(np.outer(np.abs(v) > 1e-12, np.abs(v) > 1e-12), np.inf, cov)
    with np.errstate(invalid="ignore"):
        se = np.sqrt(np.diag(cov))
        corr = cov / np.outer(se, se)
    residuals = np.where(np.isfinite(data.values), data.values - fitted, np.nan)
    return FitResult(tuple(names), sol.x.copy(), se, theta0, cov, corr, data.t.copy(), data.names,
                     data.values.copy(), fitted, residuals,
                     chi2, dof, sigma_given, success, message, int(sol.nfev), njev[0],
                     unidentified, tuple(formulas[k] for k in data.names))


def _first_order_reducible(sol, data_size: float) -> float:
    """The largest |J_jᵀ r| / (|J_j| |r|) over the parameters not at a bound (with the rows that
    hold unseen directions), i.e. the fraction of the residual a step along one of them would remove
    at first order; 0 when the residual is at round-off of the data (its direction is then noise)."""
    r, J = np.asarray(sol.fun, float), np.asarray(sol.jac, float)
    size = float(np.linalg.norm(r))
    if size <= 1e-8 * data_size or not np.all(np.isfinite(J)):
        return 0.0
    columns = np.linalg.norm(J, axis=0)
    free = (np.asarray(sol.active_mask) == 0) & (columns > 0)
    return float(np.max(np.abs(J.T @ r)[free] / (columns[free] * size), initial=0.0))

