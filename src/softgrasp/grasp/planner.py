"""The grasp planner (paper steps 1-2, Sec. 2 and 4.3): the initial grasp, the closing in
increments towards the contact triangle's centroid until the fingers hold the object, and the
forces of the *held* state (table removed) as the force set-points.

1. :func:`~softgrasp.grasp.setup.closing_setup`: the object at rest on the table
   (:mod:`softgrasp.grasp.settle`), the best force-closure initial grasp the hand reaches, and the
   fingertips' closing lines.
2. :class:`~softgrasp.grasp.closing.Closing`: whole steps up to the first touch, then increments
   doubling the squeeze until the grasp test passes, then the least travel that passes it,
   solved for within the last increment to ``force_tol`` of the force; the hold check
   (:func:`~softgrasp.grasp.hold.check_hold`) there, the fingers squeezing further by growing
   shares of force until the object is held, and the least travel held solved for to
   ``force_tol`` again. Past ``max_squeeze`` (a fraction of the shortest finger-to-centroid
   distance, travelled beyond the last finger's first contact) the object would be crushed:
   :class:`InfeasibleGrasp`. Friction too low to hold before a squeeze that finds no rest is
   :class:`InfeasibleGrasp` too, with the rigid-body least normal force.
3. The held state's finger forces, their balance (Eq. 21-22) and friction margin.
4. The set-points: the critical scale of the held state's normal forces, the least multiple
   that holds under force control (:func:`~softgrasp.grasp.margin.critical_scale`), times the
   ``safety_factor``: the :class:`GraspPlan`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import InfeasibleGrasp
from softgrasp.grasp.closing import Closing
from softgrasp.grasp.config import PlanConfig
from softgrasp.grasp.damage import check_limits, grasp_damage, patch_torsion
from softgrasp.grasp.equilibrium import minimum_normal_forces, squeeze_utilisation
from softgrasp.grasp.hold import cone_usage
from softgrasp.grasp.margin import critical_scale
from softgrasp.grasp.progress import PlanProgress
from softgrasp.grasp.result import FingerResult, GraspPlan, PlanFrames
from softgrasp.grasp.settle import centre_of_mass
from softgrasp.grasp.setup import ClosingSetup, closing_setup
from softgrasp.hand.placement import closing_paths
from softgrasp.linalg import pardiso
from softgrasp.linalg.solve import SolverCache
from softgrasp.model.ranges import check_object_mass
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.contact import FingerReport

__all__ = [
    "PlanConfig",
    "FingerResult",
    "GraspPlan",
    "PlanFrames",
    "ClosingSetup",
    "closing_setup",
    "plan_grasp",
]


def plan_grasp(
    body: Body,
    config: PlanConfig = PlanConfig(),  # noqa: B008 - frozen dataclass
    *,
    progress: Callable[[float], None] | None = None,
    phase: Callable[[str], None] | None = None,
    cache: SolverCache | None = None,
    keep_rest: bool = False,
) -> GraspPlan:
    """Plan a three-finger grasp of ``body`` resting on a table (paper steps 1-2).

    Parameters
    ----------
    body: the object.  config: everything else (:class:`PlanConfig`).
    progress: called with the fraction of the plan done, never smaller than the one before
        (:class:`~softgrasp.grasp.progress.PlanProgress`).
    phase: called with the name of each phase as it starts (``initial grasp``, ``closing``,
        ``hold check``, ``set-points``).
    cache: the linear solves' state (its ``method`` chooses the solver); a fresh one if None.
    keep_rest: read the object's rest on the table from softgrasp's cache folder when it was kept
        there, else keep it there (:func:`softgrasp.grasp.kept_rest.settle`; the same plan either
        way, bit for bit).

    Raises
    ------
    ConfigError: the object is lighter than 1 g or heavier than the hand lifts
        (:func:`~softgrasp.model.ranges.check_object_mass`), before any solve.
    InfeasibleGrasp: no reachable force-closure grasp, or no hold before the maximum squeeze.
    NotConverged: an increment between two at rest found no static equilibrium even when split
        (one past them that finds none is an InfeasibleGrasp: the object cannot be squeezed harder).
    """
    check_object_mass(float(body.total_mass), float(body.mesh.volume))
    with pardiso.blas_one_thread():
        tracker = PlanProgress(progress, phase)
        return _plan_grasp(body, config, tracker, SolverCache() if cache is None else cache, keep_rest)


def _plan_grasp(
    body: Body, config: PlanConfig, progress: PlanProgress, cache: SolverCache, keep_rest: bool
) -> GraspPlan:
    t0 = time.perf_counter()
    cfg = config
    mu = cfg.contact.mu
    progress.enter("initial grasp")
    setup = closing_setup(body, cfg, cache, keep_rest=keep_rest)  # step 1
    body = setup.body  # its rest shape where it lies on the table
    ig, placement, start, first = setup.grasp, setup.placement, setup.start, setup.first_touch
    progress.enter("closing")
    closing = Closing(body, cfg, setup, cache, progress.within("closing"))  # step 2
    passing = closing.until_the_grasp_test()
    progress.enter("hold check")
    t_final, (held_state, fixed, drift, slip) = closing.until_held(passing)
    progress.enter("set-points")
    rows, frames = closing.rows, closing.frames
    # The set-points: the held state's forces.
    hrep = fixed.report(body, held_state.x, None, 0.0, held_state.contacts[0], static=True)
    pts, push, fn = fixed.contact_frames(body, held_state.x, 0.0, held_state.contacts[0])
    com = centre_of_mass(body, held_state.x)
    fres = np.linalg.norm(hrep.force.sum(axis=0) + body.total_mass * body.gravity)
    centres = fixed.centres(0.0)
    tres = np.linalg.norm(_torque_residual(hrep, centres, com))
    # The held state's friction forces against the (circular) Coulomb cones, pair by pair.
    margin = float(1.0 - cone_usage(hrep, mu).max())
    torsion = patch_torsion(body, fixed, fn, mu)  # two fingers: the Hertz patches' torsional friction
    try:
        rigid = minimum_normal_forces(pts, push, mu, com, body.total_mass, body.gravity, torsion=torsion)
    except InfeasibleGrasp:
        rigid = np.full(len(cfg.fingers), np.nan)
    utilisation = squeeze_utilisation(pts, push, fn, mu, com, body.total_mass, body.gravity, torsion=torsion)
    damage = grasp_damage(body, fixed, held_state.x, hrep.normal)
    check_limits(damage, cfg.max_pressure, cfg.max_strain)
    fingers = tuple(
        FingerResult(
            name=name,
            initial_contact=ig.points[j],
            final_position=centres[j],
            penetration=float(max(t_final - first[j], 0.0)),
            force=hrep.force[j],
            normal_force=float(hrep.normal[j]),
            tangential_force=float(hrep.tangential[j]),
        )
        for j, name in enumerate(cfg.fingers)
    )
    normal = np.array([f.normal_force for f in fingers])
    margin_ = critical_scale(body, replace(cfg, grasp=ig), normal, guess=utilisation, setup=setup)
    if not np.isfinite(margin_.scale):
        need = (
            f"; mu = {mu:g} needs at least {rigid.sum():.2f} N of normal force in all to hold even a rigid "
            "object at these contacts"
            if np.isfinite(rigid).all()
            else ""
        )
        raise InfeasibleGrasp(
            f"mu = {mu:g} cannot hold the object under force control: closed to the held state's normal "
            f"forces ({_forces(normal)} N), and to up to {margin_.not_held:g} times them, the fingers "
            f"end elsewhere than the closing and the object is not held (at {margin_.not_held:g} times: "
            f"{margin_.why_not}){need}; raise the friction coefficient or move the grasp (--grasp)"
        )
    setpoints = cfg.safety_factor * margin_.scale * normal
    # The load the set-points put on the object: Hertz's pressure at them (the strain: the held state's).
    damage = grasp_damage(body, fixed, held_state.x, setpoints)
    check_limits(damage, cfg.max_pressure, None, setpoints=True)
    joint_paths = None
    if placement is not None:
        assert cfg.hand is not None
        lines = {f.name: (start[j], centres[j]) for j, f in enumerate(fingers)}
        joint_paths = closing_paths(cfg.hand, placement, lines, max(1, int(np.ceil(t_final / cfg.step))))
    progress.finish()
    rows.sort(key=lambda r: r[0])  # the solves' increments among the others, by travel
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
        placed=setup.placed,
        start_centres=start,
        placement=placement,
        joint_paths=joint_paths,
        config=cfg,
        wall_time=time.perf_counter() - t0,
        hold_checks=tuple(closing.checks),
        slip=slip,
        damage=damage,
        setpoints=setpoints,
        margin=margin_,
        frames=PlanFrames(
            travel=np.array([f[0] for f in frames]),
            positions=np.array([f[1] for f in frames]),
            centres=np.array([f[2] for f in frames]),
            forces=np.array([f[3] for f in frames]),
            contact_forces=np.array([f[4] for f in frames]),
        ),
        contact_forces=fixed.static_forces(body, held_state.x, 0.0, held_state.contacts[0]),
        solver_stats=dict(
            cache.stats,
            closing_systems=cache.stats["systems"]
            - cache.stats["settle_systems"]
            - cache.stats["hold_check_systems"],
            margin_systems=margin_.systems,
        ),
    )


def _forces(f: NDArray[np.float64]) -> str:
    return ", ".join(f"{v:.3g}" for v in f)


def _torque_residual(rep: FingerReport, centres, com) -> NDArray[np.float64]:
    """Sum of the fingers' moments about the centre of mass (the weight has none there)."""
    return (rep.moment + np.cross(centres - com, rep.force)).sum(axis=0)
