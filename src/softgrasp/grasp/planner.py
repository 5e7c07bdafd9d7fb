"""The closing simulation (paper step 2, Sec. 2 and 4.3.2): from the initial grasp, the three
fingertips advance together in small increments along straight lines towards the centroid of the
contact triangle; after each increment the object comes to rest; the first increment at which the
fingers hold the object against gravity stops the closing, and the forces of the *held* state
(table removed) become the force set-points.

Per increment: the object, standing on the table, is brought to static equilibrium with its
fingertip contacts (quasi-static: :func:`softgrasp.sim.static.solve_increment`; dynamic: explicit
RK4 through the increment at the closing speed, then that static solve). Then the grasp test of
Sec. 3.5 (Eq. 21-22 with friction cones, :func:`squeeze_utilisation`): can normal forces no larger
than each finger's current one, with friction inside the cones |f_t| <= mu f_n, hold
``safety_factor`` times the weight in force and torque? (On the table the fingers' normal forces
need not balance among themselves; lifted, the object shifts until they do.) When it can, the last
step is bisected ``refine`` times on that test, and the hold is verified once at the smallest
travel that passes it: with the fingertips fixed, the table's support is taken away in a few
static load steps (the weight passes to the fingers quasi-statically, as in a slow lift), then
``hold_time`` seconds of implicit (backward Euler) dynamics must keep the centre of mass within
``max_drift`` of where it stood on the table, and a static solve in the fingers alone must find
the held state within ``max_drift`` too, every fingertip sticking. A failed verification
continues the closing from there, by step / 2^refine at first and by doubling amounts up to a
whole step, with a verification after each. Past
``max_squeeze`` (a fraction of the shortest finger-to-centroid distance, travelled beyond the last
finger's first contact) the object would be crushed: :class:`InfeasibleGrasp`.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull, QhullError

from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.fingertip.laws import effective_modulus
from softgrasp.physics.fingertip.contact import FingerReport, FingertipContact
from softgrasp.physics.resting import lowered_onto_table
from softgrasp.errors import ConfigError, InfeasibleGrasp, NotConverged, SimulationUnstable
from softgrasp.grasp.equilibrium import minimum_normal_forces, squeeze_utilisation
from softgrasp.grasp.initial import FINGER_NAMES, HandLayout, InitialGrasp, ranked_grasps
from softgrasp.hand.kinematics import HandModel
from softgrasp.hand.placement import HandPlacement, closing_paths, place_hand
from softgrasp.model.mesh.placement import stable_facet_pose
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.linalg import pardiso
from softgrasp.sim.implicit import implicit_euler_step
from softgrasp.sim.explicit import simulate
from softgrasp.linalg.solve import SolverCache, by_multigrid
from softgrasp.sim.loads import RampedLoad
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import extrapolated, solve_increment, solve_static

__all__ = [
    "PlanConfig",
    "FingerResult",
    "GraspPlan",
    "PlanFrames",
    "ClosingSetup",
    "closing_setup",
    "plan_grasp",
]

SOLVERS = ("quasistatic", "dynamic")
#: First time step of the implicit holding simulation [s].
HOLD_DT = 0.05
#: Halvings of the holding simulation's step allowed when a step's Newton solve fails.
MAX_HALVINGS = 6
#: Closing steps the fingertips start back from tangency with the object: first contact falls
#: in the middle of the second increment, never on an increment's end. (Backed off one whole step,
#: every fingertip was tangent to the surface at the first increment's end, and whether its
#: facets counted as touching there, to be anchored at the unloaded surface, was decided by
#: round-off: the default plan's set-points took one of several values 1-4 % apart.)
START_BACKOFF = 1.5
#: Initial-grasp shapes the planner tries to reach with the hand before giving up.
MAX_PLACEMENTS = 12
#: Failed placements after which the planner stops trying a spread angle of the layout.
PER_SPREAD = 1
#: Centre-of-mass motion per holding step below which the step is doubled [m].
SETTLED = 1e-6
#: Static load steps in which the table's support is taken away before the holding simulation.
RELEASE_STEPS = 4
#: A fingertip counts as sliding when its resultant friction uses this close to all of its cone.
STICK_TOLERANCE = 1e-3
#: Relative tolerance of the settle on the table (the largest unbalanced nodal force over the
#: largest force present): the static solver's stall tolerance
#: (:data:`~softgrasp.sim.static.STALL_RTOL`), which a rest on a nearly neutral mode may end at
#: anyway. Against 1e-9 (the settle and, then, the closing increments): the default plan's
#: set-points the same to eight digits or more from 2 196 to 33 969 nodes (0.2 % on one finger
#: at 27 749 nodes, where the settled ball was solved again along its nearly neutral rolling
#: mode). A looser settle only moves its Newton iterations into the closing (1e-4: 40 -> 108
#: systems at 2 196 nodes, the ball still rolling when the fingers close).
PATH_RTOL = 1e-6
#: Relative tolerance of the held state the set-points come from (and of the last release step,
#: where the holding simulation starts): :func:`~softgrasp.sim.static.solve_static`'s default.
HELD_RTOL = 1e-9
#: Relative tolerance of the load steps on the way to the held state: the closing increments
#: (whole, bisected, or closing further after a failed hold check) and the hold check's release
#: steps but the last (the largest unbalanced nodal force over the largest force present; a
#: friction pass may end at up to ten times it). These rests carry the friction history to the
#: next step (which pairs stick, where they are anchored), the per-step forces the plan reports
#: (history, frames) and the grasp test that decides where the closing stops; the set-points come
#: from the held state, solved to :data:`HELD_RTOL`. At 1e-4 most steps end a Newton iteration
#: earlier. Against ``PATH_RTOL`` for the closing and ``HELD_RTOL`` for the release (the default
#: plan): 40 -> 33 Newton systems at 2 196 nodes, 41 -> 34 at 7 576, 38 -> 31 at 27 749 (575 -> 445
#: V-cycles), 40 -> 34 at 32 543 (616 -> 515); the set-points moved by at most 6e-6 of themselves
#: and the reported per-step forces by 3e-5, far below their change between those meshes (~2 %);
#: the grasp test's value moved by ~2e-5 (a test that close to its threshold could flip and move
#: the final travel by a refined step). The closing at 1e-3 saved one system more and moved them
#: alike; the last release step at 1e-4 too made the hold's implicit dynamics start unbalanced
#: (7 576 nodes: 51 systems in the hold check instead of 10). Force control's
#: :func:`~softgrasp.grasp.force_control.hold_setpoints` checks its hold with the same release.
STEP_RTOL = 1e-4
#: Newton iterations a friction pass of the settle's lowered start (:func:`_settle`) is given
#: before the level start takes over (the settles measured ended in one pass): the lowered starts
#: measured settled in 3-24 iterations; one that wanders (33 969 nodes lowered 1.2x as far: no
#: rest in 60) then costs half as much.
LOWERED_MAX_ITER = 30
#: The least node count for which the settle starts lowered (and only where its systems go to
#: multigrid). Measured below it with the multigrid path forced: the 4 498-node sphere 41 -> 19
#: systems, the 2 465-node one 47 -> 77 (no rest lowered within the limit, then level); on
#: PARDISO's exact path 4 498 nodes 16 -> 18, 7 576 17 -> 12 and a zig-zag at 18 233 nodes.
LOWERED_MIN_NODES = 10_000


@dataclass(frozen=True)
class PlanConfig:
    """Everything the planner uses besides the object.

    Attributes
    ----------
    contact: fingertip contact parameters (friction mu, exponent, K prefactor, rule ...).
    fingertip_radius: R of the three fingertips [m] (Shadow-hand-like: 8 mm).
    step: closing increment of each fingertip [m] (paper: small increments; 0.5 mm).
    solver: ``quasistatic`` (static equilibrium per increment) or ``dynamic`` (the paper's
        explicit Runge-Kutta through each increment at ``closing_speed``, then static settling).
    closing_speed: fingertip speed of the dynamic solver [m/s].
    safety_factor: the grasp test must hold this multiple of the weight (>= 1).
    hold_time: simulated holding time of the verification [s].
    max_drift: largest centre-of-mass motion over ``hold_time`` for a hold [m].
    max_squeeze: largest travel past the last finger's first contact, as a fraction of the
        shortest finger-to-centroid distance (beyond it the object is crushed).
    refine: bisections of the last closing step for the smallest travel that passes the grasp test
        (the set-points then resolve step / 2^refine: stiff objects gain force fast).
    table_mu: friction between object and table.
    layout: the search grid and coarse reach limits of the initial grasp (:class:`HandLayout`).
    hand: the hand's kinematic model (default: the packaged Shadow-like hand); the initial grasp
        must be reachable by it and its fingertips must follow the closing lines. ``None`` plans
        for free fingertips (the layout alone limits the grasp).
    grasp: an initial grasp to close from instead of searching for one (the contacts of an
        earlier plan: the same closing lines for another material or friction); ``None``: search.
    """

    contact: ContactParams = field(default_factory=ContactParams)
    fingertip_radius: float = 0.008
    step: float = 0.0005
    solver: str = "quasistatic"
    closing_speed: float = 0.05
    safety_factor: float = 1.0
    hold_time: float = 1.0
    max_drift: float = 0.001
    max_squeeze: float = 0.5
    refine: int = 3
    table_mu: float = 0.5
    layout: HandLayout = field(default_factory=HandLayout)
    hand: HandModel | None = field(default_factory=HandModel.default)
    grasp: InitialGrasp | None = None

    def __post_init__(self) -> None:
        checks = {
            "fingertip_radius": self.fingertip_radius > 0,
            "step": self.step > 0,
            "closing_speed": self.closing_speed > 0,
            "safety_factor": self.safety_factor >= 1.0,
            "hold_time": self.hold_time >= 0,
            "max_drift": self.max_drift > 0,
            "max_squeeze": 0 < self.max_squeeze < 1,
            "table_mu": self.table_mu >= 0,
            "refine": 0 <= self.refine <= 10,
        }
        for name, ok in checks.items():
            v = getattr(self, name)
            if not (ok and math.isfinite(v)):
                raise ConfigError(f"plan parameter {name} = {v} is invalid")
        if self.solver not in SOLVERS:
            raise ConfigError(f"solver must be one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if self.hand is not None:
            for finger in FINGER_NAMES:
                r = self.hand.fingertip_radius(finger)
                if abs(r - self.fingertip_radius) > 1e-9:
                    raise ConfigError(
                        f"fingertip radius {self.fingertip_radius * 1e3:g} mm differs from the hand's "
                        f"{finger} fingertip ({r * 1e3:g} mm in {self.hand.source}); plan with the hand's "
                        "radius, a URDF with the radius wanted, or no hand (--hand none)"
                    )
        if self.step >= self.fingertip_radius:
            raise ConfigError(
                f"closing step {self.step * 1e3:g} mm must be smaller than the fingertip radius "
                f"{self.fingertip_radius * 1e3:g} mm"
            )

    def describe(self) -> dict[str, object]:
        return {
            "contact": self.contact.describe(),
            "fingertip_radius_m": self.fingertip_radius,
            "step_m": self.step,
            "solver": self.solver,
            "closing_speed_m_s": self.closing_speed,
            "safety_factor": self.safety_factor,
            "hold_time_s": self.hold_time,
            "max_drift_m": self.max_drift,
            "max_squeeze": self.max_squeeze,
            "refine": self.refine,
            "table_mu": self.table_mu,
            "hand_layout": self.layout.describe(),
            "hand": None if self.hand is None else self.hand.source,
            "grasp": "given" if self.grasp is not None else "searched",
        }


@dataclass(frozen=True)
class FingerResult:
    """One finger's set-point in the held state (forces on the object)."""

    name: str
    initial_contact: NDArray[np.float64]
    final_position: NDArray[np.float64]
    penetration: float
    force: NDArray[np.float64]
    normal_force: float
    tangential_force: float

    @property
    def force_norm(self) -> float:
        return float(np.linalg.norm(self.force))


@dataclass(frozen=True)
class GraspPlan:
    """The planned grasp.

    Attributes
    ----------
    initial: the initial grasp (step 1).
    fingers: set-points of thumb, first and middle fingers in the held state.
    force_residual, torque_residual: |Eq. 21| [N] and |Eq. 22| about the centre of mass [N m] of
        the held state (finger forces and weight).
    friction_margin: 1 - the largest ratio |f_t| / (mu f_n) among the fingers in the held state,
        with each finger's resultant friction and normal forces: the share of its Coulomb cone
        left (> 0: every fingertip sticks; rim pairs of a contact patch may slip).
    com_drift: centre-of-mass motion from the release over the holding time, or to the held
        state if that is farther [m]; hold_time: that time [s].
    increments: closing increments simulated (the bisection's included).
    travel: fingertip travel at each increment [m], (K,), increasing (the bisection's increments
        sorted in among the regular ones).
    penetration, force_norm, normal_force, tangential_force: per increment and finger, (K, 3).
    feasible: whether the grasp test passed at each increment, (K,).
    rigid_normal_forces: the normal forces of smallest sum that hold the object at the held
        contact points and directions if it were rigid [N], (3,).
    rigid_utilisation: the smallest fraction of the held normal forces that would still hold the
        object if it were rigid (<= 1: they suffice; 1/3: three times what is needed).
    positions: node positions of the held state [m], (N, 3).
    centres: final fingertip centres [m], (3, 3).
    contact_points: each finger's mean contact point in the held state [m], (3, 3).
    com: centre of mass in the held state [m].
    first_contact_travel: travel at which each finger touched [m], (3,).
    placed: the unloaded object as placed on the table [m], (N, 3): the mesh as given, or turned
        onto a stable facet when it could not rest as given.
    start_centres: fingertip centres where the closing starts [m], (3, 3).
    placement: the hand's palm pose and joints at the start (None without a hand model).
    joint_paths: per finger, the joint vectors moving its fingertip along its closing line from
        the start to the final centre, one row per ``step`` of travel and the start,
        (ceil(travel / step) + 1, dof) (None without a hand model).
    config: the configuration used.  wall_time: seconds.
    hold_checks: every hold verification, in order: (travel [m], "held" or why the object was not
        held there: how far it moved during the release or the hold, which finger slid, or the
        solve that failed), so that a user can see what made the fingers close further.
    frames: the object and the fingertips at rest at the start of the closing (travel 0) and after
        each closing increment, in the order of travel (what ``softgrasp view`` animates).
    solver_stats: what the plan's linear algebra did (:attr:`SolverCache.stats
        <softgrasp.linalg.solve.SolverCache>`): Newton systems, factorisations, multigrid V-cycles
        ... (machine-independent measures of its cost); the Newton systems also by phase:
        ``settle_systems`` (the object coming to rest on the table), ``closing_systems`` (the
        closing increments and their refinement) and ``hold_check_systems`` (the table removed,
        the release, the holding simulation and the held equilibrium).
    """

    initial: InitialGrasp
    fingers: tuple[FingerResult, ...]
    force_residual: float
    torque_residual: float
    friction_margin: float
    com_drift: float
    hold_time: float
    increments: int
    travel: NDArray[np.float64]
    penetration: NDArray[np.float64]
    force_norm: NDArray[np.float64]
    normal_force: NDArray[np.float64]
    tangential_force: NDArray[np.float64]
    feasible: NDArray[np.bool_]
    rigid_normal_forces: NDArray[np.float64]
    rigid_utilisation: float
    positions: NDArray[np.float64]
    centres: NDArray[np.float64]
    contact_points: NDArray[np.float64]
    com: NDArray[np.float64]
    first_contact_travel: NDArray[np.float64]
    placed: NDArray[np.float64]
    start_centres: NDArray[np.float64]
    placement: HandPlacement | None
    joint_paths: dict[str, NDArray[np.float64]] | None
    config: PlanConfig
    wall_time: float
    hold_checks: tuple[tuple[float, str], ...] = ()
    frames: PlanFrames | None = None
    solver_stats: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class PlanFrames:
    """The closing at rest: the start (travel 0) and each increment, sorted by travel.

    Attributes
    ----------
    travel: fingertip travel [m], (K,).
    positions: node positions [m], (K, N, 3).
    centres: fingertip centres [m], (K, 3, 3).
    forces: force of each fingertip on the object [N], (K, 3, 3).
    """

    travel: NDArray[np.float64]
    positions: NDArray[np.float64]
    centres: NDArray[np.float64]
    forces: NDArray[np.float64]


def _com(body: Body, x: NDArray[np.float64]) -> NDArray[np.float64]:
    return (body.mass @ x) / body.total_mass


def _first_touch(body: Body, params: ContactParams, tip: Fingertip, x, t_max: float) -> float:
    """Travel at which ``tip`` (moving along its velocity) first touches the surface ``x``."""

    def touches(t: float) -> bool:
        fc = FingertipContact((tip,), params)
        return len(fc.pairs(body, x, t)) > 0

    grid = np.linspace(0.0, t_max, 41)
    hit = next((k for k, t in enumerate(grid) if touches(float(t))), None)
    if hit is None:
        raise InfeasibleGrasp(
            f"the {tip.name} fingertip never touches the object along its closing line "
            f"({t_max * 1e3:.1f} mm of travel); the initial grasp is not reachable"
        )
    if hit == 0:
        return 0.0
    lo, hi = float(grid[hit - 1]), float(grid[hit])
    while hi - lo > 1e-9:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if touches(mid) else (mid, hi)
    return hi


def _torque_residual(rep: FingerReport, centres, com) -> NDArray[np.float64]:
    """Sum of the fingers' moments about the centre of mass (the weight has none there)."""
    return (rep.moment + np.cross(centres - com, rep.force)).sum(axis=0)


def _hold(
    body: Body,
    scene: Scene,
    state: State,
    duration: float,
    cache: SolverCache,
    max_drift: float = np.inf,
    origin: NDArray[np.float64] | None = None,
) -> State | None:
    """``duration`` seconds of backward Euler from ``state``: steps of ``HOLD_DT``, doubled after
    every step in which the centre of mass moved less than ``SETTLED`` (the object has come to
    rest: larger steps then cost nothing in accuracy). None as soon as the centre of mass has
    moved ``max_drift`` from ``origin`` (default: where it starts; the object is not held: no need
    to simulate on)."""
    dt = HOLD_DT
    c0 = _com(body, state.x) if origin is None else origin
    while state.t < duration - 1e-12:
        h = min(dt, duration - state.t)
        before = _com(body, state.x)
        try:
            state = implicit_euler_step(scene, state, h, cache=cache)
        except NotConverged:
            if h <= HOLD_DT / 2**MAX_HALVINGS:
                raise
            dt = h / 2.0  # a sudden slip or release: resolve it in shorter steps
            continue
        c = _com(body, state.x)
        if np.linalg.norm(c - c0) >= max_drift:
            return None
        if np.linalg.norm(c - before) < SETTLED:
            dt *= 2.0
    return state


def _table(x: NDArray[np.float64], mu: float) -> PlaneContact:
    """The table: the horizontal plane under the lowest node of ``x``."""
    zmin = float(x[:, 2].min())
    return PlaneContact(Plane(np.array([0.0, 0.0, zmin]), np.array([0.0, 0.0, 1.0])), mu=mu, name="table")


def _stable_pose(body: Body, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``x`` turned onto its most stable hull facet about its centre of mass
    (:func:`softgrasp.model.mesh.placement.stable_facet_pose`)."""
    return stable_facet_pose(x, _com(body, x))


def _lowest(x: NDArray[np.float64]) -> NDArray[np.bool_]:
    """The nodes of ``x`` at its lowest height (to 1e-9 of its size): those touching a table
    under it."""
    return x[:, 2] <= x[:, 2].min() + 1e-9 * float(np.ptp(x, axis=0).max())


def _stands(x: NDArray[np.float64], com: NDArray[np.float64]) -> bool:
    """Whether ``x`` stands on the table as it is: the centre of mass lies above the convex hull
    of its lowest nodes (not balanced on a vertex or an edge, which only tips over)."""
    L = float(np.ptp(x, axis=0).max())
    low = x[_lowest(x), :2]
    if len(low) < 3:
        return False
    try:
        hull = ConvexHull(low)
    except QhullError:
        return False  # collinear: an edge
    return bool((hull.equations[:, :2] @ com[:2] + hull.equations[:, 2] <= 1e-12 * L).all())


def _lowered(body: Body, x: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Where the settle's Newton starts: ``x`` lowered by half the approach its weight presses it
    into the table (:func:`softgrasp.physics.resting.lowered_onto_table`), the nodes of the
    predicted contact patch touching from the start; ``None`` (start as placed) where gravity
    does not press the body onto the table, or where the patch is no more than the nodes that
    touch as placed (a flat face down: lowered, the foam cube's settle took 3 systems, level 2)."""
    weight = -float(body.mass.sum() * body.gravity[2])
    if not weight > 0.0:
        return None
    modulus = effective_modulus(math.inf, 0.0, body.material.E, body.material.nu)  # a rigid table
    lowered = lowered_onto_table(x, body.mesh.facets, weight, modulus)
    pressed_in = int((lowered[:, 2] < x[:, 2].min()).sum())
    return lowered if pressed_in > int(_lowest(x).sum()) else None


def _settle(body: Body, cfg: PlanConfig, cache: SolverCache) -> tuple[State, PlaneContact, NDArray]:
    """The object at rest on the table, and the table. As the mesh stands if its centre of mass is
    above its lowest nodes' hull and a rest is found there; otherwise (a convex mesh balanced on
    one node tips over: Newton creeps along the nearly free tipping mode), standing on its most
    stable hull facet, as a real object comes to rest.

    For bodies of :data:`LOWERED_MIN_NODES` nodes or more whose Newton systems go to multigrid
    (:func:`~softgrasp.linalg.solve.by_multigrid`, the default there), Newton first starts each
    placement lowered by half the approach its weight presses it into the table (:func:`_lowered`):
    the nodes of the predicted contact patch touch from the first iterate, anchored for friction
    where they stand, as when the object is set straight down; then, if that finds no rest within
    :data:`LOWERED_MAX_ITER` iterations (a friction pass), level with the table; the linear solver's
    state is dropped between starts. Settles of spheres, level -> lowered Newton systems: 15 662
    nodes 23 -> 15, 18 233 (on its facet) 9 -> 6, 27 749 13 -> 12, 31 029 13 -> 3, 32 543 15 -> 7,
    33 969 28 -> 22; but 11 874 nodes, whose as-meshed placement cycles across a contact kink from
    either start, 53 -> 69 (the lowered start's 22 iterations before the level start's 33, then 17
    instead of 22 on the facet). Smaller bodies and PARDISO's exact solves start level (measured:
    :data:`LOWERED_MIN_NODES`); the 18 233-node sphere forced onto PARDISO settled lowered in 15-17
    systems or not at all, against 9 level, its iterates zig-zagging along the nearly neutral
    rolling mode.
    Returns (the rest state, the table, the unloaded placement the rest was found from)."""
    lowers = body.n_nodes >= LOWERED_MIN_NODES and by_multigrid(3 * body.n_nodes, cache)

    def starts() -> Iterable[tuple[str, NDArray[np.float64], NDArray[np.float64] | None]]:
        x = np.asarray(body.mesh.points, dtype=np.float64)
        for where, placed in (("as meshed", x), ("on its most stable facet", None)):
            if placed is None:
                placed = _stable_pose(body, x)
            elif not _stands(x, _com(body, x)):
                continue
            guess = _lowered(body, placed) if lowers else None
            if guess is not None:
                yield f"{where}, lowered", placed, guess
            yield where, placed, None

    failures = []
    for where, x, guess in starts():
        if failures:
            cache.scene_changed()  # the failed start's factor or hierarchy is no guide here
        table = _table(x, cfg.table_mu)
        rest = Scene(body, (table,))
        limit = {} if guess is None else {"guess": guess, "max_iter": LOWERED_MAX_ITER}
        try:
            state = solve_static(rest, rest.initial_state(x), cache=cache, rtol=PATH_RTOL, **limit)[0]
            return state, table, x
        except NotConverged as exc:
            failures.append((where, exc))
    raise NotConverged(
        "the object found no rest on the table: " + "; ".join(f"{where}: {exc}" for where, exc in failures)
    ) from failures[-1][1]


def _start_centres(ig: InitialGrasp, cfg: PlanConfig) -> tuple[NDArray, NDArray, NDArray]:
    """Fingertip centres where the closing starts: tangent to the surface at each contact point,
    backed off ``START_BACKOFF`` steps along the closing line; the unit closing directions
    (towards the contact triangle's centroid) and each contact's distance to that centroid."""
    u = ig.centroid[None, :] - ig.points
    reach = np.linalg.norm(u, axis=1)
    u = u / reach[:, None]
    return ig.points + cfg.fingertip_radius * ig.normals - START_BACKOFF * cfg.step * u, u, reach


def _hand_order(hand: HandModel, ig: InitialGrasp) -> InitialGrasp:
    """``ig`` with the first and middle fingers' contacts swapped if the hand needs them the other
    way round. Seen in a grasp from above (palm y from the thumb's contact to the fingers', palm
    normal down), the finger whose knuckle lies farther along the palm's x axis takes the contact
    farther along that axis: the fingers do not cross."""
    up = np.array([0.0, 0.0, 1.0])
    y = ig.points[1:].mean(axis=0) - ig.points[0]
    y -= (y @ up) * up
    x_axis = np.cross(y, -up)
    knuckle = {f: hand.link_points(f, 0.5 * np.add(*hand.limits(f)))[0][0] for f in FINGER_NAMES[1:]}
    want = knuckle["first"] > knuckle["middle"]
    have = (ig.points[1] - ig.points[0]) @ x_axis > (ig.points[2] - ig.points[0]) @ x_axis
    if want == have:
        return ig
    k = [0, 2, 1]
    return replace(ig, points=ig.points[k], normals=ig.normals[k], facets=ig.facets[k])


def _reachable_grasp(
    xs: NDArray[np.float64],
    candidates: Iterable[InitialGrasp],
    cfg: PlanConfig,
    failures: dict[float, int] | None = None,
) -> tuple[InitialGrasp, HandPlacement | None]:
    """The best initial grasp the hand reaches, and the hand's placement for it. Candidates come
    best first; a spread angle (the layout's shape parameter) that failed ``PER_SPREAD`` times is
    skipped (on a near-symmetric object its other azimuths fail alike), and at most
    ``MAX_PLACEMENTS`` placements are tried. ``failures`` (failed placements per spread angle) is
    filled in as it goes, so that the ranking can leave out what will be skipped
    (:func:`_spread_failed`)."""
    if cfg.hand is None:
        return next(iter(candidates)), None
    failures = {} if failures is None else failures
    first_error: InfeasibleGrasp | None = None
    tried = 0
    for cand in candidates:
        if _spread_failed(failures, cand.thumb_azimuth, cand.spread):
            continue
        if tried >= MAX_PLACEMENTS:
            break
        tried += 1
        ig = _hand_order(cfg.hand, cand)
        start, _, _ = _start_centres(ig, cfg)
        try:
            placement = place_hand(cfg.hand, dict(zip(FINGER_NAMES, start, strict=True)), obstacle=xs)
        except InfeasibleGrasp as exc:
            first_error = first_error or exc
            failures[cand.spread] = failures.get(cand.spread, 0) + 1
            continue
        return ig, placement
    if cfg.grasp is not None:
        raise InfeasibleGrasp(f"the hand does not reach the given grasp: {first_error}")
    raise InfeasibleGrasp(
        f"the hand reaches none of the {tried} best force-closure grasps tried; the best one: {first_error}"
    )


def _spread_failed(failures: dict[float, int], theta: float, spread: float) -> bool:
    """Whether :func:`_reachable_grasp` skips grasps of this spread angle now (the ranking then
    need not compute their quality)."""
    return failures.get(spread, 0) >= PER_SPREAD


def _initial_grasp(
    body: Body, xs: NDArray[np.float64], com: NDArray[np.float64], cfg: PlanConfig
) -> tuple[InitialGrasp, HandPlacement | None]:
    """The initial grasp (the best reachable force-closure grasp, or ``cfg.grasp``) and the
    hand's placement for it."""
    if cfg.grasp is None:
        failures: dict[float, int] = {}
        skip = functools.partial(_spread_failed, failures)
        ranked = ranked_grasps(xs, body.mesh.facets, com, cfg.contact.mu, cfg.layout, skip=skip)
        return _reachable_grasp(xs, ranked, cfg, failures)
    ig = cfg.grasp
    R = cfg.fingertip_radius  # a fingertip resting at each contact touches the surface near it
    probe = FingertipContact(
        tuple(Fingertip(R, centre=p + 0.5 * R * n) for p, n in zip(ig.points, ig.normals, strict=True)),
        cfg.contact,
    )
    near = np.bincount(probe.pairs(body, xs, 0.0).finger, minlength=3)
    if near.min() == 0:
        j = int(np.argmin(near))
        raise InfeasibleGrasp(
            f"the given grasp's {FINGER_NAMES[j]} contact {np.round(ig.points[j] * 1e3, 2).tolist()} mm lies "
            f"more than {cfg.fingertip_radius / 2 * 1e3:g} mm off this object's surface: that grasp was "
            "planned for another object, mesh or placement"
        )
    return _reachable_grasp(xs, [ig], cfg)


@dataclass(frozen=True)
class ClosingSetup:
    """Where a closing starts: the object at rest on the table, the initial grasp, the hand's
    placement for it and the fingertips' closing lines.

    Attributes
    ----------
    settled: the object at rest on the table (no fingers).  table: the table.
    placed: the unloaded object as placed on the table [m], (N, 3).
    grasp: the initial grasp.  placement: the hand's placement (None without a hand model).
    start: fingertip centres where the closing starts [m], (3, 3).
    directions: unit closing directions (towards the contact triangle's centroid), (3, 3).
    reach: each contact's distance to that centroid [m], (3,).
    first_touch: travel along its line at which each fingertip first touches the object [m], (3,).
    max_squeeze: the configuration's ``max_squeeze``.
    """

    settled: State
    table: PlaneContact
    placed: NDArray[np.float64]
    grasp: InitialGrasp
    placement: HandPlacement | None
    start: NDArray[np.float64]
    directions: NDArray[np.float64]
    reach: NDArray[np.float64]
    first_touch: NDArray[np.float64]
    max_squeeze: float

    @property
    def max_travel(self) -> float:
        """Farthest travel of a fingertip along its line before the object counts as crushed [m]
        (``max_squeeze`` of the shortest reach past the last finger's first contact)."""
        return float(self.first_touch.max() + self.max_squeeze * self.reach.min())


def closing_setup(body: Body, cfg: PlanConfig, cache: SolverCache | None = None) -> ClosingSetup:
    """Settle ``body`` on the table, choose (or take ``cfg.grasp``) the initial grasp the hand
    reaches, and lay the fingertips' closing lines (paper step 1)."""
    cache = cache if cache is not None else SolverCache()
    before = cache.stats["systems"]
    settled, table, placed = _settle(body, cfg, cache)
    cache.stats["settle_systems"] = cache.stats["systems"] - before
    xs = settled.x
    ig, placement = _initial_grasp(body, xs, _com(body, xs), cfg)
    start, u, reach = _start_centres(ig, cfg)
    R = cfg.fingertip_radius
    first = np.array(
        [
            _first_touch(
                body,
                cfg.contact,
                Fingertip(R, centre=start[j], velocity=u[j], name=FINGER_NAMES[j]),
                xs,
                4 * cfg.step + R,
            )
            for j in range(3)
        ]
    )
    return ClosingSetup(settled, table, placed, ig, placement, start, u, reach, first, cfg.max_squeeze)


def _check_hold(
    body: Body,
    table: PlaneContact,
    fc: FingertipContact,
    state: State,
    t: float,
    cfg: PlanConfig,
    cache: SolverCache,
) -> tuple[State, FingertipContact, float] | str:
    """Remove the table and verify that the fingers hold the object. From the squeezed state at
    rest on the table, with the fingertips fixed: the table's forces on the object, applied as a
    dead load, ramp down to zero over ``RELEASE_STEPS`` static load steps (the weight passes to the
    fingers quasi-statically, as in a slow lift, friction sticking or slipping pair by pair); then
    ``hold_time`` seconds of implicit dynamics (:func:`_hold`) from that released state must keep
    the centre of mass within ``max_drift`` of where it was on the table; the held state is then
    brought to static equilibrium in the fingers alone. Returns (held state, fixed fingers, drift)
    or, when the object is not held, why not (a sentence)."""
    fixed = FingertipContact(
        tuple(replace(f, centre=f.centre_at(t), velocity=np.zeros(3)) for f in fc.fingertips),
        fc.params,
        name=fc.name,
    )
    support = RampedLoad(table.static_forces(body, state.x, t, state.contacts[0]), state.x, name="support")
    release = Scene(body, (fixed, support))
    scene = Scene(body, (fixed,))
    c0 = _com(body, state.x)
    try:
        st = State(state.x, np.zeros_like(state.x), 0.0, (state.contacts[1], None))
        cache.scene_changed()  # the table's stiffness is gone from the Newton matrices
        prev = None
        for k in range(1, RELEASE_STEPS + 1):
            # Newton starts from the last two steps' positions extrapolated (the support falls by
            # equal parts: a nearly linear response), one iteration fewer than from the last.
            guess = None if prev is None else extrapolated(st.x, prev)
            prev = st.x
            rtol = STEP_RTOL if k < RELEASE_STEPS else HELD_RTOL  # the last: where the hold starts
            st, _ = solve_static(release, st, t=k / RELEASE_STEPS, cache=cache, guess=guess, rtol=rtol)
            if (d := float(np.linalg.norm(_com(body, st.x) - c0))) >= cfg.max_drift:
                return _moved(d, cfg, f"with the table's support down to {1 - k / RELEASE_STEPS:.0%}")
        released = float(np.linalg.norm(_com(body, st.x) - c0))
        start = State(st.x, np.zeros_like(st.x), 0.0, (st.contacts[0],))
        end = _hold(body, scene, start, cfg.hold_time, cache, cfg.max_drift, origin=c0)
        if end is None:
            return _moved(cfg.max_drift, cfg, f"during the {cfg.hold_time:g} s hold")
        moved = float(np.linalg.norm(_com(body, end.x) - c0))
        held, _ = solve_static(scene, replace(end, t=0.0), t=0.0, cache=cache, rtol=HELD_RTOL)
    except (NotConverged, SimulationUnstable) as exc:
        return f"the release or the hold found no equilibrium ({exc})"
    drift = max(released, moved, float(np.linalg.norm(_com(body, held.x) - c0)))
    if drift >= cfg.max_drift:
        return _moved(drift, cfg, "at the held equilibrium")
    rep = fixed.report(body, held.x, None, 0.0, held.contacts[0], static=True)
    if rep.contacts.min() == 0:
        return f"the {FINGER_NAMES[int(np.argmin(rep.contacts))]} finger lost contact"
    usage = _cone_usage(rep, cfg.contact.mu)
    if usage.max() >= 1.0 - STICK_TOLERANCE:  # a finger slides: not held
        return f"the {FINGER_NAMES[int(np.argmax(usage))]} finger slides (its friction at the Coulomb limit)"
    return held, fixed, drift


def _moved(drift: float, cfg: PlanConfig, when: str) -> str:
    """Why a hold check failed on the centre of mass's motion."""
    return (
        f"the centre of mass moved {'at least ' if drift <= cfg.max_drift else ''}{drift * 1e3:.2f} mm "
        f"{when} (limit {cfg.max_drift * 1e3:.2f} mm)"
    )


def _cone_usage(rep: FingerReport, mu: float) -> NDArray[np.float64]:
    """Each finger's resultant friction force over mu times its resultant normal force, (3,): 1
    when the whole fingertip slides (every pair at its Coulomb limit, all in one direction), below
    1 when it sticks. Pairs at the rim of a contact patch may slip while the fingertip sticks
    (partial slip, as in Mindlin's contact): they do not make the grasp let go."""
    if mu <= 0:
        return np.ones(len(rep.normal))
    return rep.tangential / np.maximum(mu * rep.normal, 1e-300)


def plan_grasp(
    body: Body,
    config: PlanConfig = PlanConfig(),  # noqa: B008 - frozen dataclass
    *,
    progress: Callable[[float], None] | None = None, cache: SolverCache | None = None,
) -> GraspPlan:
    """Plan a three-finger grasp of ``body`` resting on a table (paper steps 1-2).

    Parameters
    ----------
    body: the object.  config: everything else (:class:`PlanConfig`).
    progress: called with the fraction of the largest allowed travel reached after each increment.
    cache: the linear solves' state (its ``method`` chooses the solver); a fresh one if None.

    Raises
    ------
    InfeasibleGrasp: no reachable force-closure grasp, or no hold before the maximum squeeze.
    NotConverged: an increment found no static equilibrium even when split.
    """
    with pardiso.blas_one_thread():
        return _plan_grasp(body, config, progress, SolverCache() if cache is None else cache)


def _plan_grasp(body: Body, config: PlanConfig, progress: Callable | None, cache: SolverCache) -> GraspPlan:
    t0 = time.perf_counter()
    cfg = config
    mu = cfg.contact.mu
    setup = closing_setup(body, cfg, cache)
    settled, table, placed, xs = setup.settled, setup.table, setup.placed, setup.settled.x
    ig, placement, start, u, first = (
        setup.grasp,
        setup.placement,
        setup.start,
        setup.directions,
        setup.first_touch,
    )
    unit_tips = tuple(
        Fingertip(cfg.fingertip_radius, centre=start[j], velocity=u[j], name=FINGER_NAMES[j])
        for j in range(3)
    )
    # The load parameter of the scene: travel [m] for the quasi-static solver, time [s] at the
    # closing speed for the dynamic one.
    scale = 1.0 if cfg.solver == "quasistatic" else 1.0 / cfg.closing_speed
    tips = tuple(replace(tip, velocity=tip.velocity / scale) for tip in unit_tips)
    fc = FingertipContact(tips, cfg.contact)
    max_travel = setup.max_travel

    scene = Scene(body, (table, fc))
    state = State(xs, np.zeros_like(xs), 0.0, (settled.contacts[0], fc.init_state(body, xs, 0.0)))
    rows: list[tuple[float, NDArray, NDArray, NDArray, NDArray, bool]] = []
    # (travel, x, centres, forces), from the settled object with the fingertips at their start
    frames: list[tuple[float, NDArray, NDArray, NDArray]] = [
        (0.0, xs.copy(), fc.centres(0.0), np.zeros((3, 3)))
    ]
    checks: list[tuple[float, str]] = []  # hold verifications: (travel, "held" or why not)
    k = 0

    def close(start: State, t: float, guess: NDArray | None = None) -> tuple[State, bool]:
        """Close to travel t from ``start``, record the increment and apply the grasp test (the
        squeeze-utilisation LP). Returns (state at rest, whether the test passes)."""
        st = _advance(scene, start, t * scale, cfg, cache, guess)
        rep = fc.report(body, st.x, None, t * scale, st.contacts[1], static=True)
        feasible = False
        if (rep.contacts > 0).all():
            pts, push, fn = fc.contact_frames(body, st.x, t * scale, st.contacts[1])
            s_need = squeeze_utilisation(
                pts, push, fn, mu, _com(body, st.x), cfg.safety_factor * body.total_mass, body.gravity
            )
            feasible = s_need <= 1.0
        rows.append(
            (
                t,
                np.maximum(t - first, 0.0),
                np.linalg.norm(rep.force, axis=1),
                rep.normal.copy(),
                rep.tangential.copy(),
                feasible,
            )
        )
        frames.append((t, st.x.copy(), fc.centres(t * scale), rep.force.copy()))
        if progress is not None:
            progress(min(t / max_travel, 1.0))
        return st, feasible

    def too_far(t: float) -> None:
        if t > max_travel + 1e-12:
            last = rows[-1][2] if rows else np.zeros(3)
            raise InfeasibleGrasp(
                f"no hold before the maximum squeeze ({(max_travel - first.max()) * 1e3:.1f} mm past "
                f"first contact, {cfg.max_squeeze:.0%} of the fingers' reach): finger forces reached "
                f"{', '.join(f'{v:.2f}' for v in last)} N with mu = {mu:g}"
                + (f" (last hold check at {checks[-1][0] * 1e3:.2f} mm: {checks[-1][1]})" if checks else "")
                + "; raise the friction coefficient, or grasp a lighter or stiffer object"
            )

    # 1. Whole steps until the grasp test passes.
    feasible, before, earlier = False, state, state
    while not feasible:
        k += 1
        too_far(k * cfg.step)
        earlier, before = before, state
        # Newton starts from the last two increments' positions extrapolated (equal steps of
        # travel): about one iteration fewer per increment than from the last rest.
        guess = None if k < 2 else extrapolated(before.x, earlier.x)
        state, feasible = close(before, k * cfg.step, guess)
    # 2. Bisect the last step on the grasp test for the smallest travel that passes it (stiff
    # objects gain force fast within one step).
    t_hi = k * cfg.step
    if k > 1:
        lo, lo_state = (k - 1) * cfg.step, before
        for _ in range(cfg.refine):
            mid = 0.5 * (lo + t_hi)
            st, ok = close(lo_state, mid, 0.5 * (lo_state.x + state.x))  # from the bracket's midpoint
            if ok:
                t_hi, state = mid, st
            else:
                lo, lo_state = mid, st
    # 3. Remove the table and verify the hold there (the expensive check: implicit dynamics).
    # Where the object is not held, the fingers close further, by the refined resolution at first
    # and by doubling amounts up to a whole step, until it is.
    t_final, extra = t_hi, cfg.step / 2**cfg.refine

    def check_hold(t: float) -> tuple[State, FingertipContact, float] | str:
        before = cache.stats["systems"]
        out = _check_hold(body, table, fc, state, t, cfg, cache)
        cache.stats["hold_check_systems"] += cache.stats["systems"] - before
        return out

    cache.stats["hold_check_systems"] = 0
    while isinstance(held := check_hold(t_final * scale), str):
        checks.append((t_final, held))
        t_final += extra
        too_far(t_final)
        state, _ = close(state, t_final)
        extra = min(2.0 * extra, cfg.step)

    checks.append((t_final, "held"))
    held_state, fixed, drift = held
    hrep = fixed.report(body, held_state.x, None, 0.0, held_state.contacts[0], static=True)
    pts, push, fn = fixed.contact_frames(body, held_state.x, 0.0, held_state.contacts[0])
    com = _com(body, held_state.x)
    fres = np.linalg.norm(hrep.force.sum(axis=0) + body.total_mass * body.gravity)
    centres = fixed.centres(0.0)
    tres = np.linalg.norm(_torque_residual(hrep, centres, com))
    # The held state's friction forces against the (circular) Coulomb cones, pair by pair.
    margin = float(1.0 - _cone_usage(hrep, mu).max())
    try:
        rigid = minimum_normal_forces(pts, push, mu, com, body.total_mass, body.gravity)
    except InfeasibleGrasp:
        rigid = np.full(3, np.nan)
    utilisation = squeeze_utilisation(pts, push, fn, mu, com, body.total_mass, body.gravity)
    fingers = tuple(
        FingerResult(
            name=FINGER_NAMES[j],
            initial_contact=ig.points[j],
            final_position=centres[j],
            penetration=float(max(t_final - first[j], 0.0)),
            force=hrep.force[j],
            normal_force=float(hrep.normal[j]),
            tangential_force=float(hrep.tangential[j]),
        )
        for j in range(3)
    )
    joint_paths = None
    if placement is not None:
        assert cfg.hand is not None
        lines = {f.name: (start[j], centres[j]) for j, f in enumerate(fingers)}
        joint_paths = closing_paths(cfg.hand, placement, lines, max(1, int(np.ceil(t_final / cfg.step))))
    if progress is not None:
        progress(1.0)
    rows.sort(key=lambda r: r[0])  # the bisection's increments among the others, by travel
    frames.sort(key=lambda f: f[0])
    return GraspPlan(
        initial=ig,
        fingers=fingers,
        force_residual=float(fres),
        torque_residual=float(tres),
        friction_margin=margin,
        com_drift=drift,
        hold_time=cfg.hold_time,
        increments=len(rows),
        travel=np.array([r[0] for r in rows]),
        penetration=np.array([r[1] for r in rows]),
        force_norm=np.array([r[2] for r in rows]),
        normal_force=np.array([r[3] for r in rows]),
        tangential_force=np.array([r[4] for r in rows]),
        feasible=np.array([r[5] for r in rows]),
        rigid_normal_forces=rigid,
        rigid_utilisation=utilisation,
        positions=held_state.x,
        centres=centres,
        contact_points=pts,
        com=com,
        first_contact_travel=first,
        placed=placed,
        start_centres=start,
        placement=placement,
        joint_paths=joint_paths,
        config=cfg,
        wall_time=time.perf_counter() - t0,
        hold_checks=tuple(checks),
        frames=PlanFrames(
            travel=np.array([f[0] for f in frames]),
            positions=np.array([f[1] for f in frames]),
            centres=np.array([f[2] for f in frames]),
            forces=np.array([f[3] for f in frames]),
        ),
        solver_stats=dict(
            cache.stats,
            closing_systems=cache.stats["systems"]
            - cache.stats["settle_systems"]
            - cache.stats["hold_check_systems"],
        ),
    )


def _advance(
    scene: Scene, state: State, t: float, cfg: PlanConfig, cache: SolverCache, guess: NDArray | None = None
) -> State:
    """Bring the object to rest with the fingers at load parameter ``t`` (travel for the
    quasi-static solver, time for the dynamic one); the quasi-static solve starts from ``guess``
    (predicted positions) where one is given."""
    try:
        if cfg.solver == "dynamic":
            # The paper's explicit Runge-Kutta while the fingers move through the increment at
            # the closing speed, then a static solve brings the object to rest there.
            state = simulate(scene, state, t, method="rk4")
            state = State(state.x, np.zeros_like(state.v), state.t, state.contacts)
        if cfg.solver != "quasistatic":
            guess = None  # the dynamics brought the object somewhere else
        state, _, _ = solve_increment(scene, state, t, cache=cache, guess=guess, rtol=STEP_RTOL)
    except NotConverged as exc:
        what = f"{t * 1e3:.3g} mm of travel" if cfg.solver == "quasistatic" else f"t = {t:.4g} s"
        raise NotConverged(f"closing increment to {what} failed: {exc}") from exc
    return state
