"""Dead loads: fixed nodal forces scaled by the load parameter, as a scene interaction.

Used to take a support away gradually: the forces a table exerts on an object at rest, applied as
a dead load that ramps down to zero over a few static load steps, hand the object's weight over
to the fingers quasi-statically (as a slow lift does) instead of all at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.physics.body import Body

__all__ = ["RampedLoad"]


@dataclass(frozen=True, eq=False)
class RampedLoad:
    """Nodal forces ``s(t) F`` [N] with the factor s going linearly from ``start`` at ``t0`` to
    ``end`` at ``t1`` (constant outside). Conservative: its energy is ``-s(t) F . (x - x_ref)``.

    Attributes
    ----------
    load: F, (N, 3) [N].  x_ref: reference positions of the energy [m], (N, 3).
    t0, t1: ramp interval of the load parameter.  start, end: factors at t0 and t1.
    """

    load: NDArray[np.float64]
    x_ref: NDArray[np.float64]
    t0: float = 0.0
    t1: float = 1.0
    start: float = 1.0
    end: float = 0.0
    name: str = "load"

    def factor(self, t: float) -> float:
        """s(t)."""
        if self.t1 <= self.t0:
            return self.end if t >= self.t1 else self.start
        a = min(max((t - self.t0) / (self.t1 - self.t0), 0.0), 1.0)
        return self.start + a * (self.end - self.start)

    def init_state(self, body: Body, x: NDArray[np.float64], t: float = 0.0) -> None:
        return None

    def static_forces(self, body: Body, x: NDArray[np.float64], t: float, state: None) -> NDArray[np.float64]:
        return self.factor(t) * self.load

    def forces(self, body: Body, x, v, t: float, state: None) -> NDArray[np.float64]:
        return self.factor(t) * self.load

    def energy(self, body: Body, x: NDArray[np.float64], t: float, state: None) -> float:
        return -self.factor(t) * float(np.sum(self.load * (x - self.x_ref)))

    def jacobian(self, body: Body, x: NDArray[np.float64], t: float, state: None) -> sp.csr_matrix:
        n = 3 * body.n_nodes
        return sp.csr_matrix((n, n))

    def update(self, body: Body, x, v, t: float, state: None) -> None:
        return None

    def stiffness_bound(self, body: Body) -> NDArray[np.float64]:
        return np.zeros(body.n_nodes)

    def damping_bound(self, body: Body) -> NDArray[np.float64]:
        return np.zeros(body.n_nodes)
