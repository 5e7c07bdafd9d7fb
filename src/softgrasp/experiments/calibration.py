"""Fitting the model to measurements (paper Sec. 4.2-4.3, Figs. 9 and 11).

*Compression* (:func:`fit_compression`): a measured force-displacement (or stress-strain) curve of
a specimen squeezed between plates gives the specimen's uniaxial law sigma = E (epsilon + c2
epsilon^2 + c3 epsilon^3) (:mod:`softgrasp.experiments.uniaxial`), the platens' friction taken from
softgrasp's own compression test (:func:`softgrasp.experiments.compression.compression_test`) of a
mesh of the specimen, and, when the file has lateral strains, Poisson's ratio; the calibrated
material's edge law is the one whose simulated specimen follows the fitted law.

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
from scipy.optimize import least_squares

from softgrasp.errors import ConfigError, MaterialError, NotConverged, SoftgraspError, diagnosis
from softgrasp.experiments.calibration_data import (
    MAX_STRAIN,
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
from softgrasp.experiments.uniaxial import (
    EDGE_LAW_TOLERANCE,
    edge_law_for,
    fit_linear,
    fit_specimen_law,
    specimen_modulus,
)
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

#: Largest change of the platens' stiffening ratio (relative) at which the fit stops iterating.
RATIO_TOLERANCE = 2e-4
#: Rounds of the fit's outer iteration (specimen law, edge law, platens' ratio, nu).
MAX_ROUNDS = 8


def _parameter(name: str, value: float, sd: float, start: float) -> Parameter:
    """A fitted parameter, flagged poorly determined when its deviation exceeds its value."""
    ok = math.isfinite(sd) and sd <= UNIDENTIFIED * abs(value)
    return Parameter(name, value, sd, "fitted" if ok else "poorly determined", start, -math.inf, math.inf)


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
    volume: str = "element",
) -> tuple[Material, CalibrationFit]:
    """Fit the specimen's uniaxial law (E, c2, c3 of :mod:`softgrasp.experiments.uniaxial`) and,
    with lateral data, nu to a compression curve, and give the body the edge law that reproduces
    it (paper Sec. 4.2, Fig. 9).

    The force model is A E (epsilon + c2 epsilon^2 + c3 epsilon^3) R(epsilon), R the platens'
    stiffening ratio simulated with the body (1 for lubricated platens, ``plate_friction`` 0):
    given R, a weighted linear least-squares problem (:func:`~softgrasp.experiments.uniaxial.fit_linear`).
    The rounds alternate that fit, the edge law whose simulated lubricated specimen follows the
    fitted law (:func:`~softgrasp.experiments.uniaxial.edge_law_for`), R from the simulated tests
    with and without friction, and nu (a one-parameter fit of the simulated lateral strains), until
    R and nu settle. With ``law="linear"`` the springs are Hookean and the simulated test itself is
    the model, with E its only (linear) parameter.

    Parameters
    ----------
    mesh: the specimen, resting on the table (its z extent is the specimen height).
    data: the measured curve (:func:`read_compression_data`).
    nu: Poisson's ratio: the fixed value, or the start when it is fitted.
    density, mass: the specimen's density [kg/m^3] or mass [kg] (gravity only; one is needed).
    E_start: E [Pa] of the first simulations of a linear fit; default from the data's slope.
    law: ``polynomial`` (fit the specimen law's E, c2, c3) or ``linear`` (Hookean springs, E only).
    fit_nu: fit nu (default: when the data have lateral strains).
    plate_friction: friction coefficient between plates and specimen (0.5: dry platens).
    steps: load increments of each simulated test.
    progress: called with the number of simulated tests so far.
    volume: the simulated body's volume term (:attr:`~softgrasp.physics.body.Body.volume`): the
        one the calibrated material will be used with.

    Returns
    -------
    (the fitted Material: E, nu and the edge law, Tabulated for ``polynomial``; the fit). For
    ``polynomial`` the fit's ``E_specimen_Pa`` is the specimen law's E and ``E_Pa`` the Material's:
    the former over the ratio of the body's simulated small-strain specimen modulus to its
    Material's E (the spring network's small-strain error, ~2 % on a coarse mesh), so that the
    calibrated body reproduces the data. A note flags a simulated lubricated specimen whose force
    drops within the data (unstable: no specimen law describes it there).
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
    H, A = data.height_m, data.area_m2
    d, F = data.displacement_m, data.force_N
    eps = d / H
    top = float(eps.max())
    count = [0]
    notes: list[str] = []

    def run(E: float, nu_: float, edge, friction: float, strain: float):
        count[0] += 1
        if progress is not None:
            progress(count[0])
        try:
            specimen = Material(E, nu_, density, edge, name="calibrated")
            body = build_body(mesh, specimen, mass=mass, volume=volume)
            return compression_test(body, strain=strain, steps=steps, plate_friction=friction)
        except SoftgraspError as exc:
            raise NotConverged(
                f"the simulated compression test failed during the fit ({diagnosis(exc)}); try another "
                "--mesh-size or --steps"
            ) from None

    # The edge-law and ratio simulations reach beyond the data (a test's last increments are its
    # least accurate); only the data's range is used.
    reach = min(1.2 * top, MAX_STRAIN)
    reach_now = [reach]

    def lubricated(E: float, nu_: float, edge_law):
        # beyond the data a lubricated specimen may fail to converge: then stop at the data's end
        try:
            return run(E, nu_, edge_law, 0.0, reach_now[0])
        except NotConverged:
            if reach_now[0] == top:
                raise
            reach_now[0] = top
            return run(E, nu_, edge_law, 0.0, top)

    nu_now = nu
    nu_sd = math.nan
    R = np.ones_like(eps)
    edge = None
    res = None
    converged = False
    specimen: tuple[float, float] | None = None
    if law == "linear":
        spring = Polynomial(0.0, 0.0)
        sel = d > 0
        E = E_start or float((eps[sel] @ (F[sel] / A)) / (eps[sel] @ eps[sel]))
        for _ in range(MAX_ROUNDS):
            res = run(E, nu_now, spring, plate_friction, top)
            per_E = curve_at(d, res.displacement_m, res.force_N) / E  # force per unit modulus
            lf = fit_linear(per_E[:, None], F)
            E_new = float(lf.p[0])
            done = abs(E_new / E - 1.0) < RATIO_TOLERANCE
            E = E_new
            if done:
                converged = True
                break
        vals, cov = [E], lf.cov
        final = Material(E, nu_now, density, spring, name="calibrated")
        res = run(E, nu_now, spring, plate_friction, top)
    else:
        for _ in range(MAX_ROUNDS):
            vals, cov = fit_specimen_law(eps, F, A * R)
            E, c2, c3 = vals
            edge = edge_law_for(lambda lw, E=E, n=nu_now: lubricated(E, n, lw), c2, c3, top, start=edge)
            lub = edge.lubricated
            R_new = np.ones_like(eps)
            if plate_friction > 0:
                stuck = run(E, nu_now, edge.law, plate_friction, reach_now[0])
                R_new = curve_at(d, stuck.displacement_m[1:], stuck.force_N[1:] / lub.force_N[1:])
            nu_new = nu_now
            if fit_nu:
                nu_new, nu_sd = _fit_nu(run, data, E, edge.law, nu_now, plate_friction, top)
            change = float(np.abs(R_new / R - 1.0).max())
            R = R_new
            if change < RATIO_TOLERANCE and abs(nu_new - nu_now) < 1e-4:
                converged = True
                break
            nu_now = nu_new
        assert edge is not None
        # The body's specimen modulus is the spring network's, a little off its Material's E: the
        # Material whose body follows the fitted law has E scaled by their ratio.
        specimen = (vals[0], math.sqrt(cov[0, 0]) if cov[0, 0] >= 0 else math.nan)
        scale = vals[0] / specimen_modulus(edge.lubricated, vals[1], vals[2])
        vals = [vals[0] * scale, *vals[1:]]
        cov = np.diag([scale, 1.0, 1.0]) @ cov @ np.diag([scale, 1.0, 1.0])
        lub = edge.lubricated
        inside = lub.strain <= top * (1 + 1e-9)
        drop = np.flatnonzero(np.diff(lub.force_N[inside]) <= 0)
        if drop.size:
            notes.append(
                f"the simulated lubricated specimen loses stability (its force drops) at strain "
                f"{lub.strain[drop[0] + 1]:.3g}: no specimen law describes the body beyond it"
            )
        if edge.deviation > 10 * EDGE_LAW_TOLERANCE:
            notes.append(
                f"the body follows the fitted specimen law only within {edge.deviation:.1%} (edge law "
                "not converged)"
            )
        final = Material(vals[0], nu_now, density, edge.law, name="calibrated")
        res = run(vals[0], nu_now, edge.law, plate_friction, reach_now[0])
    if not converged:
        notes.append(f"the fit's rounds did not settle in {MAX_ROUNDS}; its values are not reliable")
    names = ["E_Pa", "c2", "c3"][: len(vals)]
    params: dict[str, Parameter] = {}
    starts = {"E_Pa": vals[0], "c2": 0.0, "c3": 0.0}
    for k, name in enumerate(names):
        sd = math.sqrt(cov[k, k]) if cov[k, k] >= 0 else math.nan
        params[name] = _parameter(name, vals[k], sd, starts[name])
        if params[name].status == "poorly determined":
            notes.append(f"{name} poorly determined: {vals[k]:.4g} +- {sd:.3g} (consistent with zero)")
    for name in ("c2", "c3"):
        params.setdefault(name, Parameter(name, 0.0, math.nan, "fixed", 0.0, 0.0, 0.0))
    if specimen is not None:
        params["E_specimen_Pa"] = _parameter("E_specimen_Pa", specimen[0], specimen[1], specimen[0])
    if fit_nu:
        params["nu"] = _parameter("nu", nu_now, nu_sd, nu)
    else:
        params["nu"] = Parameter("nu", nu_now, math.nan, "fixed", nu_now, nu_now, nu_now)
    Fs = curve_at(d, res.displacement_m, res.force_N)
    lat = curve_at(d, res.displacement_m, res.lateral_strain) if fit_nu else None
    err = Fs - F
    Fscale = float(F.max())
    covd = {(a, b): float(cov[i, j]) for i, a in enumerate(names) for j, b in enumerate(names)}
    fit = CalibrationFit(
        kind="compression",
        parameters=params,
        x=d,
        measured=F,
        fitted=Fs,
        lateral_measured=data.lateral_strain if fit_nu else None,
        lateral_fitted=lat,
        residual_rms_N=float(np.sqrt(np.mean(err**2))),
        mean_abs_error_N=float(np.mean(np.abs(err))),
        relative_rms=float(np.sqrt(np.mean(err**2)) / Fscale),
        simulations=count[0],
        wall_time_s=time.perf_counter() - t0,
        notes=tuple(notes),
        converged=converged,
        correlation=correlation(covd),
    )
    return final, fit


def _fit_nu(run, data: CompressionData, E: float, edge, nu: float, friction: float, top: float):
    """nu (and its deviation) by least squares of the simulated lateral strains (the material's
    other parameters fixed), and the deviation from the residual variance and a central-difference
    slope."""
    assert data.lateral_strain is not None
    d, lat = data.displacement_m, data.lateral_strain

    def residual(u: NDArray[np.float64]) -> NDArray[np.float64]:
        r = run(E, float(u[0]), edge, friction, top)
        return curve_at(d, r.displacement_m, r.lateral_strain) - lat

    sol = least_squares(
        residual, [min(max(nu, -0.9), 0.49)], bounds=([-0.9], [0.49]), diff_step=1e-3, max_nfev=20
    )
    n_hat = float(sol.x[0])
    h = 1e-3
    J = (residual(np.array([min(n_hat + h, 0.49)])) - residual(np.array([max(n_hat - h, -0.9)]))) / (
        min(n_hat + h, 0.49) - max(n_hat - h, -0.9)
    )
    s2 = float(sol.fun @ sol.fun) / max(len(d) - 1, 1)
    sd = math.sqrt(s2 / float(J @ J)) if float(J @ J) > 0 else math.nan
    return n_hat, sd


# ---------------------------------------------------------------------- indentation
def fit_indentation(
    body: Body,
    data: IndentationData,
    *,
    params: ContactParams = ContactParams(),  # noqa: B008 - frozen dataclass
    radius: float = 0.008,
    speed: float = 0.005,
    fit: Sequence[str] | None = None,
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
    fit: names of the parameters to fit; default ``stiffness_prefactor`` and ``gamma_N_s_m2``, and
        ``exponent`` under the paper's law (the resolved law is Hertz's, n = 3/2); ``mu`` is added
        when the data have tangential forces.
    steps: increments of each simulated test.
    progress: called with the number of simulated tests so far.

    Returns
    -------
    (the fitted ContactParams, the fit); the fit's ``mean_abs_error_N`` is the paper's measure.
    """
    known = {"stiffness_prefactor", "exponent", "gamma_N_s_m2", "mu"}
    if fit is None:
        fit = ("stiffness_prefactor", "exponent", "gamma_N_s_m2") if params.law == "paper" else (
            "stiffness_prefactor", "gamma_N_s_m2")
    bad = [f for f in fit if f not in known]
    if bad:
        raise ConfigError(f"cannot fit {bad}; contact parameters are {sorted(known)}")
    if "exponent" in fit and params.law != "paper":
        raise ConfigError("the resolved contact law is Hertz's (exponent 1.5): fit the exponent with the paper's law")
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
