"""Paper step 2 (Sec. 2 and 4.3.2), the closing: from the initial grasp the three fingertips
advance together in increments along straight lines towards the centroid of the contact triangle,
the object coming to rest after each; the first increment at which the grasp test passes is
bisected for the smallest travel that passes it, and from there the hold is verified
(:func:`~softgrasp.grasp.hold.check_hold`), the fingers closing further until it holds.

Per increment: the object, standing on the table, is brought to static equilibrium with its
fingertip contacts (quasi-static: :func:`softgrasp.sim.static.solve_increment`; dynamic: explicit
RK4 through the increment at the closing speed, then that static solve). Then the grasp test of
Sec. 3.5 (Eq. 21-22 with friction cones, :func:`~softgrasp.grasp.equilibrium.squeeze_utilisation`):
can normal forces no larger than each finger's current one, with friction inside the cones
|f_t| <= mu f_n, hold ``safety_factor`` times the weight in force and torque? (On the table the
fingers' normal forces need not balance among themselves; lifted, the object shifts until they do.)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import InfeasibleGrasp, NotConverged
from softgrasp.grasp.config import STEP_RTOL, PlanConfig
from softgrasp.grasp.equilibrium import squeeze_utilisation
from softgrasp.grasp.hold import check_hold
from softgrasp.grasp.initial import FINGER_NAMES
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
    frames: (travel, positions, fingertip centres, fingertip forces) at the start and after each
        increment, in the order simulated.
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
            Fingertip(cfg.fingertip_radius, centre=start[j], velocity=u[j], name=FINGER_NAMES[j])
            for j in range(3)
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
        self.frames: list[tuple[float, NDArray, NDArray, NDArray]] = [
            (0.0, xs.copy(), self.fingers.centres(0.0), np.zeros((3, 3)))
        ]
        self.checks: list[tuple[float, str]] = []

    def close(self, start: State, t: float, guess: NDArray | None = None) -> tuple[State, bool]:
        """Close to travel t from ``start``, record the increment and apply the grasp test (the
        squeeze-utilisation LP). Returns (state at rest, whether the test passes)."""
        body, cfg, fc, s = self.body, self.cfg, self.fingers, self.scale
        st = _advance(self.scene, start, t * s, cfg, self.cache, guess)
        rep = fc.report(body, st.x, None, t * s, st.contacts[1], static=True)
        feasible = False
        if (rep.contacts > 0).all():
            pts, push, fn = fc.contact_frames(body, st.x, t * s, st.contacts[1])
            s_need = squeeze_utilisation(
                pts,
                push,
                fn,
                cfg.contact.mu,
                centre_of_mass(body, st.x),
                cfg.safety_factor * body.total_mass,
                body.gravity,
            )
            feasible = s_need <= 1.0
        self.rows.append(
            (
                t,
                np.maximum(t - self.setup.first_touch, 0.0),
                np.linalg.norm(rep.force, axis=1),
                rep.normal.copy(),
                rep.tangential.copy(),
                feasible,
            )
        )
        self.frames.append((t, st.x.copy(), fc.centres(t * s), rep.force.copy()))
        if self.progress is not None:
            self.progress(min(t / self.setup.max_travel, 1.0))
        return st, feasible

    def too_far(self, t: float) -> None:
        """Raise :class:`InfeasibleGrasp` if travel ``t`` [m] is past the largest allowed (the
        object would be crushed)."""
        max_travel, first = self.setup.max_travel, self.setup.first_touch
        if t > max_travel + 1e-12:
            cfg, checks = self.cfg, self.checks
            last = self.rows[-1][2] if self.rows else np.zeros(3)
            raise InfeasibleGrasp(
                f"no hold before the maximum squeeze ({(max_travel - first.max()) * 1e3:.1f} mm past "
                f"first contact, {cfg.max_squeeze:.0%} of the fingers' reach): finger forces reached "
                f"{', '.join(f'{v:.2f}' for v in last)} N with mu = {cfg.contact.mu:g}"
                + (f" (last hold check at {checks[-1][0] * 1e3:.2f} mm: {checks[-1][1]})" if checks else "")
                + "; raise the friction coefficient, or grasp a lighter or stiffer object"
            )

    def until_the_grasp_test(self) -> tuple[State, float]:
        """Whole steps until the grasp test passes, then the last step bisected ``refine`` times
        on that test for the smallest travel that passes it (stiff objects gain force fast within
        one step). Returns (the state there, its travel [m])."""
        cfg = self.cfg
        k = 0
        feasible, before, earlier, state = False, self.start, self.start, self.start
        while not feasible:
            k += 1
            self.too_far(k * cfg.step)
            earlier, before = before, state
            # Newton starts from the last two increments' positions extrapolated (equal steps of
            # travel): about one iteration fewer per increment than from the last rest.
            guess = None if k < 2 else extrapolated(before.x, earlier.x)
            state, feasible = self.close(before, k * cfg.step, guess)
        t_hi = k * cfg.step
        if k > 1:
            lo, lo_state = (k - 1) * cfg.step, before
            for _ in range(cfg.refine):
                mid = 0.5 * (lo + t_hi)
                # Newton starts from the bracket's midpoint.
                st, ok = self.close(lo_state, mid, 0.5 * (lo_state.x + state.x))
                if ok:
                    t_hi, state = mid, st
                else:
                    lo, lo_state = mid, st
        return state, t_hi

    def until_held(self, state: State, t: float) -> tuple[float, tuple[State, FingertipContact, float]]:
        """From ``state`` at travel ``t``, remove the table and verify the hold there (the
        expensive check: implicit dynamics). Where the object is not held, the fingers close
        further, by the refined resolution at first and by doubling amounts up to a whole step,
        until it is. Returns (the travel held at [m], :func:`~softgrasp.grasp.hold.check_hold`'s
        held state, fixed fingers and drift)."""
        cfg, cache = self.cfg, self.cache
        t_final, extra = t, cfg.step / 2**cfg.refine

        def checked(t: float) -> tuple[State, FingertipContact, float] | str:
            before = cache.stats["systems"]
            out = check_hold(self.body, self.setup.table, self.fingers, state, t, cfg, cache)
            cache.stats["hold_check_systems"] += cache.stats["systems"] - before
            return out

        cache.stats["hold_check_systems"] = 0
        while isinstance(held := checked(t_final * self.scale), str):
            self.checks.append((t_final, held))
            t_final += extra
            self.too_far(t_final)
            state, _ = self.close(state, t_final)
            extra = min(2.0 * extra, cfg.step)
        self.checks.append((t_final, "held"))
        return t_final, held


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
