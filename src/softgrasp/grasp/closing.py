"""Paper step 2 (Sec. 2 and 4.3.2), the closing: from the initial grasp the three fingertips
advance together in increments along straight lines towards the centroid of the contact triangle,
the object coming to rest after each: whole steps up to the first touch, then increments that
double the squeeze (:meth:`Closing.until_the_grasp_test`). Within the first increment at which
the grasp test passes, the travel where it first passes is solved for to a force tolerance; from
there the hold is verified (:func:`~softgrasp.grasp.hold.check_hold`): where the object is not
held, the fingers squeeze further by growing amounts until it is, and the travel where it is
first held is again solved for to that force tolerance. The set-points so depend on the physics,
not on the step.

Per increment: the object, standing on the table, is brought to static equilibrium with its
fingertip contacts (quasi-static: :func:`softgrasp.sim.static.solve_increment`; dynamic: explicit
RK4 through the increment at the closing speed, then that static solve). Then the grasp test of
Sec. 3.5 (Eq. 21-22 with friction cones, :func:`~softgrasp.grasp.equilibrium.squeeze_utilisation`):
the least fraction s of each finger's current normal force that, with friction inside the cones
|f_t| <= mu f_n, holds the weight in force and torque; the test passes at
s <= 1. (On the table the fingers' normal forces need not balance among themselves; lifted, the
object shifts until they do.) Since s scales the forces, a travel with s >= 1 / (1 + force_tol)
squeezes at most ``force_tol`` harder than the least squeeze that passes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import InfeasibleGrasp, NotConverged
from softgrasp.grasp.config import CONTACT_START, FIRST_GROWTH, STEP_RTOL, TOUCH_GAP, TRAVEL_FLOOR, PlanConfig
from softgrasp.grasp.damage import patch_torsion
from softgrasp.grasp.equilibrium import minimum_normal_forces, squeeze_utilisation
from softgrasp.grasp.hold import Held, check_hold
from softgrasp.grasp.settle import centre_of_mass
from softgrasp.grasp.setup import ClosingSetup
from softgrasp.linalg.solve import SolverCache
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import Fingertip
from softgrasp.sim.explicit import simulate
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import extrapolated, solve_increment

__all__ = ["Closing"]

#: One closing increment at rest: (travel [m], penetration per finger [m], force norm, normal and
#: tangential force per finger [N], whether the grasp test passed).
Row = tuple[float, NDArray, NDArray, NDArray, NDArray, bool]

#: A travel at rest on the table: (travel [m], the state there, its grasp test's s, the fingers'
#: summed normal force [N]).
Point = tuple[float, State, float, float]


class Closing:
    """The fingertips of one plan closing along their lines from ``setup``'s start, every
    increment at rest recorded.

    Attributes
    ----------
    fingers: the moving fingertips' contact (load parameter: travel [m] for the quasi-static
        solver, time [s] at the closing speed for the dynamic one; ``scale`` turns travel into it).
    scene: the object on the table with the fingertips.  start: the settled object, fingertips at
        their start.
    rows: each increment at rest (:data:`Row`), in the order simulated.
    frames: (travel, positions, fingertip centres, fingertip forces, the contact forces on the
        nodes) at the start and after each increment, in the order simulated.
    checks: every hold verification: (travel, ``"held"`` or why not).
    """

    def __init__(
        self,
        body: Body,
        cfg: PlanConfig,
        setup: ClosingSetup,
        cache: SolverCache,
        progress: Callable[[float], None] | None = None,
    ) -> None:
        self.body, self.cfg, self.setup, self.cache, self.progress = body, cfg, setup, cache, progress
        start, u, xs = setup.start, setup.directions, setup.settled.x
        unit_tips = tuple(
            Fingertip(cfg.fingertip_radius, centre=start[j], velocity=u[j], name=name)
            for j, name in enumerate(cfg.fingers)
        )
        # The load parameter of the scene: travel [m] for the quasi-static solver, time [s] at the
        # closing speed for the dynamic one.
        self.scale = 1.0 if cfg.solver == "quasistatic" else 1.0 / cfg.closing_speed
        tips = tuple(replace(tip, velocity=tip.velocity / self.scale) for tip in unit_tips)
        self.fingers = FingertipContact(tips, cfg.contact)
        self.scene = Scene(body, (setup.table, self.fingers))
        self.start = State(
            xs, np.zeros_like(xs), 0.0, (setup.settled.contacts[0], self.fingers.init_state(body, xs, 0.0))
        )
        self.rows: list[Row] = []
        self.frames: list[tuple[float, NDArray, NDArray, NDArray, NDArray]] = [
            (0.0, xs.copy(), self.fingers.centres(0.0), np.zeros((len(cfg.fingers), 3)), np.zeros_like(xs))
        ]
        self.checks: list[tuple[float, str]] = []
        self.last: Point = (0.0, self.start, math.inf, 0.0)

    def close(self, start: State, t: float, guess: NDArray | None = None) -> Point:
        """Close to travel t from ``start``, record the increment and apply the grasp test (the
        squeeze-utilisation LP). Returns the :data:`Point` at rest there."""
        body, cfg, fc, s = self.body, self.cfg, self.fingers, self.scale
        st = _advance(self.scene, start, t * s, cfg, self.cache, guess)
        rep = fc.report(body, st.x, None, t * s, st.contacts[1], static=True)
        need = math.inf
        if (rep.contacts > 0).all():
            pts, push, fn = fc.contact_frames(body, st.x, t * s, st.contacts[1])
            need = squeeze_utilisation(
                pts,
                push,
                fn,
                cfg.contact.mu,
                centre_of_mass(body, st.x),
                body.total_mass,
                body.gravity,
                torsion=patch_torsion(body, fc, fn, cfg.contact.mu),
            )
        self.rows.append(
            (
                t,
                np.maximum(t - self.setup.first_touch, 0.0),
                np.linalg.norm(rep.force, axis=1),
                rep.normal.copy(),
                rep.tangential.copy(),
                need <= 1.0,
            )
        )
        nodes = fc.static_forces(body, st.x, t * s, st.contacts[1])
        self.frames.append((t, st.x.copy(), fc.centres(t * s), rep.force.copy(), nodes))
        if self.progress is not None:  # the squeeze's way to the grasp test's passing (s <= 1)
            self.progress(min(max(t / self.setup.max_travel, 1.0 / need if need > 1.0 else 1.0), 1.0))
        self.last = (t, st, need, float(rep.normal.sum()))
        return self.last

    def _further(self, start: State, t: float, guess: NDArray | None = None) -> Point:
        """:meth:`close`, where a closing that finds no equilibrium ends the plan: the fingers
        cannot squeeze the object harder (they slide on it, or it buckles) before it is held.
        Where no rest is found at ``t``, the closing first tries half the increment and the whole
        increment further (from ``start``): Newton may find no rest at one travel where a node
        sits on the table's edge of contact (the object rocking on its bottom edge), and finds
        one a little further; only when those fail too does the plan end."""
        try:
            return self.close(start, t, guess)
        except NotConverged as exc:
            step = t - start.t / self.scale
            for ahead in (0.5 * step, step) if step > 0.0 else ():
                try:
                    self.too_far(t + ahead)
                    return self.close(start, t + ahead)
                except (NotConverged, InfeasibleGrasp):
                    continue
            raise InfeasibleGrasp(
                f"mu = {self.cfg.contact.mu:g} cannot hold the object: the closing found no equilibrium of "
                f"the squeezed object at {t * 1e3:.3g} mm of travel before it was held ({exc.diagnosis})"
                f"{self._rigid_need()[0]}; raise the friction coefficient, or grasp a lighter or stiffer "
                "object; where another --step or --mesh-size plans it (its increments pass other travels), "
                "the solver, not the friction, ended this closing"
            ) from exc

    def _rigid_need(self) -> tuple[str, bool]:
        """What the rigid-body LP (:func:`~softgrasp.grasp.equilibrium.minimum_normal_forces`)
        says of the last increment's contacts: the least normal force in all that holds the
        object if it were rigid, and what the fingers reached; and whether they reached more than
        that (then it is their proportions, not their sum, that do not hold)."""
        t, st, _, total = self.last
        body, cfg = self.body, self.cfg
        pts, push, fn = self.fingers.contact_frames(body, st.x, t * self.scale, st.contacts[1])
        if (fn <= 0).any():
            return "", False
        mu = cfg.contact.mu
        try:
            need = minimum_normal_forces(
                pts, push, mu, centre_of_mass(body, st.x), body.total_mass, body.gravity,
                torsion=patch_torsion(body, self.fingers, fn, mu),
            ).sum()
        except InfeasibleGrasp:
            none = f"; with mu = {mu:g} no normal forces at these contacts would hold even a rigid object"
            return none, False
        return (
            f"; mu = {mu:g} needs at least {need:.2f} N of normal force in all to hold even a rigid object "
            f"at these contacts, the fingers reached {total:.2f} N"
        ), bool(total > need)

    def too_far(self, t: float) -> None:
        """Raise :class:`InfeasibleGrasp` if travel ``t`` [m] is past the largest allowed (the
        object would be crushed)."""
        max_travel, first = self.setup.max_travel, self.setup.first_touch
        if t > max_travel + 1e-12:
            cfg, checks = self.cfg, self.checks
            last = self.rows[-1][2] if self.rows else np.zeros(len(self.cfg.fingers))
            need, excess = self._rigid_need() if self.rows else ("", False)
            more = f"allow more squeeze (--max-squeeze, now {cfg.max_squeeze:g})"
            if max(last, default=0.0) <= 0.0:
                advice = f"; {more}"
            elif excess:  # enough force in all, in proportions that do not hold
                advice = (
                    "; the fingers press more than a rigid object needs, but not in the proportions "
                    f"that hold it: {more}, raise the friction coefficient, or grasp elsewhere (--grasp)"
                )
            else:
                advice = f"; {more}, raise the friction coefficient, or grasp a lighter or stiffer object"
            raise InfeasibleGrasp(
                f"no hold before the maximum squeeze ({(max_travel - first.max()) * 1e3:.1f} mm past "
                f"first contact, {cfg.max_squeeze:.0%} of the fingers' reach): finger forces reached "
                f"{', '.join(f'{v:.2f}' for v in last)} N with mu = {cfg.contact.mu:g}"
                + (f" (last hold check at {checks[-1][0] * 1e3:.3g} mm: {checks[-1][1]})" if checks else "")
                + need
                + advice
            )

    def until_the_grasp_test(self) -> Point:
        """Increments until the grasp test passes, then the least travel that passes it, to the
        force tolerance (:meth:`_least_passing`). Returns its :data:`Point`.

        The fingertips approach in whole steps up to ``TOUCH_GAP`` before the first one touches;
        from there each increment at most doubles the travel past that touch (at least
        ``CONTACT_START`` times the fingertip radius, at most a whole step). The squeeze so
        passes through the same travels whatever the step, until the increments reach it: the
        friction anchors of the stick-slip contacts, set along that path, depend on the physics
        rather than on the step."""
        cfg = self.cfg
        touch = float(self.setup.first_touch.min())
        approach = touch - TOUCH_GAP
        start = CONTACT_START * cfg.fingertip_radius
        before, earlier, now = self.last, self.last, self.last
        while not now[2] <= 1.0:
            t = now[0]
            if t < approach:
                t_new = min(t + cfg.step, approach)
            else:
                t_new = t + min(cfg.step, max(t - touch, start))
            self.too_far(t_new)
            earlier, before = before, now
            # Newton starts from the last two increments' positions extrapolated: about one
            # iteration fewer per increment than from the last rest.
            guess = None
            if earlier is not before and before[0] > earlier[0]:
                guess = extrapolated(
                    before[1].x, earlier[1].x, (t_new - before[0]) / (before[0] - earlier[0])
                )
            now = self._further(before[1], t_new, guess)
        return self._least_passing(before, now)

    def _least_passing(self, lo: Point, hi: Point) -> Point:
        """Between ``lo`` (the grasp test fails) and ``hi`` (it passes), the travel where it first
        passes, to the force tolerance: regula falsi (Illinois) on g(t) = s(t)^(-2/3) - 1, aimed
        a half tolerance on the passing side (s^(-2/3) is nearly linear in travel where the forces
        grow as its 3/2 power, as Hertz's do), until the passing end's s >= 1 / (1 + force_tol),
        the bracket is narrower than ``TRAVEL_FLOOR`` or ``refine`` iterations are spent.
        Returns the passing end."""
        cfg = self.cfg
        accept = 1.0 / (1.0 + cfg.force_tol)
        aim = (1.0 + 0.5 * cfg.force_tol) ** (2.0 / 3.0) - 1.0

        def g(s: float) -> float:
            return (s ** (-2.0 / 3.0) if 0.0 < s < math.inf else 0.0) - 1.0 - aim

        touch = float(self.setup.first_touch.max())
        g_lo, g_hi, side = g(lo[2]), g(hi[2]), 0
        for _ in range(cfg.refine):
            if hi[2] >= accept or hi[0] - lo[0] < TRAVEL_FLOOR:
                break
            # While a finger does not touch at the lower end, the forces start from the last
            # finger's first touch (on the settled object) where that lies inside the bracket.
            t0 = min(max(lo[0], touch), hi[0]) if lo[2] == math.inf else lo[0]
            w = float(
                np.clip((t0 + g_lo / (g_lo - g_hi) * (hi[0] - t0) - lo[0]) / (hi[0] - lo[0]), 0.02, 0.98)
            )
            try:
                pt = self.close(lo[1], lo[0] + w * (hi[0] - lo[0]), self._between(lo, hi, w))
            except NotConverged:
                # No rest found there (a contact flickering on and off at the touch): halfway to
                # the passing end instead.
                w = 0.5 * (1.0 + w)
                pt = self._further(lo[1], lo[0] + w * (hi[0] - lo[0]), self._between(lo, hi, w))
            if pt[2] <= 1.0:
                hi, g_hi = pt, g(pt[2])
                g_lo *= 0.5 if side == 1 else 1.0
                side = 1
            else:
                lo, g_lo = pt, g(pt[2])
                g_hi *= 0.5 if side == -1 else 1.0
                side = -1
        return hi

    @staticmethod
    def _between(lo: Point, hi: Point, w: float) -> NDArray | None:
        """Newton's start for the travel a fraction w from ``lo`` to ``hi``: their positions
        interpolated, or None (from ``lo`` at rest) while a finger does not touch at ``lo``."""
        return lo[1].x + w * (hi[1].x - lo[1].x) if lo[2] < math.inf else None

    def _checked(self, pt: Point) -> Held | str:
        """The hold check at ``pt`` (its Newton systems counted apart), recorded in ``checks``."""
        cache = self.cache
        before = cache.stats["systems"]
        out = check_hold(
            self.body, self.setup.table, self.fingers, pt[1], pt[0] * self.scale, self.cfg, cache
        )
        cache.stats["hold_check_systems"] += cache.stats["systems"] - before
        self.checks.append((pt[0], out if isinstance(out, str) else "held"))
        return out

    def until_held(self, pt: Point) -> tuple[float, Held]:
        """From ``pt`` (the grasp test's least passing travel), remove the table and verify the
        hold there (the expensive check: implicit dynamics). Where the object is not held, the
        fingers squeeze further, each time by the travel that raises their force by
        ``FIRST_GROWTH`` and then by doubling shares (at most a whole step; Hertz's 3/2 power from
        the last finger's first touch), until it is; then the bracket between the last travel not
        held and the first held is halved until their forces differ by at most ``force_tol``.
        Returns (the travel held at [m], :func:`~softgrasp.grasp.hold.check_hold`'s held state)."""
        cfg = self.cfg
        self.cache.stats["hold_check_systems"] = 0
        held = self._checked(pt)
        if not isinstance(held, str):
            return pt[0], held
        lo, growth, touch = pt, FIRST_GROWTH, float(self.setup.first_touch.max())
        while True:
            past = max(lo[0] - touch, 1e-6)
            t = lo[0] + min(past * ((1.0 + growth) ** (2.0 / 3.0) - 1.0), cfg.step)
            self.too_far(t)
            hi = self._further(lo[1], t)
            held = self._checked(hi)
            if not isinstance(held, str):
                break
            lo, growth = hi, 2.0 * growth
        for _ in range(cfg.refine):
            if hi[3] <= (1.0 + cfg.force_tol) * lo[3] or hi[0] - lo[0] < TRAVEL_FLOOR:
                break
            mid = self._further(lo[1], 0.5 * (lo[0] + hi[0]), self._between(lo, hi, 0.5))
            out = self._checked(mid)
            if isinstance(out, str):
                lo = mid
            else:
                hi, held = mid, out
        return hi[0], held


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
        raise NotConverged(f"closing increment to {what} failed: {exc.diagnosis}", exc.advice) from exc
    return state
