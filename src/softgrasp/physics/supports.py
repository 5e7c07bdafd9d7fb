"""Weak tether springs that hold rigid motions an experiment leaves free.

A frictionless compression test leaves the body free to slide sideways and spin about the loading
axis; a static solve then has a singular stiffness. Tethering every node to its rest position along
chosen axes with a spring ``ratio`` times the node's own stiffness (default 1e-6) removes the
singularity. Under a symmetric load the tethers carry no net force; their total force is available
to check that (:meth:`Tether.total_force`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.errors import ContactError
from softgrasp.physics.body import Body
from softgrasp.physics.forces import assemble_blocks

__all__ = ["Tether"]


@dataclass(frozen=True)
class Tether:
    """Weak springs from every node to its rest position along ``axes`` (subset of ``"xyz"``)."""

    axes: str = "xy"
    ratio: float = 1e-6
    name: str = "tether"

    def __post_init__(self) -> None:
        if not self.axes or set(self.axes) - set("xyz"):
            raise ContactError(f"tether axes must be letters of 'xyz', got {self.axes!r}")
        if not 0 < self.ratio < 1e-2:
            raise ContactError(f"tether ratio must lie in (0, 0.01), got {self.ratio}")

    def _k(self, body: Body) -> NDArray[np.float64]:
        mask = np.array([a in self.axes for a in "xyz"], dtype=float)
        return (self.ratio * body.node_stiffness)[:, None] * mask[None, :]

    def init_state(self, body: Body, x: NDArray[np.float64], t: float = 0.0) -> None:
        return None

    def static_forces(self, body: Body, x: NDArray[np.float64], t: float, state: None) -> NDArray[np.float64]:
        return -self._k(body) * (x - body.mesh.points)

    def forces(
        self, body: Body, x: NDArray[np.float64], v: NDArray[np.float64], t: float, state: None
    ) -> NDArray[np.float64]:
        return self.static_forces(body, x, t, state)

    def energy(self, body: Body, x: NDArray[np.float64], t: float, state: None) -> float:
        return 0.5 * float(np.sum(self._k(body) * (x - body.mesh.points) ** 2))

    def jacobian(self, body: Body, x: NDArray[np.float64], t: float, state: None) -> sp.csr_matrix:
        idx = np.arange(body.n_nodes)
        blocks = -self._k(body)[:, :, None] * np.eye(3)[None]
        return assemble_blocks(body.n_nodes, idx, idx, blocks)

    def update(
        self, body: Body, x: NDArray[np.float64], v: NDArray[np.float64], t: float, state: None
    ) -> None:
        return None

    def stiffness_bound(self, body: Body) -> NDArray[np.float64]:
        return self._k(body).max(axis=1)

    def damping_bound(self, body: Body) -> NDArray[np.float64]:
        return np.zeros(body.n_nodes)

    def total_force(self, body: Body, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Net force [N] the tethers exert on the body, (3,)."""
        return self.static_forces(body, x, 0.0, None).sum(axis=0)
