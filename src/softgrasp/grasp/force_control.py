"""Force-controlled closing to set-points, then the hold check: the execution of paper step 3
(Sec. 4.3.3) simulated with softgrasp's own object model, quasi-statically.

From the object at rest on the table and the fingertips at the start of their closing lines
(:func:`softgrasp.grasp.setup.closing_setup`), each fingertip first moves to where it touches
the object; then every increment moves the fingertips along their lines by the travels that
bring their normal forces (the tactile sensors' readings) to their set-points, estimated from the
increments so far (:func:`_next_move`) on G = F^(1/n), n the contact law's exponent,

    J d = G_set - G,   each d_j clipped to [-step, step],   J ~ dG/ds (Broyden's secant Jacobian),

and the object comes to static equilibrium (the fingers push the object on the table and each
other's forces change with it: J is not diagonal). The contact (F ~ p^n in its penetration p;
Hertz's n = 3/2) is linear in G, so the secant follows a contact that stiffens as it loads; a
secant on F itself is softer than the tangent there and overshoots the set-point, on a stiff
object by a multiple of it, leaving a friction state that depends on the step. A finger without
a secant yet moves by the travel at which its own contact law, against a rigid object, takes it
from its force to its set-point (under the patch rule the object's deformation only adds to
it; the paper's facet rule gives each touched facet the whole law). The closing ends when every
finger is within ``tolerance`` of its set-point. Then the table is taken away and the object
held for ``hold_time`` seconds
(:func:`softgrasp.grasp.hold.check_hold`): the grasp holds when every step finds its
equilibrium, every finger keeps contact and no fingertip slides in the object by more than
``max_slip`` times its contact radius.

This answers "do these set-points hold this object?" for any material and friction, which is what
robust set-points (:mod:`softgrasp.sweep.robust`) are checked with.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError, NotConverged
from softgrasp.grasp.config import STEP_RTOL, PlanConfig
from softgrasp.grasp.hold import check_hold, cone_usage
from softgrasp.grasp.setup import ClosingSetup, closing_setup
from softgrasp.linalg.solve import SolverCache
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import Fingertip
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import solve_increment, solve_static

__all__ = ["SetpointHold", "hold_setpoints", "TOLERANCE", "MAX_INCREMENTS"]

#: Relative force error within which a set-point counts as reached.
TOLERANCE = 0.01
#: Closing increments of the force controller before it gives up.
MAX_INCREMENTS = 80
#: The fraction of the way to its set-point that a finger below it aims for by its own secant
#: alone (before the Jacobian has seen the fingers' coupling): the others' pushes move the object
#: towards it, on the table's elastic slip, and add to its force.
OWN_SECANT_REACH = 0.9


@dataclass(frozen=True)
class SetpointHold:
    """A force-controlled closing and its hold check.

    Attributes
    ----------
    setpoints: the normal forces asked for [N], (3,).
    reached: each finger's normal force at the end of the closing, on the table [N], (3,).
    peak: the largest normal force each finger pressed with during the closing [N], (3,).
    travel: each fingertip's travel along its closing line from its start [m], (3,).
    penetration: each fingertip's travel past its first touch of the object [m], (3,).
    increments: closing increments the controller used.
    held: whether the fingers held the object with the table taken away.
    reason: ``"held"``, or why not (a set-point not reached before the crushing limit, the
        controller not settling, the object moving or a finger sliding in the hold).
    drift: centre-of-mass motion of the hold check [m] (nan when not held: ``reason`` says how far
        it moved, or why the check did not run).
    friction_margin: 1 - the largest |f_t| / (mu f_n) of the fingers in the held state (nan when
        not held).
    held_normal: normal forces in the held state [N], (3,) (nan when not held).
    max_travel: the crushing limit: the farthest travel along a closing line [m].
    wall_time: seconds.
    systems: Newton systems solved (the settle, when made here, the closing and the hold check).
    """

    setpoints: NDArray[np.float64]
    reached: NDArray[np.float64]
    peak: NDArray[np.float64]
    travel: NDArray[np.float64]
    penetration: NDArray[np.float64]
    increments: int
    held: bool
    reason: str
    drift: float
    friction_margin: float
    held_normal: NDArray[np.float64]
    max_travel: float
    wall_time: float
    systems: int = 0


def _tips(cfg: PlanConfig, centres: NDArray[np.float64], moves: NDArray[np.float64]) -> FingertipContact:
    """Fingertips at ``centres`` moving by ``moves`` (k, 3) over the load parameter 0 -> 1."""
    return FingertipContact(
        tuple(
            Fingertip(cfg.fingertip_radius, centre=centres[j], velocity=moves[j], name=name)
            for j, name in enumerate(cfg.fingers)
        ),
        cfg.contact,
    )


def _next_move(
    ds: NDArray[np.float64],
    dG: NDArray[np.float64],
    err: NDArray[np.float64],
    gain: NDArray[np.float64],
    jac: NDArray[np.float64] | None,
    step: float,
    first: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None]:
    """The force controller's next travel of each fingertip along its line [m], from the last
    increment's travels ``ds`` [m] and changes ``dG`` of the controlled force measure
    G = F^(1/n) and the errors ``err`` = G_set - G (module docstring).

    Each finger's own secant ``gain`` dG_j/ds_j is kept from the last increment that moved it
    with a rising force. Until every finger has one, a finger with a gain steps by err_j / gain_j
    (:func:`_own`) and one without moves by ``first`` [m] (the contact law's travel from its
    force to its set-point) towards a set-point above its force, a quarter ``step`` back from one
    below it.
    Then the fingers move together: the Jacobian ``jac`` dG/ds (k, k), started as diag(gain),
    follows Broyden's update (each finger's force also changes when the others push the object),
    and the move solves jac d = err, so that a finger already at its set-point compensates for the
    others. A Jacobian that turns singular or gives a finger a non-positive own gain (a contact
    slipping or lost) restarts from diag(gain) (a step by :func:`_own`). Each finger's move is
    clipped to at most ``step`` either way.

    Returns (move, gain, jac)."""
    moved = np.abs(ds) > 1e-12
    slope = dG / np.where(moved, ds, 1.0)
    gain = np.where(moved & (slope > 0), slope, gain)
    known = np.isfinite(gain)
    if not known.all():
        jac = None
        blind = np.where(err > 0, first, -0.25 * step)
        move = np.where(known, _own(err, np.where(known, gain, 1.0)), blind)
        return np.clip(move, -step, step), gain, jac
    if jac is not None and moved.any():
        jac = jac + np.outer(dG - jac @ ds, ds) / float(ds @ ds)  # Broyden's rank-one update
    move = None
    if jac is not None and (np.diag(jac) > 0).all():
        try:
            move = np.linalg.solve(jac, err)
        except np.linalg.LinAlgError:
            move = None
    if move is None or not np.isfinite(move).all():
        jac = np.diag(gain)
        move = _own(err, gain)
    return np.clip(move, -step, step), gain, jac


def _own(err: NDArray[np.float64], gain: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each finger's travel to its set-point by its own secant ``gain`` [1/m of G] from its error
    ``err`` in G, :data:`OWN_SECANT_REACH` of the way from below and the whole way back from
    above."""
    return np.where(err > 0, OWN_SECANT_REACH, 1.0) * err / gain


def _law_travels(
    body: Body, fc: FingertipContact, target: NDArray[np.float64], t: float
) -> NDArray[np.float64]:
    """Each fingertip's penetration at which its own normal law (at its position at time ``t``)
    gives its set-point ``target`` [N] against a rigid object [m], (k,)."""
    from softgrasp.physics.fingertip.resolved import penetration_value

    law, n = fc.law_table(body, t), fc.params.exponent
    return np.array(
        [penetration_value(float(F), law[j, 5], law[j, 0], n, *law[j, 1:5]) for j, F in enumerate(target)]
    )


def _increment(
    body: Body,
    cfg: PlanConfig,
    setup: ClosingSetup,
    fc: FingertipContact,
    state: State,
    move: NDArray[np.float64],
    s: NDArray[np.float64],
    cache: SolverCache,
) -> tuple[NDArray[np.float64], FingertipContact, State]:
    """One closing increment: the fingertips moved by ``move`` [m] along their lines (from their
    travels ``s``, never past the crushing limit nor behind a line's start) and the object at
    rest there. Where Newton finds no rest (its iterates cycling as a node of the object flips in
    and out of the table's contact, the object rocking on it: a band of travel a few tenths of a
    millimetre wide), moves half as long, 1.5 and 2 times as long, a quarter and 3 times as long
    are tried in turn, as the position-controlled closing goes on past such a travel
    (:meth:`~softgrasp.grasp.closing.Closing.close`); the next increments correct any overshoot.
    Each is tried first by one static solve, the cheap way past the band, and only when none of
    them finds a rest so with the increment's splitting and backward Euler steps
    (:func:`~softgrasp.sim.static.solve_increment`), which cost some 25 times as much where they
    fail. Returns (the move made, the fingertips there, the rest); raises the first NotConverged
    when none of them finds a rest."""

    def at(factor: float) -> tuple[NDArray[np.float64], FingertipContact, Scene]:
        made = np.clip(factor * move, -s, setup.max_travel - s)
        tips = _tips(cfg, fc.centres(1.0), setup.directions * made[:, None])
        return made, tips, Scene(body, (setup.table, tips))

    start = replace(state, t=0.0)
    made, tips, scene = at(1.0)
    try:
        return made, tips, solve_increment(scene, start, 1.0, cache=cache, rtol=STEP_RTOL)[0]
    except NotConverged as exc:
        first = exc
    for whole in (False, True):
        for factor in (0.5, 1.5, 2.0, 0.25, 3.0):
            made, tips, scene = at(factor)
            try:
                if whole:
                    rest = solve_increment(scene, start, 1.0, cache=cache, rtol=STEP_RTOL)[0]
                else:
                    rest = solve_static(scene, start, t=1.0, cache=cache, rtol=STEP_RTOL)[0]
            except NotConverged:
                continue
            return made, tips, rest
    raise first


def hold_setpoints(
    body: Body,
    config: PlanConfig,
    setpoints: NDArray[np.float64] | tuple[float, float, float],
    *,
    tolerance: float = TOLERANCE,
    max_increments: int = MAX_INCREMENTS,
    setup: ClosingSetup | None = None,
) -> SetpointHold:
    """Close the fingertips on ``body`` under force control to ``setpoints`` (normal forces
    [N], one per finger of ``config.fingers``), each along its own closing line, then check the hold with the
    table taken away (module docstring).

    The closing lines are the planner's: from ``config.grasp`` when given (the same contacts as an
    earlier plan), else from the best reachable grasp. A set-point that the finger does not reach
    before the crushing limit (``config.max_squeeze``), or a controller that does not settle in
    ``max_increments`` increments, makes the grasp not held (``reason`` says which finger).
    ``setup``: the closing's start (:func:`~softgrasp.grasp.setup.closing_setup` of ``body`` and
    ``config``) when already made, as for several set-points on one grasp.

    Raises
    ------
    ConfigError: set-points that are not one positive finite force per finger, or a bad tolerance.
    InfeasibleGrasp: no reachable initial grasp (as :func:`~softgrasp.grasp.planner.plan_grasp`).
    NotConverged: the object finds no rest on the table.
    """
    t0 = time.perf_counter()
    target = np.asarray(setpoints, dtype=np.float64)
    k = len(config.fingers)
    if target.shape != (k,) or not (np.isfinite(target).all() and (target > 0).all()):
        raise ConfigError(
            f"set-points must be {k} normal forces > 0 N (one per finger), got "
            f"{np.asarray(setpoints).tolist()}"
        )
    if not 0 < tolerance < 0.5:
        raise ConfigError(f"the set-point tolerance must lie in (0, 0.5), got {tolerance}")
    if max_increments < 1:
        raise ConfigError(f"max_increments must be >= 1, got {max_increments}")
    cfg = config
    cache = SolverCache()
    if setup is None:
        setup = closing_setup(body, cfg, cache)
    body = setup.body  # its rest shape where it lies on the table
    u = setup.directions
    limit = setup.max_travel

    def result(s, forces, n, held, reason, drift=math.nan, margin=math.nan, normal=None) -> SetpointHold:
        return SetpointHold(
            target,
            np.asarray(forces, dtype=np.float64).copy(),
            peak.copy(),
            s.copy(),
            s - setup.first_touch,
            n,
            held,
            reason,
            drift,
            margin,
            np.full(k, math.nan) if normal is None else normal,
            limit,
            time.perf_counter() - t0,
            int(cache.stats["systems"]),
        )

    # Each fingertip to its first touch (no force yet: the object stays as it rests).
    s = setup.first_touch.copy()
    fc = _tips(cfg, setup.start, u * s[:, None])
    state = State(
        setup.settled.x,
        np.zeros_like(setup.settled.x),
        0.0,
        (setup.settled.contacts[0], fc.init_state(body, setup.settled.x, 0.0)),
    )
    forces = np.zeros(k)
    peak = forces.copy()
    first = _law_travels(body, fc, target, 1.0)
    power = 1.0 / cfg.contact.exponent  # G = F^(1/n): linear in the penetration of the law
    g_set = target**power
    s_prev, g_prev = s.copy(), forces.copy()
    gain = np.full(k, math.nan)  # dG/ds of each finger, from the last increment that moved it
    jac: NDArray[np.float64] | None = None  # dG/ds of the fingers together, once each has a gain
    increments = 0
    while True:
        err = target - forces
        done = np.abs(err) <= tolerance * target
        if done.all():
            break
        stuck = (s >= limit - 1e-12) & ~done & (err > 0)
        if stuck.any():
            j = int(np.argmax(stuck))
            return result(
                s,
                forces,
                increments,
                False,
                f"the {cfg.fingers[j]} finger reached {forces[j]:.3f} N of its {target[j]:.3f} N set-point "
                f"at the crushing limit ({limit * 1e3:.1f} mm of travel)",
            )
        if increments == max_increments:
            return result(
                s,
                forces,
                increments,
                False,
                f"the force control did not settle within {max_increments} increments (forces "
                f"{', '.join(f'{v:.3f}' for v in forces)} N for {', '.join(f'{v:.3f}' for v in target)} N)",
            )
        g = np.maximum(forces, 0.0) ** power
        rest = first * np.clip((g_set - g) / g_set, 0.0, 1.0)  # the law's travel from g to g_set
        move, gain, jac = _next_move(s - s_prev, g - g_prev, g_set - g, gain, jac, cfg.step, rest)
        try:
            move, fc, state = _increment(body, cfg, setup, fc, state, move, s, cache)
        except NotConverged as exc:
            return result(
                s, forces, increments, False, f"a closing increment found no equilibrium ({exc.diagnosis})"
            )
        increments += 1
        s_prev, g_prev = s, g
        s = s + move
        forces = fc.report(body, state.x, None, 1.0, state.contacts[1], static=True).normal
        peak = np.maximum(peak, forces)
    checked = check_hold(body, setup.table, fc, state, 1.0, cfg, cache)
    if isinstance(checked, str):
        return result(s, forces, increments, False, checked)
    held, fixed, drift, _ = checked
    rep = fixed.report(body, held.x, None, 0.0, held.contacts[0], static=True)
    margin = float(1.0 - cone_usage(rep, cfg.contact.mu).max())
    return result(s, forces, increments, True, "held", drift, margin, rep.normal.copy())
