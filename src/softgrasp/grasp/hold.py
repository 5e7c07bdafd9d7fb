"""The hold check (paper Sec. 4.3.2): with the fingertips fixed where the closing stopped, the
table is taken away and the fingers alone must hold the object: the table's support ramps down in
static load steps (a slow lift), then implicit dynamics over the holding time, then the held
state is brought to static equilibrium. The object is held when every step finds its
equilibrium, every finger keeps contact and no fingertip slides in the object by more than
``max_slip`` times its contact radius: a fingertip that slides less stays on the patch it held by,
while one that slides further has let go of it (the grasp's contacts have moved).

A fingertip slides *as a whole* only when every pair of its contact patch slips (Algorithm 1's
slip displacement u grows on each): its slip over one step is the least slip increment among its
pairs in contact before and after (a patch with one sticking pair does not slide; rim pairs slip
in partial slip, as in Mindlin's contact). The elastic deformation of the object, its sag in the
fingers included, moves no anchor and is no slip.

The contact radius is Hertz's at each fingertip's normal force where the check starts
(:func:`~softgrasp.grasp.damage.contact_radii`): the limit follows the grasp's contacts, not the
object's size, so that a small stiff contact and a large soft one are held to the same geometry.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import NotConverged, SimulationUnstable, diagnosis
from softgrasp.grasp.config import (
    HELD_RTOL,
    HOLD_DT,
    MAX_HALVINGS,
    RELEASE_MAX_ITER,
    RELEASE_PATIENCE,
    RELEASE_STEPS,
    SETTLED,
    STEP_RTOL,
    PlanConfig,
)
from softgrasp.grasp.damage import contact_radii
from softgrasp.grasp.settle import centre_of_mass
from softgrasp.linalg.solve import SolverCache
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.contact import FingerReport, FingertipContact
from softgrasp.physics.fingertip.state import FingerState
from softgrasp.physics.planes import PlaneContact
from softgrasp.sim.implicit import implicit_euler_step
from softgrasp.sim.loads import RampedLoad
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import extrapolated, solve_static

__all__ = ["Held", "check_hold", "cone_usage", "finger_slip"]

#: A held state: (state at rest in the fingers, the fixed fingers, the centre of mass's largest
#: motion from the table [m], each fingertip's slip in the object [m] (3,)).
Held = tuple[State, FingertipContact, float, NDArray[np.float64]]


class _NotHeld(Exception):
    """The hold check's verdict, raised where it is found."""


def finger_slip(before: FingerState, after: FingerState) -> NDArray[np.float64]:
    """How far each fingertip slid as a whole between two contact states [m], (n_f,): the least
    slip increment |du| among its pairs in contact in both (0 where it has none)."""
    both = before.active & after.active
    du = np.linalg.norm(after.slip - before.slip, axis=2)
    least = np.where(both, du, np.inf).min(axis=1)
    return np.where(np.isfinite(least), least, 0.0)


class _Tracker:
    """Each fingertip's slip summed over the steps of one hold check, and the verdicts on it:
    ``share`` (``max_slip``) of each fingertip's contact ``radius`` [m] (n_f,) is its limit."""

    def __init__(
        self, share: float, radius: NDArray[np.float64], fs: FingerState, names: tuple[str, ...]
    ) -> None:
        self.share, self.radius, self.last, self.names = share, radius, fs, names
        self.slip = np.zeros(fs.active.shape[0])

    def step(self, fs: FingerState, when: str) -> None:
        self.slip += finger_slip(self.last, fs)
        self.last = fs
        touching = fs.active.any(axis=1)
        if not touching.all():
            raise _NotHeld(f"the {self.names[int(np.argmin(touching))]} finger lost contact {when}")
        limit = self.share * self.radius
        if (self.slip > limit).any():
            j = int(np.argmax(self.slip - limit))
            raise _NotHeld(
                f"the {self.names[j]} fingertip slid {self.slip[j] * 1e3:.2f} mm in the object {when} "
                f"(limit {limit[j] * 1e3:.2f} mm, {self.share:.1%} of its "
                f"{self.radius[j] * 1e3:.2f} mm contact radius)"
            )


def check_hold(
    body: Body,
    table: PlaneContact,
    fc: FingertipContact,
    state: State,
    t: float,
    cfg: PlanConfig,
    cache: SolverCache,
) -> Held | str:
    """Remove the table and verify that the fingers hold the object. From the squeezed state at
    rest on the table, with the fingertips fixed: the table's forces on the object, applied as a
    dead load, ramp down to zero over ``RELEASE_STEPS`` static load steps (the weight passes to the
    fingers quasi-statically, as in a slow lift, friction sticking or slipping pair by pair); then
    ``hold_time`` seconds of implicit dynamics (:func:`_simulate_hold`) from that released state
    (a release step that needs more than ``RELEASE_MAX_ITER`` Newton iterations, or goes
    ``RELEASE_PATIENCE`` of them without a lower unbalanced force, finds none);
    then the held state's static equilibrium in the fingers alone. After every step each finger
    must touch the object and each fingertip's slip so far (:func:`finger_slip`, summed) must stay
    within ``cfg.max_slip`` times its contact radius at the start
    (:func:`~softgrasp.grasp.damage.contact_radii` of its normal force there). A step that finds no
    equilibrium means the object slides out of the fingers. Returns the :data:`Held` state or,
    when the object is not held, why not (a sentence)."""
    fixed = FingertipContact(
        tuple(replace(f, centre=f.centre_at(t), velocity=np.zeros(3)) for f in fc.fingertips),
        fc.params,
        name=fc.name,
    )
    support = RampedLoad(table.static_forces(body, state.x, t, state.contacts[0]), state.x, name="support")
    release = Scene(body, (fixed, support))
    scene = Scene(body, (fixed,))
    c0 = centre_of_mass(body, state.x)
    normal = fc.report(body, state.x, None, t, state.contacts[1], static=True).normal
    radius = contact_radii(body, fc, normal, t)
    track = _Tracker(cfg.max_slip, radius, state.contacts[1], tuple(f.name for f in fc.fingertips))
    drift = 0.0
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
            when = f"with the table's support down to {1 - k / RELEASE_STEPS:.0%}"
            try:
                st, _ = solve_static(
                    release,
                    st,
                    t=k / RELEASE_STEPS,
                    cache=cache,
                    guess=guess,
                    rtol=rtol,
                    max_iter=RELEASE_MAX_ITER,
                    patience=RELEASE_PATIENCE,
                )
            except (NotConverged, SimulationUnstable) as exc:
                raise _NotHeld(
                    f"the object slides out of the fingers {when} (no equilibrium: {diagnosis(exc)})"
                ) from exc
            track.step(st.contacts[0], when)
            drift = max(drift, float(np.linalg.norm(centre_of_mass(body, st.x) - c0)))
        start = State(st.x, np.zeros_like(st.x), 0.0, (st.contacts[0],))
        end = _simulate_hold(body, scene, start, cfg.hold_time, cache, track)
        drift = max(drift, float(np.linalg.norm(centre_of_mass(body, end.x) - c0)))
        try:
            held, _ = solve_static(scene, replace(end, t=0.0), t=0.0, cache=cache, rtol=HELD_RTOL)
        except (NotConverged, SimulationUnstable) as exc:
            raise _NotHeld(
                f"the object slides out of the fingers after the hold (no equilibrium: {diagnosis(exc)})"
            ) from exc
        track.step(held.contacts[0], "at the held equilibrium")
    except _NotHeld as why:
        return str(why)
    drift = max(drift, float(np.linalg.norm(centre_of_mass(body, held.x) - c0)))
    return held, fixed, drift, track.slip


def cone_usage(rep: FingerReport, mu: float) -> NDArray[np.float64]:
    """Each finger's resultant friction force over mu times its resultant normal force, (3,): 1
    when the whole fingertip slides (every pair at its Coulomb limit, all in one direction), below
    1 when it sticks. Pairs at the rim of a contact patch may slip while the fingertip sticks
    (partial slip, as in Mindlin's contact): they do not make the grasp let go."""
    if mu <= 0:
        return np.ones(len(rep.normal))
    return rep.tangential / np.maximum(mu * rep.normal, 1e-300)


def _simulate_hold(
    body: Body, scene: Scene, state: State, duration: float, cache: SolverCache, track: _Tracker
) -> State:
    """``duration`` seconds of backward Euler from ``state``: steps of ``HOLD_DT``, doubled after
    every step in which the centre of mass moved less than ``SETTLED`` (the object has come to
    rest: larger steps then cost nothing in accuracy), halved where a step finds no solution (a
    sudden slip), down to ``HOLD_DT / 2**MAX_HALVINGS``: below that the object slides out of the
    fingers. ``track`` follows the fingertips' slip after every step (and ends the check as soon
    as the object is not held)."""
    dt = HOLD_DT
    while state.t < duration - 1e-12:
        h = min(dt, duration - state.t)
        before = centre_of_mass(body, state.x)
        when = f"{state.t + h:.3g} s into the {duration:g} s hold"
        try:
            state = implicit_euler_step(scene, state, h, cache=cache)
        except (NotConverged, SimulationUnstable) as exc:
            if h <= HOLD_DT / 2**MAX_HALVINGS:
                raise _NotHeld(
                    f"the object slides out of the fingers {when} (no solution: {diagnosis(exc)})"
                ) from exc
            dt = h / 2.0  # a sudden slip or release: resolve it in shorter steps
            continue
        track.step(state.contacts[0], when)
        if np.linalg.norm(centre_of_mass(body, state.x) - before) < SETTLED:
            dt *= 2.0
    return state
