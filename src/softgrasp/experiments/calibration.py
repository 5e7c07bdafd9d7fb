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

Uncertainties, identifiability and the least-squares engine:
:mod:`softgrasp.experiments.fitting`; reading the measured curves:
:mod:`softgrasp.experiments.calibration_data`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError, MaterialError, NotConverged, SoftgraspError
from softgrasp.experiments.calibration_data import (
    CompressionData,
    IndentationData,
    read_compression_data,
    read_indentation_data,
    specimen_geometry,
)
from softgrasp.experiments.compression import compression_test
from softgrasp.experiments.fitting import (
    UNIDENTIFIED,
    CalibrationFit,
    FitSpec,
    Parameter,
    correlation,
    curve_at,
    solve_fit,
)
from softgrasp.experiments.indentation import indentation_test
from softgrasp.model.material import Material, Polynomial
from softgrasp.model.mesh.tetmesh import TetMesh
from softgrasp.physics.body import Body, build_body
from softgrasp.physics.fingertip.laws import contact_damping
from softgrasp.physics.fingertip.params import ContactParams

__all__ = [
    "Parameter",
    "CalibrationFit",
    "CompressionData",
    "IndentationData",
    "read_compression_data",
    "read_indentation_data",
    "specimen_geometry",
    "fit_compression",
    "fit_indentation",
]

#: Bounds of the polynomial law's a2 in a fit, and of its excess b = a3 - a2^2 / 3 (> 0 keeps the
#: law increasing at every strain: its slope 1 + 2 a2 e + 3 a3 e^2 then has no real root).
A2_BOUNDS = (-4.0, 4.0)
B_BOUNDS = (1e-3, 20.0)


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
        F = curve_at(data.displacement_m, res.displacement_m, res.force_N)
        last["F"] = F
        r = (F - data.force_N) / Fscale
        if fit_nu:
            assert data.lateral_strain is not None
            lat = curve_at(data.displacement_m, res.displacement_m, res.lateral_strain)
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
        Fs = curve_at(data.displacement_m, trial.displacement_m, trial.force_N)
        # the initial part of the curve, where the law is nearly linear
        n0 = max(2, int(np.searchsorted(e, 0.1 * e.max())))
        E0 = E_trial * float(Fs[:n0] @ data.force_N[:n0]) / float(Fs[:n0] @ Fs[:n0])
    specs = [FitSpec("E_Pa", E0, E0 / 20.0, E0 * 20.0, log=True)]
    fixed = {}
    if law == "polynomial":
        specs += [FitSpec("a2", 0.0, *A2_BOUNDS), FitSpec("b", 0.01, *B_BOUNDS, log=True)]
    else:
        fixed.update({"a2": 0.0, "b": 0.0})
    if fit_nu:
        specs.append(FitSpec("nu", min(max(nu, -0.9), 0.49), -0.9, 0.49))
    else:
        fixed["nu"] = nu
    n_force = len(data.force_N)
    blocks = [n_force, n_force] if fit_nu else None
    solution = solve_fit(residual, specs, fixed, progress, blocks=blocks, quiet=("b",))
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
    F = curve_at(data.displacement_m, res.displacement_m, res.force_N)
    lat = curve_at(data.displacement_m, res.displacement_m, res.lateral_strain) if fit_nu else None
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
        correlation=correlation(solution.cov),
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
        r = (curve_at(data.penetration_m, res.penetration_m, F) - data.force_N) / Fscale
        if data.tangential_force_N is not None:
            Ft = curve_at(data.penetration_m, res.penetration_m, res.tangential_force_N)
            r = np.concatenate([r, (Ft - data.tangential_force_N) / tscale])
        return r

    specs = [
        FitSpec(n, start[n], *bounds[n], log=(n == "stiffness_prefactor"))
        for n in ("stiffness_prefactor", "exponent", "gamma_N_s_m2", "mu")
        if n in names
    ]
    fixed = {n: start[n] for n in start if n not in names}
    n_force = len(data.force_N)
    blocks = [n_force, n_force] if data.tangential_force_N is not None else None
    solution = solve_fit(residual, specs, fixed, progress, blocks=blocks)
    fitted, count, notes = solution.params, solution.evaluations, solution.notes
    final = {k: p.value for k, p in fitted.items()}
    res, F = simulate(final)
    if res is None:
        raise NotConverged("the simulated indentation failed at the fitted contact parameters")
    Fi = curve_at(data.penetration_m, res.penetration_m, F)
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
        correlation=correlation(solution.cov),
    )
    return contact(final), fit_result
