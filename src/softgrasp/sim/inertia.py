"""The inertia term of a backward Euler step, as a static interaction.

A backward Euler step of size dt from (x0, v0) balances the scene's forces and
``-m (x - x_pred) / dt^2``, a spring of stiffness m_i / dt^2 pulling each node towards its
predicted position ``x_pred = x0 + dt v0``. Written as an interaction, the static solver handles
it with every other (:mod:`softgrasp.sim.implicit` steps in time with it;
:func:`softgrasp.sim.static.proximal_solve` uses it to hold a static solve's iterates).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.physics.body import Body
from softgrasp.physics.forces import assemble_blocks

__all__ = ["Inertia"]


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
