"""The hold check (paper Sec. 4.3.2): with the fingertips fixed where the closing stopped, the
table is taken away and the fingers alone must hold the object: the table's support ramps down in
static load steps (a slow lift), then implicit dynamics over the holding time must keep the centre
of mass within ``max_drift`` of where it stood, and the held state is brought to static
equilibrium with every fingertip sticking.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import NotConverged, SimulationUnstable
from softgrasp.grasp.config import (
    HELD_RTOL,
    HOLD_DT,
    MAX_HALVINGS,
    RELEASE_STEPS,
    SETTLED,
    STEP_RTOL,
    STICK_TOLERANCE,
    PlanConfig,
)
from softgrasp.grasp.initial import FINGER_NAMES
from softgrasp.grasp.settle import centre_of_mass
from softgrasp.linalg.solve import SolverCache
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.contact import FingerReport, FingertipContact
from softgrasp.physics.planes import PlaneContact
from softgrasp.sim.implicit import implicit_euler_step
from softgrasp.sim.loads import RampedLoad
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import extrapolated, solve_static

__all__ = ["check_hold", "cone_usage"]


def check_hold(
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
    ``hold_time`` seconds of implicit dynamics (:func:`_simulate_hold`) from that released state
    must keep the centre of mass within ``max_drift`` of where it was on the table; the held state
    is then brought to static equilibrium in the fingers alone. Returns (held state, fixed fingers,
    drift) or, when the object is not held, why not (a sentence)."""
    fixed = FingertipContact(
        tuple(replace(f, centre=f.centre_at(t), velocity=np.zeros(3)) for f in fc.fingertips),
        fc.params,
        name=fc.name,
    )
    support = RampedLoad(table.static_forces(body, state.x, t, state.contacts[0]), state.x, name="support")
    release = Scene(body, (fixed, support))
    scene = Scene(body, (fixed,))
    c0 = centre_of_mass(body, state.x)
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
            if (d := float(np.linalg.norm(centre_of_mass(body, st.x) - c0))) >= cfg.max_drift:
                return _moved(d, cfg, f"with the table's support down to {1 - k / RELEASE_STEPS:.0%}")
        released = float(np.linalg.norm(centre_of_mass(body, st.x) - c0))
        start = State(st.x, np.zeros_like(st.x), 0.0, (st.contacts[0],))
        end = _simulate_hold(body, scene, start, cfg.hold_time, cache, cfg.max_drift, origin=c0)
        if end is None:
            return _moved(cfg.max_drift, cfg, f"during the {cfg.hold_time:g} s hold")
        moved = float(np.linalg.norm(centre_of_mass(body, end.x) - c0))
        held, _ = solve_static(scene, replace(end, t=0.0), t=0.0, cache=cache, rtol=HELD_RTOL)
    except (NotConverged, SimulationUnstable) as exc:
        return f"the release or the hold found no equilibrium ({exc})"
    drift = max(released, moved, float(np.linalg.norm(centre_of_mass(body, held.x) - c0)))
    if drift >= cfg.max_drift:
        return _moved(drift, cfg, "at the held equilibrium")
    rep = fixed.report(body, held.x, None, 0.0, held.contacts[0], static=True)
    if rep.contacts.min() == 0:
        return f"the {FINGER_NAMES[int(np.argmin(rep.contacts))]} finger lost contact"
    usage = cone_usage(rep, cfg.contact.mu)
    if usage.max() >= 1.0 - STICK_TOLERANCE:  # a finger slides: not held
        return f"the {FINGER_NAMES[int(np.argmax(usage))]} finger slides (its friction at the Coulomb limit)"
    return held, fixed, drift


def _moved(drift: float, cfg: PlanConfig, when: str) -> str:
    """Why a hold check failed on the centre of mass's motion."""
    return (
        f"the centre of mass moved {'at least ' if drift <= cfg.max_drift else ''}{drift * 1e3:.2f} mm "
        f"{when} (limit {cfg.max_drift * 1e3:.2f} mm)"
    )


def cone_usage(rep: FingerReport, mu: float) -> NDArray[np.float64]:
    """Each finger's resultant friction force over mu times its resultant normal force, (3,): 1
    when the whole fingertip slides (every pair at its Coulomb limit, all in one direction), below
    1 when it sticks. Pairs at the rim of a contact patch may slip while the fingertip sticks
    (partial slip, as in Mindlin's contact): they do not make the grasp let go."""
    if mu <= 0:
        return np.ones(len(rep.normal))
    return rep.tangential / np.maximum(mu * rep.normal, 1e-300)


def _simulate_hold(
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
    c0 = centre_of_mass(body, state.x) if origin is None else origin
    while state.t < duration - 1e-12:
        h = min(dt, duration - state.t)
        before = centre_of_mass(body, state.x)
        try:
            state = implicit_euler_step(scene, state, h, cache=cache)
        except NotConverged:
            if h <= HOLD_DT / 2**MAX_HALVINGS:
                raise
            dt = h / 2.0  # a sudden slip or release: resolve it in shorter steps
            continue
        c = centre_of_mass(body, state.x)
        if np.linalg.norm(c - c0) >= max_drift:
            return None
        if np.linalg.norm(c - before) < SETTLED:
            dt *= 2.0
    return state
