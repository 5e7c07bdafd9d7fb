"""What a plan returns: each finger's set-point in the held state (:class:`FingerResult`), the
closing's path at rest (:class:`PlanFrames`) and the whole plan (:class:`GraspPlan`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from softgrasp.grasp.config import PlanConfig
from softgrasp.grasp.damage import Damage
from softgrasp.grasp.initial import InitialGrasp
from softgrasp.grasp.margin import Margin
from softgrasp.hand.placement import HandPlacement

__all__ = ["FingerResult", "GraspPlan", "PlanFrames"]


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
    com_drift: the centre of mass's largest motion from the table over the release, the holding
        time and the held state [m] (elastic sag included; the hold is judged on the fingertips'
        slip); hold_time: that time [s].
    increments: closing increments simulated (the solves' for the least travel included).
    travel: fingertip travel at each increment [m], (K,), increasing (the solves' increments
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
        held there: which fingertip slid how far in the object, which finger lost contact, or where
        the object slid out of the fingers with no equilibrium), so that a user can see what made
        the fingers close further.
    slip: how far each fingertip slid as a whole in the object from the table's removal to the
        held state [m], (3,) (:func:`~softgrasp.grasp.hold.finger_slip`, summed over the check's
        steps; at most ``max_slip`` times its contact radius).
    damage: the set-points' peak contact pressures and the held state's peak strain
        (:mod:`softgrasp.grasp.damage`).
    setpoints: the force set-points [N], (3,): the normal forces the fingers close to under force
        control, ``safety_factor`` times the critical scale times the held state's normal forces.
    margin: the critical scale of the held state's normal forces (:mod:`softgrasp.grasp.margin`).
    frames: the object and the fingertips at rest at the start of the closing (travel 0) and after
        each closing increment, in the order of travel (what ``softgrasp view`` animates).
    contact_forces: the fingertips' forces on each node of the object in the held state [N],
        (N, 3) (Eq. 17-20: each pair's force shared among its facet's nodes), or None.
    solver_stats: what the closing's linear algebra did, the critical scale's checks apart
        (:attr:`SolverCache.stats <softgrasp.linalg.solve.SolverCache>`): Newton systems,
        factorisations, multigrid V-cycles ... (machine-independent measures of its cost); the
        Newton systems also by phase:
        ``settle_systems`` (the object coming to rest on the table), ``closing_systems`` (the
        closing increments and their refinement) and ``hold_check_systems`` (the table removed,
        the release, the holding simulation and the held equilibrium); and ``margin_systems``,
        those the critical scale's checks solved on their own (not in ``systems``).
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
    slip: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    damage: Damage | None = None
    frames: PlanFrames | None = None
    setpoints: NDArray[np.float64] = field(default_factory=lambda: np.full(3, np.nan))
    margin: Margin | None = None
    solver_stats: dict[str, int] = field(default_factory=dict)
    contact_forces: NDArray[np.float64] | None = None

    @property
    def held_increment(self) -> int:
        """Index of the increment (in :attr:`travel`) the object was held at: the last hold
        check's travel (increments past it only bracketed the least squeeze that holds)."""
        if not len(self.travel):
            return 0
        if not self.hold_checks:
            return len(self.travel) - 1
        return int(np.argmin(np.abs(self.travel - self.hold_checks[-1][0])))


@dataclass(frozen=True)
class PlanFrames:
    """The closing at rest: the start (travel 0) and each increment, sorted by travel.

    Attributes
    ----------
    travel: fingertip travel [m], (K,).
    positions: node positions [m], (K, N, 3).
    centres: fingertip centres [m], (K, 3, 3).
    forces: force of each fingertip on the object [N], (K, 3, 3).
    contact_forces: the fingertips' forces on each node of the object [N], (K, N, 3) (Eq. 17-20),
        or None.
    """

    travel: NDArray[np.float64]
    positions: NDArray[np.float64]
    centres: NDArray[np.float64]
    forces: NDArray[np.float64]
    contact_forces: NDArray[np.float64] | None = None
