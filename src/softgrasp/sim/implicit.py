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
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.errors import ConfigError
from softgrasp.linalg.solve import SolverCache
from softgrasp.physics.body import Body
from softgrasp.physics.forces import assemble_blocks
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import solve_static

__all__ = ["Inertia", "implicit_euler_step", "simulate_implicit"]


@dataclass(frozen=True, eq=False)
class Inertia:
    """The inertia term of a backward Euler step as a static interaction: ``-m (x - x_pred) / dt^2``."""

    x_pred: NDArray[np.float64]
    dt: float
    name: str = "inertia"

    def _k(self, body: Body) -> NDArray[np.float64]:
        return body.mass / self.dt**2

    def init_state(self, body: Body, x: NDArray[np.float64], t: float = 0.0) -> None:
        return None

    def static_forces(self, body: Body, x: NDArray[np.float64], t: float, state: None) -> NDArray[np.float64]:
        return -self._k(body)[:, None] * (x - self.x_pred)

    def forces(self, body: Body, x, v, t: float, state: None) -> NDArray[np.float64]:
        return self.static_forces(body, x, t, state)

    def energy(self, body: Body, x: NDArray[np.float64], t: float, state: None) -> float:
        return 0.5 * float(np.sum(self._k(body)[:, None] * (x - self.x_pred) ** 2))

    def jacobian_diagonal(
        self, body: Body, x: NDArray[np.float64], t: float, state: None
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """:meth:`jacobian` by its diagonal 3x3 blocks: (every node, ``-m / dt^2`` times I)."""
        return np.arange(body.n_nodes), -self._k(body)[:, None, None] * np.eye(3)[None]

    def jacobian(self, body: Body, x: NDArray[np.float64], t: float, state: None) -> sp.csr_matrix:
        idx, blocks = self.jacobian_diagonal(body, x, t, state)
        return assemble_blocks(body.n_nodes, idx, idx, blocks)

    def update(self, body: Body, x, v, t: float, state: None) -> None:
        return None

    def stiffness_bound(self, body: Body) -> NDArray[np.float64]:
        return self._k(body)

    def damping_bound(self, body: Body) -> NDArray[np.float64]:
        return np.zeros(body.n_nodes)


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
