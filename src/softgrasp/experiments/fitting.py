"""The fitting engine of the calibrations: bounded non-linear least squares over named parameters
(some in log space), with uncertainties, identifiability and correlations, and the result types.

Uncertainties are one standard deviation from the Gauss-Newton covariance s^2 (J^T J)^-1 at the
optimum (s^2 the residual variance). A parameter the data do not depend on (its column of J is
~0) is reported as *not identified* and kept at its starting value, never silently invented; one
whose standard deviation exceeds ``UNIDENTIFIED`` times its value is flagged *poorly determined*.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import PchipInterpolator
from scipy.optimize import least_squares

from softgrasp.errors import NotConverged

__all__ = [
    "UNIDENTIFIED",
    "CalibrationFit",
    "FitSolution",
    "FitSpec",
    "Parameter",
    "correlation",
    "curve_at",
    "solve_fit",
]

#: Relative standard deviation above which a fitted parameter counts as not identified.
UNIDENTIFIED = 1.0


@dataclass(frozen=True)
class Parameter:
    """One model parameter of a fit.

    Attributes
    ----------
    name: its name (``E_Pa``, ``nu``, ``a2``, ``a3``, ``stiffness_prefactor``, ``exponent``,
        ``gamma_N_s_m2``).
    value: fitted (or kept) value, SI units.
    stderr: one standard deviation (nan when not fitted).
    status: ``fitted``; ``poorly determined`` (fitted, but its standard deviation exceeds its
        value); ``not identified`` (the data do not depend on it: kept at its start); or
        ``fixed`` (not asked for).
    start: starting value.  lower, upper: bounds of the fit.
    """

    name: str
    value: float
    stderr: float
    status: str
    start: float
    lower: float
    upper: float

    def describe(self) -> dict[str, object]:
        """JSON-ready description."""
        return {
            "value": self.value,
            "stderr": None if math.isnan(self.stderr) else self.stderr,
            "status": self.status,
            "start": self.start,
            "bounds": [self.lower, self.upper],
        }


@dataclass(frozen=True)
class CalibrationFit:
    """Result of a fit: parameters, the measured and fitted curves, and the residual.

    Attributes
    ----------
    kind: ``compression`` or ``indentation``.
    parameters: by name (:class:`Parameter`).
    x: the measured abscissa [m] (displacement or penetration), (P,).
    measured, fitted: measured and simulated force at ``x`` [N], (P,).
    lateral_measured, lateral_fitted: lateral strains when the data have them, else None.
    residual_rms_N: root-mean-square force residual [N].
    mean_abs_error_N: mean absolute force residual [N] (the paper's figure of merit in Fig. 11).
    relative_rms: residual_rms_N over the largest measured force.
    simulations: number of simulated tests the fit ran.
    wall_time_s: seconds.
    notes: remarks for the user (unidentified parameters and why).
    converged: whether the least-squares solve converged.
    correlation: correlation coefficients between the fitted parameters (E and the stiffness
        prefactor in log space; b = a3 - a2^2 / 3 for the law), by name.
    """

    kind: str
    parameters: dict[str, Parameter]
    x: NDArray[np.float64]
    measured: NDArray[np.float64]
    fitted: NDArray[np.float64]
    lateral_measured: NDArray[np.float64] | None
    lateral_fitted: NDArray[np.float64] | None
    residual_rms_N: float
    mean_abs_error_N: float
    relative_rms: float
    simulations: int
    wall_time_s: float
    notes: tuple[str, ...] = field(default=())
    converged: bool = True
    correlation: dict[str, dict[str, float]] = field(default_factory=dict)

    def value(self, name: str) -> float:
        """The fitted or kept value of parameter ``name``."""
        return self.parameters[name].value


@dataclass(frozen=True)
class FitSpec:
    """A parameter of the fit vector: name, start, bounds, and whether it is fitted in log space."""

    name: str
    start: float
    lower: float
    upper: float
    log: bool = False

    def to_vec(self, v: float) -> float:
        return math.log(v) if self.log else v

    def from_vec(self, u: float) -> float:
        return math.exp(u) if self.log else u


def correlation(cov: dict[tuple[str, str], float]) -> dict[str, dict[str, float]]:
    """Correlation coefficients from a covariance by name pairs (parameters with a finite variance)."""
    names = [a for (a, b) in cov if a == b and math.isfinite(cov[(a, a)]) and cov[(a, a)] > 0]
    return {a: {b: cov[(a, b)] / math.sqrt(cov[(a, a)] * cov[(b, b)]) for b in names} for a in names}


@dataclass(frozen=True)
class FitSolution:
    """What the fitting engine found (see :func:`solve_fit`)."""

    params: dict[str, Parameter]
    residual: NDArray[np.float64]
    evaluations: int
    notes: list[str]
    cov: dict[tuple[str, str], float]
    converged: bool


def solve_fit(
    residual: Callable[[dict[str, float]], NDArray[np.float64]],
    specs: Sequence[FitSpec],
    fixed: dict[str, float],
    progress: Callable[[int], None] | None,
    *,
    blocks: Sequence[int] | None = None,
    quiet: Sequence[str] = (),
    max_evaluations: int = 60,
) -> FitSolution:
    """Minimise |residual|^2 over ``specs`` (the rest in ``fixed``).

    ``blocks``: sizes of consecutive residual blocks of different quantities (force, lateral
    strain): each gets its own variance, estimated from its own residuals, and the covariance is
    that of the weighted problem. ``quiet``: internal parameters whose status needs no note (they
    are reported through a derived one). A solve that ran out of evaluations, or a parameter that
    ends on a bound, is said so in the notes (and ``converged`` is False for the former).
    """
    count = [0]

    def fun(u: NDArray[np.float64]) -> NDArray[np.float64]:
        vals = dict(fixed)
        vals.update({s.name: s.from_vec(float(ui)) for s, ui in zip(specs, u, strict=True)})
        count[0] += 1
        if progress is not None:
            progress(count[0])
        return residual(vals)

    u0 = np.array([s.to_vec(s.start) for s in specs])
    lo = np.array([s.to_vec(s.lower) for s in specs])
    hi = np.array([s.to_vec(s.upper) for s in specs])
    r0 = fun(u0)
    if not np.isfinite(r0).all():
        raise NotConverged(
            "the simulated test failed at the starting parameters; check the specimen mesh and the "
            "starting material (--material, --nu)"
        )
    try:
        sol = least_squares(
            fun, u0, bounds=(lo, hi), method="trf", diff_step=1e-3, x_scale="jac", max_nfev=max_evaluations
        )
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise NotConverged(
            f"the fit failed ({exc}); the simulated test fails near the start: try another --mesh-size "
            "or a starting material closer to the data (--material)"
        ) from None
    r = sol.fun
    notes: list[str] = []
    converged = bool(sol.status > 0)
    if not converged:
        notes.append(
            f"the fit stopped after {max_evaluations} simulated tests without converging; its values "
            "and deviations are not reliable (more or better-spread data would help)"
        )
    # The covariance from a central-difference Jacobian at the optimum (the solver's own is a
    # one-sided estimate from its last iteration).
    J = np.empty((r.size, len(specs)))
    for k in range(len(specs)):
        h = 1e-3 * max(abs(float(sol.x[k])), 1.0)
        hi_k = min(float(sol.x[k]) + h, hi[k])
        lo_k = max(float(sol.x[k]) - h, lo[k])
        up, dn = sol.x.copy(), sol.x.copy()
        up[k], dn[k] = hi_k, lo_k
        J[:, k] = (fun(up) - fun(dn)) / (hi_k - lo_k)
    if not np.isfinite(J).all():
        J = sol.jac
    m, p = J.shape
    col = np.linalg.norm(J, axis=0)
    scale = max(float(col.max()), 1e-300)
    live = col > 1e-8 * scale
    # Parameters on a bound count as fixed there: the covariance is that of the free ones.
    free = live & (sol.active_mask == 0)
    n_free = int(free.sum())
    # Per-block variances: each block's residual variance (its share of the degrees of freedom).
    sizes = list(blocks) if blocks else [m]
    w = np.empty(m)
    at = 0
    for size in sizes:
        rb = r[at : at + size]
        dof_b = max(size - n_free * size / m, 1.0)
        w[at : at + size] = 1.0 / max(float(rb @ rb) / dof_b, 1e-300)
        at += size
    Jw = J * np.sqrt(w)[:, None]
    cov = np.full((p, p), np.nan)
    if free.any():
        idx = np.flatnonzero(free)
        cov[np.ix_(idx, idx)] = np.linalg.pinv(Jw[:, idx].T @ Jw[:, idx])
    params: dict[str, Parameter] = {}
    for k, s in enumerate(specs):
        val = s.from_vec(float(sol.x[k]))
        if not live[k]:
            if s.name not in quiet:
                notes.append(f"{s.name} not identified (the data do not depend on it); kept at {s.start:.6g}")
            params[s.name] = Parameter(s.name, s.start, math.nan, "not identified", s.start, s.lower, s.upper)
            continue
        sd_u = math.sqrt(cov[k, k]) if math.isfinite(cov[k, k]) and cov[k, k] >= 0 else math.nan
        sd = abs(val) * sd_u if s.log else sd_u  # first order: d exp(u) = exp(u) du
        status = "fitted"
        if sol.active_mask[k] != 0:
            status = "at bound"
            if s.name not in quiet:
                notes.append(
                    f"{s.name} ended on its bound ({val:.4g}, bounds {s.lower:.4g}..{s.upper:.4g}); the "
                    "data ask for a value outside what the fit allows"
                )
        elif not (math.isfinite(sd) and sd <= UNIDENTIFIED * abs(val)):
            status = "poorly determined"
            if s.name not in quiet:
                notes.append(
                    f"{s.name} poorly determined: {val:.4g} +- {sd:.3g}; the data hardly constrain it "
                    "(more points, a larger range or lateral measurements would)"
                )
        params[s.name] = Parameter(s.name, val, sd, status, s.start, s.lower, s.upper)
    for name, v in fixed.items():
        params[name] = Parameter(name, v, math.nan, "fixed", v, v, v)
    names = [s.name for s in specs]
    covd = {(a, b): float(cov[i, j]) for i, a in enumerate(names) for j, b in enumerate(names)}
    return FitSolution(params, r, count[0], notes, covd, converged)


def curve_at(x: NDArray[np.float64], xs: NDArray[np.float64], ys: NDArray[np.float64]) -> NDArray[np.float64]:
    """A simulated curve (xs increasing) at the measured abscissae x: monotone cubic (PCHIP)
    interpolation, whose error between the simulated increments is far below a straight chord's
    on these convex curves (a chord would bias the fitted non-linearity)."""
    return PchipInterpolator(xs, ys, extrapolate=True)(np.clip(x, xs[0], xs[-1]))
