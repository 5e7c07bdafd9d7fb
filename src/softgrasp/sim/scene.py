"""A scene: one body plus the rigid things that touch it, and the simulation state.

The :class:`Scene` is the static model (brax-style ``System``); :class:`State` is what changes.
Every interaction (table, plates, and later fingertips) implements the small
:class:`Interaction` protocol, so integrators and the static solver treat them alike.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.physics.body import Body
from softgrasp.physics.forces import gravity_forces

__all__ = ["Interaction", "Scene", "State"]


class Interaction(Protocol):
    """Something that pushes on the body's nodes and may carry friction state.

    Optional members the static solver uses where an interaction has them:
    ``jacobian_diagonal(body, x, t, state) -> (nodes (K,), blocks (K, 3, 3))``, its Jacobian when
    it couples no two nodes (each node at most once), added to the Newton matrix without a sparse
    matrix; ``symmetric_jacobian = False`` when :meth:`jacobian` is only a symmetric
    approximation (the solver then also differentiates :meth:`static_forces`), and
    ``pinned_static_forces`` to do that with the touching pairs held fixed; ``static_begin(body,
    x, t, state)``, the state at the start of each Newton pass (the table's limits),
    ``refresh(body, x, t, state)``, the state between Newton steps where it differs from the
    static update, and ``static_finish(body, x, t, state)``, the state once the solve ends (the
    table's slip return).
    """

    @property
    def name(self) -> str:
        """Label of the interaction."""
        ...

    def init_state(self, body: Body, x: NDArray[np.float64], t: float = 0.0) -> Any: ...

    def forces(
        self, body: Body, x: NDArray[np.float64], v: NDArray[np.float64], t: float, state: Any
    ) -> NDArray[np.float64]: ...

    def static_forces(
        self, body: Body, x: NDArray[np.float64], t: float, state: Any
    ) -> NDArray[np.float64]: ...

    def energy(self, body: Body, x: NDArray[np.float64], t: float, state: Any) -> float: ...

    def jacobian(self, body: Body, x: NDArray[np.float64], t: float, state: Any) -> sp.csr_matrix: ...

    def update(
        self, body: Body, x: NDArray[np.float64], v: NDArray[np.float64], t: float, state: Any
    ) -> Any: ...

    def stiffness_bound(self, body: Body) -> NDArray[np.float64]: ...

    def damping_bound(self, body: Body) -> NDArray[np.float64]: ...


@dataclass(frozen=True)
class State:
    """What changes during a simulation.

    Attributes
    ----------
    x: node positions [m], (N, 3).
    v: node velocities [m/s], (N, 3).
    t: time [s].
    contacts: one state per interaction of the scene, in the same order.
    """

    x: NDArray[np.float64]
    v: NDArray[np.float64]
    t: float = 0.0
    contacts: tuple[Any, ...] = field(default=())

    def replace(self, **kw: Any) -> State:
        """A copy with fields replaced."""
        return replace(self, **kw)


@dataclass(frozen=True, eq=False)
class Scene:
    """A body, gravity, and the interactions acting on it."""

    body: Body
    interactions: tuple[Interaction, ...] = ()

    def frozen(self, t: float) -> Scene:
        """The scene with each interaction's time-dependent data held at time t, for interactions
        that have any (a ``frozen(body, t)`` method: the fingertips' contact law)."""
        inter = tuple(i.frozen(self.body, t) if hasattr(i, "frozen") else i for i in self.interactions)
        return replace(self, interactions=inter)

    def initial_state(
        self, x: NDArray[np.float64] | None = None, v: NDArray[np.float64] | None = None, t: float = 0.0
    ) -> State:
        """State at rest in the mesh configuration (or at ``x``, ``v``), contacts initialised."""
        x0 = np.array(self.body.mesh.points if x is None else x, dtype=np.float64)
        v0 = np.zeros_like(x0) if v is None else np.array(v, dtype=np.float64)
        contacts = tuple(i.init_state(self.body, x0, t) for i in self.interactions)
        return State(x0, v0, t, contacts)

    def forces(
        self, x: NDArray[np.float64], v: NDArray[np.float64], t: float, contacts: tuple[Any, ...]
    ) -> NDArray[np.float64]:
        """Total force on every node [N], (N, 3): internal, damping, gravity, interactions."""
        b = self.body
        f = b.internal_forces(x, v) + gravity_forces(b.mass, b.gravity)
        for inter, st in zip(self.interactions, contacts, strict=True):
            f += inter.forces(b, x, v, t, st)
        return f

    def static_forces(
        self,
        x: NDArray[np.float64],
        t: float,
        contacts: tuple[Any, ...],
        internal: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        """Total force at rest with sticking friction: minus the gradient of :meth:`energy`.
        ``internal``: the body's internal forces at ``x`` where the caller has them already."""
        b = self.body
        f = (b.internal_forces(x) if internal is None else internal) + gravity_forces(b.mass, b.gravity)
        for inter, st in zip(self.interactions, contacts, strict=True):
            f += inter.static_forces(b, x, t, st)
        return f

    def energy(self, x: NDArray[np.float64], t: float, contacts: tuple[Any, ...]) -> float:
        """Total potential energy [J]: elastic, gravitational, contact penalty and stick springs."""
        b = self.body
        e = b.internal_energy(x) - float(np.sum(b.mass * (x @ b.gravity)))
        for inter, st in zip(self.interactions, contacts, strict=True):
            e += inter.energy(b, x, t, st)
        return e

    def jacobian(self, x: NDArray[np.float64], t: float, contacts: tuple[Any, ...]) -> sp.csr_matrix:
        """``d static_forces / d x``, sparse (3N, 3N)."""
        J = self.body.internal_jacobian(x)
        for inter, st in zip(self.interactions, contacts, strict=True):
            J = J + inter.jacobian(self.body, x, t, st)
        return J.tocsr()

    def update_contacts(
        self, x: NDArray[np.float64], v: NDArray[np.float64], t: float, contacts: tuple[Any, ...]
    ) -> tuple[Any, ...]:
        """Friction states after an accepted step or static solve."""
        return tuple(
            i.update(self.body, x, v, t, st) for i, st in zip(self.interactions, contacts, strict=True)
        )

    def begin_static(self, x: NDArray[np.float64], t: float, contacts: tuple[Any, ...]) -> tuple[Any, ...]:
        """Contact states at the start of a Newton pass of a static solve (``static_begin`` where
        an interaction defines it, else as they are)."""
        return tuple(
            inter.static_begin(self.body, x, t, st) if hasattr(inter, "static_begin") else st
            for inter, st in zip(self.interactions, contacts, strict=True)
        )

    def finish_static(self, x: NDArray[np.float64], t: float, contacts: tuple[Any, ...]) -> tuple[Any, ...]:
        """Contact states at the end of a static solve (``static_finish`` where an interaction
        defines it, else as they are)."""
        return tuple(
            inter.static_finish(self.body, x, t, st) if hasattr(inter, "static_finish") else st
            for inter, st in zip(self.interactions, contacts, strict=True)
        )

    def refresh_contacts(
        self, x: NDArray[np.float64], t: float, contacts: tuple[Any, ...]
    ) -> tuple[Any, ...]:
        """Light state refresh between Newton steps of a static solve: ``refresh`` where an
        interaction defines it, else its static update."""
        out = []
        for inter, st in zip(self.interactions, contacts, strict=True):
            if hasattr(inter, "refresh"):
                out.append(inter.refresh(self.body, x, t, st))
            else:
                out.append(self._static_update(inter, x, t, st))
        return tuple(out)

    def _static_update(self, inter: Interaction, x: NDArray[np.float64], t: float, st: Any) -> Any:
        if hasattr(inter, "static_update"):
            return inter.static_update(self.body, x, t, st)
        return inter.update(self.body, x, np.zeros_like(x), t, st)

    def static_update_contacts(
        self, x: NDArray[np.float64], t: float, contacts: tuple[Any, ...]
    ) -> tuple[Any, ...]:
        """Contact states after a static solve pass (``static_update`` where an interaction
        defines one, else ``update`` at rest)."""
        return tuple(
            self._static_update(i, x, t, st) for i, st in zip(self.interactions, contacts, strict=True)
        )

    def kinetic_energy(self, v: NDArray[np.float64]) -> float:
        """Kinetic energy [J]."""
        return 0.5 * float(np.sum(self.body.mass * np.einsum("ij,ij->i", v, v)))

    def interaction(self, name: str) -> tuple[int, Interaction]:
        """Index and object of the interaction called ``name``."""
        for i, inter in enumerate(self.interactions):
            if inter.name == name:
                return i, inter
        raise KeyError(f"no interaction named {name!r}; have {[i.name for i in self.interactions]}")
