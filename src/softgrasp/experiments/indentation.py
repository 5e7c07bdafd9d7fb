"""Indentation by one fingertip (paper Sec. 4.3.1, Figs. 10-11): force versus penetration.

A spherical fingertip presses straight down on the object resting on the table. The object, turned
onto its most stable facet where it would tip over as meshed (:func:`softgrasp.grasp.settle.standing`,
as a plan places it), first settles under gravity (:func:`softgrasp.sim.static.solve_rest`); the
fingertip starts one increment above the surface point under the press point and moves down
along -z. The test is quasi-static: the fingertip path is cut into load increments and every
increment is a static solve (:func:`softgrasp.sim.static.solve_increment`, the load parameter
``t`` being the fingertip travel in metres since its start, the fingertip velocity
``(0, 0, -1)`` in those units). Times are reported as ``travel / speed``.

Definitions
-----------
travel
    Distance the fingertip centre has moved since its start [m].
first contact
    The travel at which the fingertip first touches a boundary facet of the *settled* object
    (the contact detection of Sec. 3.1 reports a pair). Before first contact nothing pushes on the
    object, so it is found exactly, by bisection on the settled positions, without a solve.
penetration
    Travel since first contact [m]: how far the finger has pushed, the abscissa of Fig. 11. It is
    the sum of the contact-law depth (max delta_j of Eq. 14, reported separately) and the object's
    own deformation under the finger.

First contact is found with the contact model's own detection (its rule). The paper's detection
(Sec. 3.1, ``rule="facet"``) needs the projection of the fingertip centre on a facet to fall
inside the facet: above a mesh vertex or an edge where the surface is (even minutely) convex,
every projection falls just outside its facet and the fingertip is never detected (the patch
rule measures the overlap to each facet's closest point and has no such blind spot). The press
point is therefore checked before loading: if the fingertip touching the surface under it is not
detected, it is moved towards the centroid of the facet under it (first by 1e-4 of the way, then
further) until it is. The point used and the shift are reported.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError, ContactError, NotConverged, diagnosis
from softgrasp.experiments.measured import read_table
from softgrasp.experiments.surface import surface_height
from softgrasp.grasp.settle import no_rest_advice, standing
from softgrasp.linalg.solve import SolverCache
from softgrasp.model.mesh.placement import rigid_fit
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.contact import FingerReport, FingertipContact
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim.newton import STALL_RTOL
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import extrapolated, solve_increment, solve_rest

__all__ = [
    "DEFAULT_INCREMENT",
    "MIN_STEPS",
    "IndentationResult",
    "default_steps",
    "indentation_test",
    "mean_abs_force_error",
    "read_force_curve",
    "surface_height",
]

#: Default load increment of the fingertip travel [m].
DEFAULT_INCREMENT = 0.25e-3
#: Fewest increments of a default schedule.
MIN_STEPS = 10
#: How often an increment that does not converge is halved before giving up.
MAX_HALVINGS = 4
#: Fractions of the way towards the facet centroid tried when the press point is in a blind spot.
_NUDGES = (0.0, 1e-4, 1e-2, 0.1, 0.3, 1.0)


@dataclass(frozen=True)
class IndentationResult:
    """Force-penetration record of an indentation test, one entry per increment.

    The first entry is the instant of first contact (penetration 0).

    Attributes
    ----------
    time_s: time since the fingertip started, travel / speed [s], (K,).
    travel_m: fingertip travel since its start [m], (K,).
    penetration_m: fingertip travel since first contact [m], (K,).
    force_N: norm of the total force of the fingertip on the object [N], (K,).
    normal_force_N: sum of the facet normal force magnitudes (Eq. 9-10) [N], (K,).
    tangential_force_N: norm of the summed friction force [N], (K,).
    contacts: number of touched facets, (K,).
    contact_depth_m: largest contact-law penetration delta of Eq. 14 [m], (K,).
    newton_iterations: Newton iterations of each increment's static solve(s), (K,); the first
        entry is the settling solve under gravity.
    first_contact_travel_m: travel at first contact [m].
    depth_m: requested penetration [m].
    speed_m_s: fingertip speed [m/s].
    peak_force_N: largest force [N].
    K_N_m1_5: contact stiffness K of Eq. 11 [N/m^1.5] (for the default exponent 1.5).
    fingertip: the fingertip at its start, with its physical velocity (0, 0, -speed) [m/s].
    params: contact parameters.
    table_mu: friction coefficient of the table.
    point_m: (x, y) where the fingertip pressed [m], (2,).
    point_shift_m: distance the press point was moved out of a detection blind spot [m] (0 if not).
    surface_z_m: height of the settled surface under the press point [m].
    settle_sag_m: lowest-to-highest drop of the top under gravity while settling [m].
    turned: whether the object was turned onto its most stable facet (it does not stand as meshed).
    halvings: increments that had to be split to converge (0 normally).
    wall_time_s: wall time of the test [s].
    final_positions_m: node positions at the last increment [m], (N, 3).
    """

    time_s: NDArray[np.float64]
    travel_m: NDArray[np.float64]
    penetration_m: NDArray[np.float64]
    force_N: NDArray[np.float64]
    normal_force_N: NDArray[np.float64]
    tangential_force_N: NDArray[np.float64]
    contacts: NDArray[np.int64]
    contact_depth_m: NDArray[np.float64]
    newton_iterations: NDArray[np.int64]
    first_contact_travel_m: float
    depth_m: float
    speed_m_s: float
    peak_force_N: float
    K_N_m1_5: float
    fingertip: Fingertip
    params: ContactParams
    table_mu: float
    point_m: NDArray[np.float64]
    point_shift_m: float
    surface_z_m: float
    settle_sag_m: float
    turned: bool
    halvings: int
    wall_time_s: float
    final_positions_m: NDArray[np.float64]


def default_steps(depth: float) -> int:
    """Number of increments of about :data:`DEFAULT_INCREMENT` for ``depth`` [m], at least
    :data:`MIN_STEPS`."""
    return max(MIN_STEPS, math.ceil(depth / DEFAULT_INCREMENT - 1e-9))


def _contact_at(probe: FingertipContact, body: Body, x, xy, ztop: float, travel: float) -> bool:
    """Whether the fingertip above ``xy`` (centre at ztop, moving down) is detected at ``travel``
    by the contact model's own detection rule (``probe``: its parameters, one fingertip)."""
    tip = replace(probe.fingertips[0], centre=np.array([xy[0], xy[1], ztop - travel]))
    return len(replace(probe, fingertips=(tip,)).pairs(body, x, 0.0)) > 0


def _first_contact(
    probe: FingertipContact, body: Body, x, xy, zc: float, radius: float, t_geo: float
) -> float | None:
    """Travel of first detected contact of a fingertip starting with its centre at height ``zc``
    above ``xy`` on the fixed positions ``x``; None if it is not detected by ``t_geo`` plus a small
    tolerance (the travel at which it reaches the surface under ``xy``)."""
    t_end = t_geo + 1e-3 * radius
    grid = np.linspace(0.0, t_end, 65)
    hit = next((k for k, t in enumerate(grid) if _contact_at(probe, body, x, xy, zc, t)), None)
    if hit is None:
        return None
    if hit == 0:
        return 0.0
    lo, hi = float(grid[hit - 1]), float(grid[hit])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if _contact_at(probe, body, x, xy, zc, mid):
            hi = mid
        else:
            lo = mid
        if hi - lo <= 1e-12 * max(radius, 1.0):
            break
    return hi


def _place_fingertip(probe: FingertipContact, body: Body, x, xy0, radius: float, gap: float):
    """Press point out of detection blind spots, surface height, start height and first contact.

    Returns (xy, shift, surface_z, start centre height, first-contact travel)."""
    facets = body.mesh.facets
    _, f0 = surface_height(x, facets, xy0)
    target = x[facets[f0]].mean(axis=0)[:2]
    for frac in _NUDGES:
        xy = xy0 + frac * (target - xy0)
        zs, _ = surface_height(x, facets, xy)
        zc = zs + radius + gap
        t0 = _first_contact(probe, body, x, xy, zc, radius, gap)
        if t0 is not None:
            return xy, float(np.linalg.norm(xy - xy0)), zs, zc, t0
    raise ContactError(
        f"the fingertip above ({xy0[0] * 1e3:.2f}, {xy0[1] * 1e3:.2f}) mm is never detected by the "
        "facet contact test (the point lies in a blind spot of the detection); choose another point"
    )


def _check(depth, radius, speed, steps, table_mu, fingertip_E, fingertip_nu, height) -> int:
    def bad(name: str, v: object, rule: str) -> ConfigError:
        return ConfigError(f"indentation {name} = {v} is invalid: {rule}")

    for name, v in (("depth", depth), ("radius", radius), ("speed", speed)):
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            raise bad(name, v, "give a finite value > 0 (SI units: m, m, m/s)")
    if depth >= height:
        raise ConfigError(
            f"indentation depth = {depth * 1e3:.4g} mm is invalid: it must be smaller than the "
            f"object's height {height * 1e3:.4g} mm"
        )
    if steps is None:
        steps = default_steps(depth)
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer) or not 1 <= steps <= 100_000:
        raise bad("steps", steps, "give an integer number of increments from 1 to 100000")
    if not (math.isfinite(table_mu) and table_mu >= 0):
        raise bad("table friction", table_mu, "it must be >= 0")
    if not fingertip_E > 0:
        raise bad("fingertip E", fingertip_E, "it must be > 0 Pa (inf: rigid)")
    if not -1.0 < fingertip_nu < 0.5:
        raise bad("fingertip nu", fingertip_nu, "it must lie in (-1, 0.5)")
    return int(steps)


def _solve(
    scene: Scene, state: State, t: float, cache: SolverCache, hint: str = "", guess: NDArray | None = None
) -> tuple[State, int, int]:
    """Static solve at travel ``t`` from ``state`` (Newton starting from ``guess`` where given),
    split in halves when it fails (:func:`softgrasp.sim.static.solve_increment`). Returns (state,
    Newton iterations, halvings)."""
    try:
        return solve_increment(scene, state, t, cache=cache, max_halvings=MAX_HALVINGS, guess=guess)
    except NotConverged as exc:
        raise NotConverged(f"indentation increment to travel {t * 1e3:.4g} mm failed: {exc}{hint}") from exc


def indentation_test(
    body: Body,
    *,
    depth: float = 0.005,
    radius: float = 0.008,
    speed: float = 0.005,
    steps: int | None = None,
    params: ContactParams = ContactParams(),  # noqa: B008 - frozen dataclass
    point: Sequence[float] | None = None,
    table_mu: float = 0.5,
    fingertip_E: float = math.inf,
    fingertip_nu: float = 0.3,
    progress: Callable[[float], None] | None = None,
) -> IndentationResult:
    """Press one spherical fingertip straight down into ``body`` and record force vs penetration.

    Parameters
    ----------
    body: the object; it rests on a table at the height of its lowest node.
    depth: penetration to reach, fingertip travel beyond first contact [m]; 0 < depth < height.
    radius: fingertip radius R [m].
    speed: fingertip speed [m/s]; sets the time axis only (the test is quasi-static).
    steps: number of equal increments from first contact to ``depth``; default about 0.25 mm
        each, at least 10 (:func:`default_steps`).
    params: contact parameters (friction mu, exponent, K prefactor, rule ...).
    point: (x, y) [m] where to press; default the object's volume centroid. On an object turned to
        stand, the surface point above it as meshed, turned with the object.
    table_mu: friction coefficient between the object and the table.
    fingertip_E: Young's modulus of the fingertip [Pa] (Eq. 12); ``inf`` (default) is rigid.
    fingertip_nu: Poisson ratio of the fingertip.
    progress: called with the completed fraction after every increment.

    Returns
    -------
    IndentationResult (see its attributes; the first entry is the instant of first contact).

    Raises
    ------
    ConfigError: a parameter out of range, or the point is not above the object.
    ContactError: the fingertip cannot be detected above the point, or it lost contact while
        pressing (its contact depth reached its radius).
    NotConverged: an increment did not reach equilibrium even when split.
    """
    t_start = time.perf_counter()
    placed = standing(body)
    turned = placed is not body
    if turned and point is not None:
        # The point of the surface above ``point`` as meshed, carried with the turn.
        x0 = np.asarray(body.mesh.points)
        top = np.array([point[0], point[1], surface_height(x0, body.mesh.facets, point)[0], 1.0])
        point = (rigid_fit(x0, placed.mesh.points) @ top)[:2]
    body = placed
    x_mesh = np.asarray(body.mesh.points)
    zmin = float(x_mesh[:, 2].min())
    height = float(x_mesh[:, 2].max()) - zmin
    steps = _check(depth, radius, speed, steps, table_mu, fingertip_E, fingertip_nu, height)
    xy0 = np.asarray(body.mesh.centroid[:2] if point is None else point, dtype=np.float64)
    if xy0.shape != (2,) or not np.isfinite(xy0).all():
        raise ConfigError(f"indentation point must be two finite numbers (x, y) in m, got {point!r}")
    inc = depth / steps

    # Double-precision factors: the calibration differences these curves (see SolverCache.precision).
    # The body's exact matrix factorised whatever its size: a nodal body's indentation converges
    # in fewer Newton iterations than with GMRES on the per-tet approximation (a 20 mm ball
    # pressed 0.5 mm on 2 200 uniform nodes: 55 iterations and 4 s against 143 and 12 s).
    cache = SolverCache(precision="double", exact_body=True)
    table = PlaneContact(
        Plane(np.array([0.0, 0.0, zmin]), np.array([0.0, 0.0, 1.0])), mu=table_mu, name="table"
    )
    rest = Scene(body, (table,))
    # To the stall tolerance, as a plan's settle: a ball rolls neutrally, a tighter rest wanders.
    try:
        settled, its0 = solve_rest(rest, rest.initial_state(), cache=cache, rtol=STALL_RTOL)
    except NotConverged as exc:
        advice = no_rest_advice(body)
        raise NotConverged(f"the object found no rest on the table: {diagnosis(exc)}", advice) from exc
    xs = settled.x
    top = float(xs[:, 2].max())
    sag = float(x_mesh[:, 2].max() - top)

    # The fingertip starts one increment above the surface under the press point.
    probe = FingertipContact((Fingertip(radius, E=fingertip_E, nu=fingertip_nu),), params)
    xy, shift, zs, zc, t0 = _place_fingertip(probe, body, xs, xy0, radius, inc)
    centre = np.array([xy[0], xy[1], zc])
    moving = Fingertip(
        radius, centre=centre, velocity=np.array([0.0, 0.0, -1.0]), E=fingertip_E, nu=fingertip_nu
    )
    finger = FingertipContact((moving,), params)
    K = float(finger.stiffness(body)[0])
    scene = Scene(body, (table, finger))
    state = State(xs, np.zeros_like(xs), t0, (settled.contacts[0], finger.init_state(body, xs, t0)))

    hint = (
        " (with the 'facet' rule the total force jumps whenever a facet enters contact, so a static "
        "equilibrium may not exist; the 'patch' rule is continuous)"
        if params.rule == "facet"
        else ""
    )
    rows: list[tuple[float, ...]] = []
    iters: list[int] = []
    halvings = 0

    def record(st: State, n_it: int) -> FingerReport:
        rep = finger.report(body, st.x, None, st.t, st.contacts[1], static=True)
        rows.append(
            (
                st.t,
                float(np.linalg.norm(rep.force[0])),
                float(rep.normal[0]),
                float(rep.tangential[0]),
                float(rep.contacts[0]),
                float(rep.depth[0]),
            )
        )
        iters.append(n_it)
        return rep

    record(state, its0)
    if progress is not None:
        progress(1.0 / (steps + 1))
    previous = state
    for k in range(1, steps + 1):
        # Equal increments: Newton starts from the last two rests extrapolated.
        guess = extrapolated(state.x, previous.x) if k > 1 else None
        previous = state
        state, n_it, h = _solve(scene, state, t0 + k * inc, cache, hint, guess)
        halvings += int(h > 0)
        rep = record(state, n_it)
        if rep.contacts[0] == 0:
            raise ContactError(
                f"the fingertip lost contact at a penetration of {k * inc * 1e3:.3g} mm: its contact "
                f"depth reached its radius {radius * 1e3:.3g} mm; use a smaller depth or a larger fingertip"
            )
        if progress is not None:
            progress((k + 1) / (steps + 1))

    a = np.array(rows)
    travel = a[:, 0]
    force = a[:, 1]
    return IndentationResult(
        time_s=travel / speed,
        travel_m=travel,
        penetration_m=travel - t0,
        force_N=force,
        normal_force_N=a[:, 2],
        tangential_force_N=a[:, 3],
        contacts=a[:, 4].astype(np.int64),
        contact_depth_m=a[:, 5],
        newton_iterations=np.array(iters, dtype=np.int64),
        first_contact_travel_m=t0,
        depth_m=float(depth),
        speed_m_s=float(speed),
        peak_force_N=float(force.max()),
        K_N_m1_5=K,
        fingertip=Fingertip(
            radius,
            centre=centre,
            velocity=np.array([0.0, 0.0, -speed]),
            E=fingertip_E,
            nu=fingertip_nu,
            name="finger",
        ),
        params=params,
        table_mu=float(table_mu),
        point_m=xy,
        point_shift_m=shift,
        surface_z_m=zs,
        settle_sag_m=sag,
        turned=turned,
        halvings=halvings,
        wall_time_s=time.perf_counter() - t_start,
        final_positions_m=state.x,
    )


# ---------------------------------------------------------------------- measured curves
_PENETRATION_UNITS = {"penetration_m": 1.0, "penetration_mm": 1e-3}


def read_force_curve(
    path: str | Path, *, max_penetration: float | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Read a measured force-penetration curve from a CSV file.

    The file needs a header row naming a penetration column, ``penetration_m`` [m] or
    ``penetration_mm`` [mm] (converted to m), and ``force_N`` [N]; other columns are ignored, blank
    lines and lines starting with ``#`` are skipped. At least two rows of finite numbers are needed.

    Parameters
    ----------
    path: the CSV file.
    max_penetration: largest penetration the simulation reaches [m]; a measured penetration
        outside ``[0, max_penetration]`` is an error (the simulated force is not extrapolated).

    Returns
    -------
    (penetration [m], force [N]), each (P,), in file order.

    Raises
    ------
    ConfigError: the file is missing or unreadable, has the wrong columns, a value that is not a
        finite number (the message names the line), fewer than two rows, or a penetration outside
        the simulated range.
    """
    table = read_table(path)
    found = table.unit_column(_PENETRATION_UNITS)
    if found is None or not table.has("force_N"):
        raise ConfigError(
            f"measured data file {table.name!r}: header (line {table.header_line}) "
            f"must name the columns penetration_m (or penetration_mm) and force_N, got "
            f"{','.join(table.columns)!r}"
        )
    P = table.values(*found)
    force = table.values("force_N")
    name = table.name
    if max_penetration is not None:
        tol = 1e-9 * max(max_penetration, 1e-3)
        out = np.flatnonzero((P < -tol) | (P > max_penetration + tol))
        if out.size:
            k = int(out[0])
            raise ConfigError(
                f"measured data file {name!r}, line {table.line_of(k)}: penetration {P[k] * 1e3:.4g} mm "
                f"is outside the simulated range 0..{max_penetration * 1e3:.4g} mm; raise --depth or "
                "trim the data"
            )
    return P, force


def mean_abs_force_error(
    result: IndentationResult, penetration_m: NDArray[np.float64], force_N: NDArray[np.float64]
) -> float:
    """Mean absolute difference [N] between the simulated force, linearly interpolated at the
    measured penetrations [m], and the measured forces [N] (the paper's 0.3 N figure of merit)."""
    sim = np.interp(penetration_m, result.penetration_m, result.force_N)
    return float(np.mean(np.abs(sim - np.asarray(force_N))))
