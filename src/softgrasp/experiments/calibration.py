"""Fitting the model to measurements (paper Sec. 4.2-4.3, Figs. 9 and 11).

*Compression* (:func:`fit_compression`): a measured force-displacement (or stress-strain) curve of
a specimen squeezed between plates is matched by softgrasp's own compression test
(:func:`softgrasp.experiments.compression.compression_test`) of a mesh of the specimen, by
bounded non-linear least squares over Young's modulus E, the polynomial law's a2 and a3
(:class:`softgrasp.model.material.Polynomial`) and, when the file has lateral strains, Poisson's ratio.

*Indentation* (:func:`fit_indentation`): a measured force-penetration curve of one fingertip
pressed into the object is matched by softgrasp's indentation test
(:func:`softgrasp.experiments.indentation.indentation_test`) over the contact law's stiffness
prefactor c (K = c Psi sqrt(R), Eq. 11), exponent n (Eq. 9) and damping gamma (Eq. 13). The test
is quasi-static: the damping force is added at the test speed, with delta_dot the rate of the
contact-law penetration delta (which grows slower than the fingertip's travel: the body's own
compliance is in series), a small offset of the loading curve, identifiable only when the data
resolve it.

Uncertainties are one standard deviation from the Gauss-Newton covariance s^2 (J^T J)^-1 at the
optimum (s^2 the residual variance). A parameter the data do not depend on (its column of J is
~0) is reported as *not identified* and kept at its starting value, never silently invented; one
whose standard deviation exceeds ``UNIDENTIFIED`` times its value is flagged *poorly determined*.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import PchipInterpolator
from scipy.optimize import least_squares

from softgrasp.physics.body import Body, build_body
from softgrasp.physics.fingertip.params import ContactParams
from softgrasp.physics.fingertip.laws import contact_damping
from softgrasp.errors import ConfigError, MaterialError, NotConverged, SoftgraspError
from softgrasp.experiments.compression import compression_test, outline_area
from softgrasp.experiments.indentation import indentation_test
from softgrasp.experiments.measured import MeasuredTable, read_table
from softgrasp.model.material import Material, Polynomial
from softgrasp.model.mesh.tetmesh import TetMesh

__all__ = [
    "Parameter",
    "CalibrationFit",
    "CompressionData",
    "IndentationData",
    "read_compression_data",
    "read_indentation_data",
    "fit_compression",
    "fit_indentation",
]

#: Relative standard deviation above which a fitted parameter counts as not identified.
UNIDENTIFIED = 1.0
#: Largest nominal strain a compression fit simulates.
MAX_STRAIN = 0.8
#: Bounds of the polynomial law's a2 in a fit, and of its excess b = a3 - a2^2 / 3 (> 0 keeps the
#: law increasing at every strain: its slope 1 + 2 a2 e + 3 a3 e^2 then has no real root).
A2_BOUNDS = (-4.0, 4.0)
B_BOUNDS = (1e-3, 20.0)

_DISPLACEMENT_UNITS = {"displacement_m": 1.0, "displacement_mm": 1e-3}
_STRESS_UNITS = {"stress_Pa": 1.0, "stress_kPa": 1e3, "stress_MPa": 1e6}
_PENETRATION_UNITS = {"penetration_m": 1.0, "penetration_mm": 1e-3}


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


# ---------------------------------------------------------------------- data
@dataclass(frozen=True)
class CompressionData:
    """A measured compression curve in SI units (loading, increasing displacement).

    Attributes
    ----------
    displacement_m: plate travel from first contact [m], (P,).
    force_N: plate force [N], (P,).
    lateral_strain: change of width over initial width (positive: widening), (P,), or None.
    height_m, area_m2: the specimen height and nominal area used to convert strain and stress.
    source: the file.
    """

    displacement_m: NDArray[np.float64]
    force_N: NDArray[np.float64]
    lateral_strain: NDArray[np.float64] | None
    height_m: float
    area_m2: float
    source: str


@dataclass(frozen=True)
class IndentationData:
    """A measured force-penetration curve in SI units (loading, increasing penetration).

    Attributes
    ----------
    penetration_m: fingertip travel from first contact [m], (P,).
    force_N: fingertip force [N], (P,).
    tangential_force_N: tangential force [N], (P,), or None.
    source: the file.
    """

    penetration_m: NDArray[np.float64]
    force_N: NDArray[np.float64]
    tangential_force_N: NDArray[np.float64] | None
    source: str


def _check_curve(table: MeasuredTable, x: NDArray, y: NDArray, xname: str, yname: str, min_rows: int) -> None:
    """A loading curve: enough rows, x >= 0 strictly increasing, y >= 0; errors name the line."""
    if len(x) < min_rows:
        raise ConfigError(
            f"measured data file {table.name!r} has {len(x)} data row(s); a fit needs at least {min_rows} "
            "(more rows than fitted parameters)"
        )
    for i in range(len(x)):
        if x[i] < 0:
            raise ConfigError(
                f"measured data file {table.name!r}, line {table.line_of(i)}: {xname} {x[i]:.6g} is "
                "negative; measure from first contact (0 at first contact)"
            )
        if y[i] < 0:
            raise ConfigError(
                f"measured data file {table.name!r}, line {table.line_of(i)}: {yname} {y[i]:.6g} is "
                "negative; give compressive forces as positive numbers"
            )
        if i > 0 and not x[i] > x[i - 1]:
            raise ConfigError(
                f"measured data file {table.name!r}, line {table.line_of(i)}: {xname} {x[i]:.6g} does not "
                f"increase from the previous row's {x[i - 1]:.6g}; the fit needs the loading part of "
                "the curve only, with increasing values (drop the unloading rows, sort or average repeats)"
            )
    if not (y > 0).any():
        raise ConfigError(f"measured data file {table.name!r}: every {yname} is zero; nothing to fit")


def specimen_geometry(mesh: TetMesh) -> tuple[float, float]:
    """Height [m] (z extent) and nominal area [m^2] (outline seen from above) of a specimen, as
    the compression test measures them."""
    p = np.asarray(mesh.points)
    return float(np.ptp(p[:, 2])), outline_area(p)


def read_compression_data(path: str | Path, height_m: float, area_m2: float) -> CompressionData:
    """Read a compression curve: ``displacement_m`` (or ``_mm``) and ``force_N``, or ``strain``
    (nominal, compressive positive) and ``stress_Pa`` (or ``_kPa``, ``_MPa``), converted with the
    specimen's ``height_m`` and ``area_m2``; optional ``lateral_strain`` (positive: widening).

    Raises ConfigError naming the file, line and column for anything a fit cannot use: empty, too
    few rows, wrong columns, non-numbers, negative force, non-increasing displacement, a strain
    beyond 0.8.
    """
    table = read_table(path, min_rows=1)
    disp = table.unit_column(_DISPLACEMENT_UNITS)
    stress = table.unit_column(_STRESS_UNITS)
    # checked in the file's own units (messages quote the file), then converted
    if disp is not None and table.has("force_N"):
        xname, yname = disp[0], "force_N"
        xs, ys = disp[1], 1.0
    elif table.has("strain") and stress is not None:
        xname, yname = "strain", stress[0]
        xs, ys = height_m, stress[1] * area_m2
    else:
        raise ConfigError(
            f"measured data file {table.name!r}: the header (line {table.header_line}) must name "
            "displacement_m (or displacement_mm) and force_N, or strain and stress_Pa (or stress_kPa, "
            f"stress_MPa); it has {','.join(table.columns)!r}"
        )
    x, y = table.values(xname), table.values(yname)
    lateral = table.values("lateral_strain") if table.has("lateral_strain") else None
    _check_curve(table, x, y, xname, yname, 4)
    x, y = x * xs, y * ys
    over = np.flatnonzero(x / height_m > MAX_STRAIN)
    if over.size:
        i = int(over[0])
        raise ConfigError(
            f"measured data file {table.name!r}, line {table.line_of(i)}: a strain of "
            f"{x[i] / height_m:.0%} ({x[i] * 1e3:.4g} mm of the specimen height {height_m * 1e3:.4g} mm); "
            f"the fit simulates up to {MAX_STRAIN:.0%} (check the specimen: --object, --mesh-size)"
        )
    return CompressionData(x, y, lateral, height_m, area_m2, table.name)


def read_indentation_data(path: str | Path) -> IndentationData:
    """Read a force-penetration curve: ``penetration_m`` (or ``_mm``) and ``force_N``; optional
    ``tangential_force_N``. Errors as :func:`read_compression_data`."""
    table = read_table(path, min_rows=1)
    pen = table.unit_column(_PENETRATION_UNITS)
    if pen is None or not table.has("force_N"):
        raise ConfigError(
            f"measured data file {table.name!r}: the header (line {table.header_line}) must name "
            f"penetration_m (or penetration_mm) and force_N; it has {','.join(table.columns)!r}"
        )
    x = table.values(pen[0])
    y = table.values("force_N")
    _check_curve(table, x, y, pen[0], "force_N", 4)
    x = x * pen[1]
    tangential = table.values("tangential_force_N") if table.has("tangential_force_N") else None
    return IndentationData(x, y, tangential, table.name)


# ---------------------------------------------------------------------- the fitting engine
@dataclass(frozen=True)
class _Spec:
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


def _correlation(cov: dict[tuple[str, str], float]) -> dict[str, dict[str, float]]:
    """Correlation coefficients from a covariance by name pairs (parameters with a finite variance)."""
    names = [a for (a, b) in cov if a == b and math.isfinite(cov[(a, a)]) and cov[(a, a)] > 0]
    return {a: {b: cov[(a, b)] / math.sqrt(cov[(a, a)] * cov[(b, b)]) for b in names} for a in names}


@dataclass(frozen=True)
class _Solution:
    """What the fitting engine found (see :func:`_least_squares`)."""

    params: dict[str, Parameter]
    residual: NDArray[np.float64]
    evaluations: int
    notes: list[str]
    cov: dict[tuple[str, str], float]
    converged: bool


def _least_squares(
    residual: Callable[[dict[str, float]], NDArray[np.float64]],
    specs: Sequence[_Spec],
    fixed: dict[str, float],
    progress: Callable[[int], None] | None,
    *,
    blocks: Sequence[int] | None = None,
    quiet: Sequence[str] = (),
    max_evaluations: int = 60,
) -> _Solution:
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
    return _Solution(params, r, count[0], notes, covd, converged)


def _at(x: NDArray[np.float64], xs: NDArray[np.float64], ys: NDArray[np.float64]) -> NDArray[np.float64]:
    """A simulated curve (xs increasing) at the measured abscissae x: monotone cubic (PCHIP)
    interpolation, whose error between the simulated increments is far below a straight chord's
    on these convex curves (a chord would bias the fitted non-linearity)."""
    return PchipInterpolator(xs, ys, extrapolate=True)(np.clip(x, xs[0], xs[-1]))


# ---------------------------------------------------------------------- compression
def _law(vals: dict[str, float]) -> Polynomial:
    """The polynomial law of fit values a2 and b = a3 - a2^2 / 3."""
    a2 = vals.get("a2", 0.0)
    return Polynomial(a2, vals.get("b", 0.0) + a2 * a2 / 3.0)


def _with_a3(params: dict[str, Parameter], cov: dict[tuple[str, str], float]) -> dict[str, Parameter]:
    """Replace the fit's b by a3 = b + a2^2 / 3, its variance from the fit's covariance (first
    order; b is fitted in log space), its status judged on its own deviation."""
    out = dict(params)
    b, a2 = out.pop("b"), out["a2"]
    a3 = b.value + a2.value**2 / 3.0
    if b.status == "fixed":
        out["a3"] = Parameter("a3", a3, math.nan, "fixed", a3, a3, a3)
        return out
    g = {"b": b.value, "a2": 2.0 * a2.value / 3.0}  # d a3 / d(log b), d a3 / d a2
    var = sum(g[m] * g[n] * cov.get((m, n), math.nan) for m in g for n in g)
    sd = math.sqrt(var) if math.isfinite(var) and var >= 0 else math.nan
    if b.status == "not identified":
        status = "not identified"
    elif b.status == "at bound":
        status = "at bound"  # b at its floor: a3 = a2^2 / 3, the least that keeps the law increasing
    else:
        status = "fitted" if sd <= UNIDENTIFIED * abs(a3) else "poorly determined"
    start = b.start + a2.start**2 / 3.0
    out["a3"] = Parameter("a3", a3, sd, status, start, math.nan, math.nan)
    return out


def fit_compression(
    mesh: TetMesh,
    data: CompressionData,
    *,
    nu: float,
    density: float | None = None,
    mass: float | None = None,
    E_start: float | None = None,
    law: str = "polynomial",
    fit_nu: bool | None = None,
    plate_friction: float = 0.5,
    steps: int = 12,
    progress: Callable[[int], None] | None = None,
) -> tuple[Material, CalibrationFit]:
    """Fit E, the polynomial law (a2, a3) and, with lateral data, nu to a compression curve by
    simulating the compression test of ``mesh`` (paper Sec. 4.2, Fig. 9).

    Parameters
    ----------
    mesh: the specimen, resting on the table (its z extent is the specimen height).
    data: the measured curve (:func:`read_compression_data`).
    nu: Poisson's ratio: the fixed value, or the start when it is fitted.
    density, mass: the specimen's density [kg/m^3] or mass [kg] (gravity only; one is needed).
    E_start: starting E [Pa]; default from the data's slope.
    law: ``polynomial`` (fit a2, a3) or ``linear`` (E only).
    fit_nu: fit nu (default: when the data have lateral strains).
    plate_friction: friction coefficient between plates and specimen (0.5: dry platens).
    steps: load increments of each simulated test.
    progress: called with the number of simulated tests so far.

    Returns
    -------
    (the fitted Material with a Polynomial law, the fit).
    """
    if law not in ("polynomial", "linear"):
        raise ConfigError(f"law must be 'polynomial' or 'linear', got {law!r}")
    if not (-1.0 < nu < 0.5):
        raise MaterialError(f"nu = {nu} is invalid: it must lie in (-1, 0.5)")
    if density is None and mass is None:
        raise ConfigError("give the specimen's density or mass (its weight loads the test)")
    if fit_nu is None:
        fit_nu = data.lateral_strain is not None
    if fit_nu and data.lateral_strain is None:
        raise ConfigError(
            "fitting nu needs lateral measurements: add a lateral_strain column (change of width over "
            "initial width) to the compression data, or give --nu"
        )
    t0 = time.perf_counter()
    H = data.height_m
    strain = float(data.displacement_m.max()) / H
    Fscale = float(data.force_N.max())
    lat_scale = float(np.abs(data.lateral_strain).max()) if data.lateral_strain is not None else 1.0
    lat_scale = lat_scale if lat_scale > 0 else 1.0
    last: dict[str, object] = {}

    def simulate(vals: dict[str, float]):
        try:
            mat = Material(
                E=vals["E_Pa"],
                nu=vals["nu"],
                density=density,
                law=_law(vals),
                name="calibrated",
            )
            body = build_body(mesh, mat, mass=mass)
            return compression_test(body, strain=strain, steps=steps, plate_friction=plate_friction)
        except SoftgraspError:  # a trial point the model cannot take (law, solve): a failed step
            return None

    def residual(vals: dict[str, float]) -> NDArray[np.float64]:
        res = simulate(vals)
        n = len(data.force_N) + (len(data.force_N) if fit_nu else 0)
        if res is None:
            return np.full(n, np.nan)
        F = _at(data.displacement_m, res.displacement_m, res.force_N)
        last["F"] = F
        r = (F - data.force_N) / Fscale
        if fit_nu:
            assert data.lateral_strain is not None
            lat = _at(data.displacement_m, res.displacement_m, res.lateral_strain)
            last["lat"] = lat
            r = np.concatenate([r, (lat - data.lateral_strain) / lat_scale])
        return r

    # Starting E: one linear simulation at a trial modulus, scaled (forces are nearly
    # proportional to E: only the specimen's weight is not).
    E0 = E_start
    if E0 is None:
        e = data.displacement_m / H
        sel = data.displacement_m > 0
        E_trial = float((e[sel] @ (data.force_N[sel] / data.area_m2)) / (e[sel] @ e[sel]))
        trial = simulate({"E_Pa": E_trial, "nu": nu})
        if trial is None:
            raise NotConverged(
                "the simulated compression test failed at the starting modulus; check the mesh"
            )
        Fs = _at(data.displacement_m, trial.displacement_m, trial.force_N)
        # the initial part of the curve, where the law is nearly linear
        n0 = max(2, int(np.searchsorted(e, 0.1 * e.max())))
        E0 = E_trial * float(Fs[:n0] @ data.force_N[:n0]) / float(Fs[:n0] @ Fs[:n0])
    specs = [_Spec("E_Pa", E0, E0 / 20.0, E0 * 20.0, log=True)]
    fixed = {}
    if law == "polynomial":
        specs += [_Spec("a2", 0.0, *A2_BOUNDS), _Spec("b", 0.01, *B_BOUNDS, log=True)]
    else:
        fixed.update({"a2": 0.0, "b": 0.0})
    if fit_nu:
        specs.append(_Spec("nu", min(max(nu, -0.9), 0.49), -0.9, 0.49))
    else:
        fixed["nu"] = nu
    n_force = len(data.force_N)
    blocks = [n_force, n_force] if fit_nu else None
    solution = _least_squares(residual, specs, fixed, progress, blocks=blocks, quiet=("b",))
    count, notes = solution.evaluations, list(solution.notes)
    final = {k: p.value for k, p in solution.params.items()}
    params = _with_a3(solution.params, solution.cov)
    for name in ("a3",):
        p = params[name]
        if p.status == "poorly determined":
            notes.append(f"a3 poorly determined: {p.value:.4g} +- {p.stderr:.3g}")
        elif p.status == "at bound":
            notes.append(f"a3 = a2^2/3 = {p.value:.4g}: the law's least stiffening in tension allowed")
    final["a3"] = params["a3"].value
    res = simulate(final)
    if res is None:
        raise NotConverged("the simulated compression test failed at the fitted parameters")
    F = _at(data.displacement_m, res.displacement_m, res.force_N)
    lat = _at(data.displacement_m, res.displacement_m, res.lateral_strain) if fit_nu else None
    mat = Material(
        E=final["E_Pa"],
        nu=final["nu"],
        density=density,
        law=Polynomial(final["a2"], final["a3"]),
        name="calibrated",
    )
    err = F - data.force_N
    fit = CalibrationFit(
        kind="compression",
        parameters=params,
        x=data.displacement_m,
        measured=data.force_N,
        fitted=F,
        lateral_measured=data.lateral_strain if fit_nu else None,
        lateral_fitted=lat,
        residual_rms_N=float(np.sqrt(np.mean(err**2))),
        mean_abs_error_N=float(np.mean(np.abs(err))),
        relative_rms=float(np.sqrt(np.mean(err**2)) / Fscale),
        simulations=count + 2,
        wall_time_s=time.perf_counter() - t0,
        notes=tuple(notes),
        converged=solution.converged,
        correlation=_correlation(solution.cov),
    )
    return mat, fit


# ---------------------------------------------------------------------- indentation
def fit_indentation(
    body: Body,
    data: IndentationData,
    *,
    params: ContactParams = ContactParams(),  # noqa: B008 - frozen dataclass
    radius: float = 0.008,
    speed: float = 0.005,
    fit: Sequence[str] = ("stiffness_prefactor", "exponent", "gamma_N_s_m2"),
    steps: int = 12,
    progress: Callable[[int], None] | None = None,
) -> tuple[ContactParams, CalibrationFit]:
    """Fit the contact law (c of K = c Psi sqrt(R), n, gamma; mu with tangential data) to a
    measured force-penetration curve by simulating the indentation test of ``body`` (Fig. 11).

    Parameters
    ----------
    body: the object with its (calibrated) material.
    data: the measured curve (:func:`read_indentation_data`).
    params: the contact parameters to start from (and to keep for what is not fitted).
    radius: fingertip radius [m].  speed: fingertip speed of the measurement [m/s].
    fit: names of the parameters to fit; ``mu`` is added when the data have tangential forces.
    steps: increments of each simulated test.
    progress: called with the number of simulated tests so far.

    Returns
    -------
    (the fitted ContactParams, the fit); the fit's ``mean_abs_error_N`` is the paper's measure.
    """
    known = {"stiffness_prefactor", "exponent", "gamma_N_s_m2", "mu"}
    bad = [f for f in fit if f not in known]
    if bad:
        raise ConfigError(f"cannot fit {bad}; contact parameters are {sorted(known)}")
    if not (radius > 0 and math.isfinite(radius)):
        raise ConfigError(f"fingertip radius = {radius} m is invalid: it must be > 0")
    if not (speed > 0 and math.isfinite(speed)):
        raise ConfigError(f"indentation speed = {speed} m/s is invalid: it must be > 0")
    names = list(fit)
    if data.tangential_force_N is not None and "mu" not in names:
        names.append("mu")
    t0 = time.perf_counter()
    depth = float(data.penetration_m.max())
    Fscale = float(data.force_N.max())
    tscale = max(Fscale, 1e-12)
    start = {
        "stiffness_prefactor": params.prefactor,
        "exponent": params.exponent,
        "gamma_N_s_m2": params.gamma,
        "mu": params.mu,
    }
    bounds = {
        "stiffness_prefactor": (params.prefactor / 50.0, params.prefactor * 50.0),
        "exponent": (1.0, 3.0),
        "gamma_N_s_m2": (0.0, max(1e3, 100.0 * params.gamma)),
        "mu": (0.0, 2.0),
    }

    def contact(vals: dict[str, float]) -> ContactParams:
        return replace(
            params,
            prefactor=vals["stiffness_prefactor"],
            exponent=vals["exponent"],
            gamma=vals["gamma_N_s_m2"],
            mu=vals["mu"],
        )

    def simulate(vals: dict[str, float]):
        try:
            p = contact(vals)
            res = indentation_test(body, depth=depth, radius=radius, speed=speed, steps=steps, params=p)
        except (SoftgraspError, ValueError):
            return None, None
        # The damping term of Eq. 12-14 at the test speed. The contact-law penetration delta is in
        # series with the body's own compliance: delta_dot = (d delta / d travel) * speed.
        C = contact_damping(radius, p.gamma)
        rate = np.gradient(res.contact_depth_m, res.penetration_m) * speed
        damp = C * rate * (res.contact_depth_m**p.exponent if p.damping == "hunt-crossley" else 1.0)
        damp = np.where(res.penetration_m > 0, damp, 0.0)
        return res, res.force_N + damp

    def residual(vals: dict[str, float]) -> NDArray[np.float64]:
        res, F = simulate(vals)
        n = len(data.force_N) * (2 if data.tangential_force_N is not None else 1)
        if res is None:
            return np.full(n, np.nan)
        r = (_at(data.penetration_m, res.penetration_m, F) - data.force_N) / Fscale
        if data.tangential_force_N is not None:
            Ft = _at(data.penetration_m, res.penetration_m, res.tangential_force_N)
            r = np.concatenate([r, (Ft - data.tangential_force_N) / tscale])
        return r

    specs = [
        _Spec(n, start[n], *bounds[n], log=(n == "stiffness_prefactor"))
        for n in ("stiffness_prefactor", "exponent", "gamma_N_s_m2", "mu")
        if n in names
    ]
    fixed = {n: start[n] for n in start if n not in names}
    n_force = len(data.force_N)
    blocks = [n_force, n_force] if data.tangential_force_N is not None else None
    solution = _least_squares(residual, specs, fixed, progress, blocks=blocks)
    fitted, count, notes = solution.params, solution.evaluations, solution.notes
    final = {k: p.value for k, p in fitted.items()}
    res, F = simulate(final)
    if res is None:
        raise NotConverged("the simulated indentation failed at the fitted contact parameters")
    Fi = _at(data.penetration_m, res.penetration_m, F)
    err = Fi - data.force_N
    mae = float(np.mean(np.abs(err)))
    fit_result = CalibrationFit(
        kind="indentation",
        parameters=fitted,
        x=data.penetration_m,
        measured=data.force_N,
        fitted=Fi,
        lateral_measured=None,
        lateral_fitted=None,
        residual_rms_N=float(np.sqrt(np.mean(err**2))),
        mean_abs_error_N=mae,
        relative_rms=float(np.sqrt(np.mean(err**2)) / Fscale),
        simulations=count + 1,
        wall_time_s=time.perf_counter() - t0,
        notes=tuple(notes),
        converged=solution.converged,
        correlation=_correlation(solution.cov),
    )
    return contact(final), fit_result
