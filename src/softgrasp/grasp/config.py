"""The planner's configuration (:class:`PlanConfig`) and its fixed, tuned constants, each with
the reason for its value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from softgrasp.errors import ConfigError
from softgrasp.grasp.initial import FINGER_NAMES, HandLayout, InitialGrasp
from softgrasp.hand.kinematics import HandModel
from softgrasp.hand.packaged import portable_name
from softgrasp.model.ranges import RANGES
from softgrasp.physics.fingertip.params import ContactParams

__all__ = [
    "PlanConfig",
    "SOLVERS",
    "START_BACKOFF",
    "MAX_PLACEMENTS",
    "PER_SPREAD",
    "PATH_RTOL",
    "LOWERED_MAX_ITER",
    "LOWERED_MIN_NODES",
    "STEP_RTOL",
    "HELD_RTOL",
    "RELEASE_STEPS",
    "RELEASE_MAX_ITER",
    "RELEASE_PATIENCE",
    "HOLD_DT",
    "MAX_HALVINGS",
    "SETTLED",
    "TRAVEL_FLOOR",
    "FIRST_GROWTH",
    "TOUCH_GAP",
    "CONTACT_START",
]

#: The closing's solvers: a static solve per increment, or explicit dynamics through it first.
SOLVERS = ("quasistatic", "dynamic")

# Step 1: the initial grasp and the closing lines.
#: Closing steps the fingertips start back from tangency with the object: first contact falls in
#: the middle of the second increment, never on an increment's end, where whether a tangent
#: facet touches (and is anchored at the unloaded surface) would be decided by round-off.
START_BACKOFF = 1.5
#: Initial-grasp shapes the planner tries to reach with the hand before giving up: a bound on
#: the placement searches spent on an object the hand cannot grasp.
MAX_PLACEMENTS = 12
#: Failed placements after which a spread angle of the layout is skipped: on a near-symmetric
#: object its other azimuths fail alike.
PER_SPREAD = 1

# The object at rest on the table.
#: Relative tolerance of the settle on the table: the static solver's stall tolerance
#: (:data:`~softgrasp.sim.newton.STALL_RTOL`), where a rest on a nearly neutral rolling mode may
#: end anyway; a tighter settle leaves the set-points the same to eight digits.
PATH_RTOL = 1e-6
#: Newton iterations a friction pass of the settle's lowered start is given before the level start
#: takes over: lowered starts that find a rest take 3-24; one that wanders costs half the usual 60.
LOWERED_MAX_ITER = 30
#: The least node count for which the settle starts lowered (only where its systems go to
#: multigrid): below it the lowered start saved Newton systems on some meshes and cost on others.
LOWERED_MIN_NODES = 10_000

# Step 2: the closing increments, the release and the held state.
#: Relative tolerance of the load steps on the way to the held state (the closing increments and
#: the release steps but the last): they carry only the friction history, the reported per-step
#: forces and the grasp test, and end a Newton iteration earlier than at ``HELD_RTOL`` while the
#: set-points, solved from the held state, move by less than 1e-5 of themselves.
STEP_RTOL = 1e-4
#: Relative tolerance of the held state the set-points come from, and of the last release step
#: where the holding simulation starts (a looser start leaves the hold's dynamics unbalanced).
HELD_RTOL = 1e-9
#: Static load steps in which the table's support is taken away before the holding simulation:
#: the weight passes to the fingers quasi-statically, as in a slow lift.
RELEASE_STEPS = 4
#: Newton iterations a release step is given before the object counts as sliding out of the
#: fingers: converged release steps took up to 29 where the fingers slip as the weight passes to
#: them (the sphere at mu = 0.05, squeezed 14 N: its iterates crawl along the slip at 5-15 % a
#: step), at most 9 on the foam cube, 19 on the rubber box and 6 on the spheres from mu = 0.15 up.
#: One whose object slides out meets ever more singular systems (no stiffness along the slide);
#: Newton's crawl and climb checks end most of those long before the limit.
RELEASE_MAX_ITER = 40
#: A release step gives up once this many Newton iterations in a row found no lower unbalanced
#: force than an earlier one (:func:`softgrasp.sim.newton.stalls`): its object slides out of the
#: fingers, each step taken for the energy the fall frees while the forces grow (the 2 196-node
#: sphere's check below its critical scale rose from 3.0e-3 to 1.1e-2 N over 38 iterations, and
#: as far again from the last rest). Release steps that balanced went at most 3 iterations so
#: (the default sphere at mu = 0.05, whose fingers slip), 4 on the rubber box, 0 on the foam cube.
RELEASE_PATIENCE = 12
#: First time step of the implicit holding simulation [s]: a twentieth of the default hold.
HOLD_DT = 0.05
#: Halvings of the holding simulation's step allowed when a step's Newton solve fails: a sudden
#: slip or release resolved in steps down to HOLD_DT / 64.
MAX_HALVINGS = 6
#: Centre-of-mass motion per holding step below which the step is doubled [m]: the object has
#: come to rest, and larger steps then cost nothing in accuracy.
SETTLED = 1e-6
#: Narrowest bracket of travel the closing's solves split [m]: a nanometre, far below any
#: squeeze a force tolerance asks for, where the static solves' own tolerance starts to show.
TRAVEL_FLOOR = 1e-9
#: Growth of the fingers' force asked of the first further squeeze after a failed hold check
#: (then doubled after each failure): ten times the default force tolerance, so that a hold a
#: little past the grasp test is bracketed in one or two checks and split in three or four.
FIRST_GROWTH = 0.1
#: Gap from the object's surface [m] at which the closing's approach ends, just before the first
#: fingertip touches: a tenth of a micrometre, far below any squeeze that holds, and clear of
#: tangency (where round-off would decide whether a facet touches).
TOUCH_GAP = 1e-7
#: First squeeze increment past the touch, as a fraction of the fingertip radius (80 um for the
#: default 8 mm): the increments then double the squeeze, so that stick-slip friction is followed
#: along the same travels whatever the step (a stiff object may pass the grasp test within it).
CONTACT_START = 0.01


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
    safety_factor: the set-points are this multiple (>= 1) of the least normal forces that hold
        under force control (:mod:`softgrasp.grasp.margin`).
    hold_time: simulated holding time of the verification [s].
    max_slip: largest slip of a fingertip in the object, as a whole, from the table's removal to
        the held state, as a fraction of its Hertz contact radius at its normal force where the
        check starts: beyond it the fingertip has left the patch it held by, and the object slides
        in the fingers (its elastic sag is no slip). An eighth: 0.27-0.31 mm on the default
        sphere, 0.3-0.6 mm on the 50 x 40 x 30 mm rubber box. A fixed share of the object's size
        (0.25 %, the same limit on the sphere) would count the box's fingers, which slide
        0.1-0.2 mm down its faces as the table goes and then hold, as letting go: its set-points
        then come out at 1.6-4.5 times the rigid-body least force and not monotone in mu. Half
        the contact radius (1 % of the sphere's size) lets a grasp whose fingertips slide into a
        better hold pass below the force at which sliding starts, by an amount that changes from
        one mesh to the next.
    max_squeeze: largest travel past the last finger's first contact, as a fraction of the
        shortest finger-to-centroid distance (beyond it the object is crushed).
    force_tol: relative force tolerance of the set-points: the closing's travel is solved until
        the squeeze where the grasp test first passes, and where the object is first held, is
        known within this fraction of the fingers' forces.
    refine: the most iterations of each of those solves (a bound: the force tolerance ends them
        first on smooth closings).
    table_mu: friction between object and table.
    layout: the search grid and coarse reach limits of the initial grasp (:class:`HandLayout`);
        ``None``: the hand's (:meth:`HandLayout.for_hand`: its reach limits and fingers).
    hand: the hand's kinematic model (default: the packaged Shadow-like hand); the initial grasp
        must be reachable by it and its fingertips must follow the closing lines. ``None`` plans
        for free fingertips (the layout alone limits the grasp).
    grasp: an initial grasp to close from instead of searching for one (the contacts of an
        earlier plan: the same closing lines for another material or friction); ``None``: search.
    max_pressure: largest peak contact pressure the held grasp may put on the object [Pa]
        (:mod:`softgrasp.grasp.damage`); ``None``: no limit.
    max_strain: largest principal strain the held grasp may cause in the object; ``None``: no limit.
    """

    contact: ContactParams = field(default_factory=ContactParams)
    fingertip_radius: float = 0.008
    step: float = 0.0005
    solver: str = "quasistatic"
    closing_speed: float = 0.05
    safety_factor: float = 1.25
    hold_time: float = 1.0
    max_slip: float = 0.125
    max_squeeze: float = 0.5
    force_tol: float = 0.01
    refine: int = 12
    table_mu: float = 0.5
    layout: HandLayout = None  # type: ignore[assignment]  # None: the hand's (set in __post_init__)
    hand: HandModel | None = field(default_factory=HandModel.default)
    grasp: InitialGrasp | None = None
    max_pressure: float | None = None
    max_strain: float | None = None

    def __post_init__(self) -> None:
        for name in ("fingertip_radius", "step", "safety_factor", "max_squeeze", "refine"):
            RANGES[name].check(f"plan parameter {name}", getattr(self, name))
        if self.hold_time != 0:  # 0: the grasp test alone, without the holding simulation
            RANGES["hold_time"].check("plan parameter hold_time", self.hold_time)
        checks = {
            "closing_speed": self.closing_speed > 0,
            "max_slip": 0 < self.max_slip < 1,
            "force_tol": 0 < self.force_tol < 1,
            "table_mu": self.table_mu >= 0,
        }
        for name, ok in checks.items():
            v = getattr(self, name)
            if not (ok and math.isfinite(v)):
                raise ConfigError(f"plan parameter {name} = {v} is invalid")
        for name in ("max_pressure", "max_strain"):
            v = getattr(self, name)
            if v is not None:
                RANGES[name].check(f"plan parameter {name}", v)
        if self.solver not in SOLVERS:
            raise ConfigError(f"solver must be one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if self.layout is None:
            object.__setattr__(self, "layout", HandLayout.for_hand(self.hand))
        if self.hand is not None:
            for finger in self.fingers:
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

    @property
    def fingers(self) -> tuple[str, ...]:
        """The fingers of the grasp, the opposing one first: the hand's
        (:attr:`~softgrasp.hand.kinematics.HandModel.grasp_fingers`), or thumb, first and middle
        without a hand."""
        return FINGER_NAMES if self.hand is None else self.hand.grasp_fingers

    def describe(self) -> dict[str, object]:
        return {
            "contact": self.contact.describe(),
            "fingertip_radius_m": self.fingertip_radius,
            "step_m": self.step,
            "solver": self.solver,
            "closing_speed_m_s": self.closing_speed,
            "safety_factor": self.safety_factor,
            "hold_time_s": self.hold_time,
            "max_slip": self.max_slip,
            "max_squeeze": self.max_squeeze,
            "force_tol": self.force_tol,
            "refine": self.refine,
            "table_mu": self.table_mu,
            "hand_layout": self.layout.describe(),
            "hand": None if self.hand is None else portable_name(self.hand.source),
            "grasp": "given" if self.grasp is not None else "searched",
            "max_pressure_Pa": self.max_pressure,
            "max_strain": self.max_strain,
        }
