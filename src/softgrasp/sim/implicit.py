"""Backward (implicit) Euler steps through the static Newton solver.

One step of size dt from (x0, v0) solves ``M (x1 - x0 - dt v0) / dt^2 = f(x1)`` and sets
``v1 = (x1 - x0) / dt``: the static balance of the scene's forces plus an *inertia* term, a
spring of stiffness m_i / dt^2 pulling each node towards its predicted position x0 + dt v0
(:class:`Inertia`). So every interaction the static solver handles (contacts with friction
advanced by stick predictor and slip return) works here too, and the step size is limited by
accuracy, not by the stiffest spring: softgrasp uses it for long, slow phases such as holding a
grasped object for a second, where the explicit stable step (~1e-5 s on the rubber sphere with
fingertips) would need ~1e5 steps. Backward Euler damps high frequencies (numerical dissipation);
it is meant for motions slow compared with dt, not for wave dynamics or impacts.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from softgrasp.errors import ConfigError
from softgrasp.linalg.solve import SolverCache
from softgrasp.sim.inertia import Inertia
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import solve_static

__all__ = ["Inertia", "implicit_euler_step", "simulate_implicit"]


def implicit_euler_step(scene: Scene, state: State, dt: float, *, cache: SolverCache | None = None) -> State:
    """One backward Euler step of size ``dt`` [s] (the scene's load parameter advances with time).

    Raises NotConverged when Newton finds no solution (then try a smaller dt)."""
    if not dt > 0:
        raise ConfigError(f"implicit time step dt = {dt} s must be > 0")
    x0 = state.x
    inertia = Inertia(x0 + dt * state.v, dt)
    step_scene = Scene(scene.body, (*scene.interactions, inertia))
    start = State(x0, state.v, state.t, (*state.contacts, None))
    # Newton starts from the explicit prediction x0 + dt v (the inertia's own target).
    new, _ = solve_static(step_scene, start, t=state.t + dt, cache=cache, guess=x0 + dt * state.v)
    return State(new.x, (new.x - x0) / dt, state.t + dt, new.contacts[:-1])


def simulate_implicit(
    scene: Scene,
    state: State,
    t_end: float,
    dt: float,
    *,
    callback: Callable[[State], None] | None = None,
    cache: SolverCache | None = None,
) -> State:
    """Backward Euler from ``state.t`` to ``t_end`` in equal steps of at most ``dt``."""
    if not (np.isfinite(dt) and dt > 0):
        raise ConfigError(f"implicit time step dt = {dt} s must be a finite number > 0")
    span = t_end - state.t
    if not span >= 0:
        raise ConfigError(f"t_end = {t_end} s lies before the start time {state.t} s")
    if callback is not None:
        callback(state)
    if span == 0:
        return state
    n = max(1, int(np.ceil(span / dt - 1e-9)))
    h = span / n
    cache = cache if cache is not None else SolverCache()
    for _ in range(n):
        state = implicit_euler_step(scene, state, h, cache=cache)
        if callback is not None:
            callback(state)
    return state
