"""Rigid planes touching the body's nodes: the table, and the plates of a compression test.

Normal force: a penalty spring-dashpot per node, ``f_n = max(0, k_c p - c_c v_n)`` with penetration
p = -(x - P)·n. Friction: the elastic-slider model of the paper's Algorithm 1 applied per node: a
tangential spring from the node to an *anchor* fixed on the plane (stick displacement v) gives
``f_t = -k_t v - c_t v_t``; when its norm would exceed ``mu f_n`` the node slips, the force is
``mu f_n`` along the trial direction and the anchor is dragged along (slip displacement u). Anchors
are created when a node touches the plane and dropped when it leaves. At rest (the static solver's
forces) the stick spring is ``mu f_n / s_e``, so that a node slips once it has moved its elastic
slip s_e from its anchor; within a static solve its stiffness stays that of the solve's first rest
(:meth:`PlaneContact.static_begin`).

:meth:`PlaneContact.forces` and :meth:`PlaneContact.update` run the law of
:mod:`softgrasp.physics.planes_compiled`, which the fused stepper calls too.

Stiffnesses are per node and proportional to the node's own elastic stiffness
(:attr:`softgrasp.physics.body.Body.node_stiffness`), so the contact is equally stiff on any mesh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.errors import ContactError
from softgrasp.physics.body import Body
from softgrasp.physics.forces import assemble_blocks

__all__ = ["Plane", "PlaneContact", "PlaneState"]


def _f64(a: NDArray) -> NDArray[np.float64]:
    return np.ascontiguousarray(a, dtype=np.float64)


@dataclass(frozen=True)
class Plane:
    """An infinite rigid plane moving at constant velocity.

    Attributes
    ----------
    point: a point of the plane at t = 0 [m], (3,).
    normal: unit normal pointing towards the body (the free side), (3,).
    velocity: plane velocity [m/s], (3,).
    """

    point: NDArray[np.float64]
    normal: NDArray[np.float64]
    velocity: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64)
        norm = float(np.linalg.norm(n))
        if not norm > 0:
            raise ContactError("plane normal must be a non-zero vector")
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "point", np.asarray(self.point, dtype=np.float64))
        object.__setattr__(self, "velocity", np.asarray(self.velocity, dtype=np.float64))

    def point_at(self, t: float) -> NDArray[np.float64]:
        """A point of the plane at time t [m]."""
        return self.point + t * self.velocity


#: A node's elastic slip at rest, as a fraction of its edges' mean length: how far it moves from
#: where it stuck before it slips (the regularisation of Coulomb's law finite-element codes use,
#: 0.5 % of the elements' size).
ELASTIC_SLIP = 0.005


def _stick_stiffness(body: Body, limit: NDArray[np.float64], nodes) -> NDArray[np.float64]:
    """Stick stiffness [N/m] of the nodes ``nodes`` (indices or a slice) whose Coulomb limits are
    ``limit`` [N]: the limit over the node's elastic slip (:data:`ELASTIC_SLIP` of its edges'
    mean length)."""
    return limit / (ELASTIC_SLIP * body.node_edge_length[nodes])


@dataclass(frozen=True)
class PlaneState:
    """Friction state of one plane: which nodes touch and their anchors.

    Attributes
    ----------
    active: nodes in contact at the last update, (N,) bool.
    anchor: anchor positions in the plane, relative to its moving point [m], (N, 3). A free node's
        anchor follows it, so that a node touching during a step sticks where it entered contact.
    cap: within a static solve, each node's Coulomb limit ``mu f_n`` [N] where the Newton pass
        began (NaN where it did not touch then), (N,); None outside one (the static forces then
        take it from the penetrations at hand).
    stick: within a static solve, from its first pass's rest on, each node's stick stiffness
        [N/m] (its limit there over its elastic slip; NaN where it did not touch there: its
        pass's limit over its elastic slip), (N,); None before and outside one.
    """

    active: NDArray[np.bool_]
    anchor: NDArray[np.float64]
    cap: NDArray[np.float64] | None = None
    stick: NDArray[np.float64] | None = None


@dataclass(frozen=True)
class PlaneContact:
    """Penalty contact with Coulomb friction between a plane and every node of the body.

    Parameters
    ----------
    plane: the plane.
    mu: friction coefficient (>= 0); 0 is frictionless.
    penalty: normal stiffness per node as a multiple of the node's elastic stiffness.
    damping_ratio: damping ratio of each node's penalty spring (with the node's mass).
    tangential_ratio: k_t / k_n.
    name: label (``table``, ``bottom``, ``top``).
    """

    plane: Plane
    mu: float = 0.5
    penalty: float = 50.0
    damping_ratio: float = 0.5
    tangential_ratio: float = 1.0
    name: str = "plane"

    def __post_init__(self) -> None:
        for k in ("mu", "penalty", "damping_ratio", "tangential_ratio"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v >= 0):
                raise ContactError(f"{self.name}: {k} = {v} is invalid; it must be >= 0")
        if self.penalty <= 0:
            raise ContactError(f"{self.name}: penalty must be > 0")

    # ------------------------------------------------------------------ parameters
    def stiffness(self, body: Body) -> NDArray[np.float64]:
        """Normal penalty stiffness per node [N/m], (N,)."""
        return self.penalty * body.node_stiffness

    def _coeffs(self, body: Body) -> tuple[NDArray[np.float64], ...]:
        k = self.stiffness(body)
        c = 2.0 * self.damping_ratio * np.sqrt(k * body.mass)
        return k, c, self.tangential_ratio * k, self.tangential_ratio * c

    def init_state(self, body: Body, x: NDArray[np.float64], t: float = 0.0) -> PlaneState:
        """State with every node's anchor at its current position (nodes already touching stick
        where they are)."""
        p0, n, pen = self._geometry(x, t)
        rel = x - p0
        anchor = rel - (rel @ n)[:, None] * n
        return PlaneState(active=pen > 0, anchor=anchor)

    def stiffness_bound(self, body: Body) -> NDArray[np.float64]:
        """Largest stiffness the contact may add to each node [N/m], (N,) (for time steps)."""
        k = self.stiffness(body)
        return k * max(1.0, self.tangential_ratio)

    def damping_bound(self, body: Body) -> NDArray[np.float64]:
        """Largest damping the contact may add to each node [N s/m], (N,)."""
        _, c, _, ct = self._coeffs(body)
        return np.maximum(c, ct)

    # ------------------------------------------------------------------ kernels
    def _geometry(self, x: NDArray[np.float64], t: float):
        p0 = self.plane.point_at(t)
        n = self.plane.normal
        pen = -(x - p0) @ n
        return p0, n, pen

    def forces(
        self, body: Body, x: NDArray[np.float64], v: NDArray[np.float64], t: float, state: PlaneState
    ) -> NDArray[np.float64]:
        """Contact forces on the nodes [N], (N, 3); slip is capped at ``mu f_n`` (Eq. 15-16)."""
        k, c, kt, ct = self._coeffs(body)
        from softgrasp.physics.planes_compiled import plane_forces

        out = np.zeros((len(x), 3))
        plane_forces(
            _f64(x), _f64(v), self.plane.point_at(t), self.plane.normal, self.plane.velocity,
            float(self.mu), k, c, kt, ct, _f64(state.anchor), 0, len(x), out,
        )  # fmt: skip
        return out

    def _static_law(
        self, body: Body, x: NDArray[np.float64], t: float, state: PlaneState, on: NDArray[np.int64]
    ):
        """The static law's terms at the nodes ``on`` (those on or beyond the plane): penalty
        stiffnesses, the normal, penetrations, tangential stretches from the anchors, Coulomb
        limits [N] (NaN: held without one, :meth:`static_begin`; NaN too where a node is not in
        the plane) and stick stiffnesses [N/m] (the state's frozen ones, else limit over elastic
        slip)."""
        p0, n, pen = self._geometry(x, t)
        k = self.stiffness(body)[on]
        s = x[on] - (p0 + state.anchor[on])
        pen = pen[on]
        cap = self.mu * k * pen if state.cap is None else state.cap[on]
        cap = np.where(pen > 0, cap, np.nan)
        stick = _stick_stiffness(body, cap, on)
        if state.stick is not None:
            stick = np.where(np.isnan(state.stick[on]), stick, state.stick[on])
        return k, n, pen, s - (s @ n)[:, None] * n, cap, stick

    def _static_touching(self, body: Body, x: NDArray[np.float64], t: float, state: PlaneState):
        """The touching nodes (the few a body stands on, not all N: only they carry force) and
        :meth:`_static_law` there."""
        _, _, pen = self._geometry(x, t)
        on = np.flatnonzero(pen > 0)
        return (on, *self._static_law(body, x, t, state, on))

    def static_begin(self, body: Body, x: NDArray[np.float64], t: float, state: PlaneState) -> PlaneState:
        """State at the start of a Newton pass of a static solve: each node's Coulomb limit
        ``mu f_n`` from its penetration at ``x``, where the pass starts (NaN where it does not
        touch).

        At rest the table holds each touching node by a stick spring up to Coulomb's limit, and
        beyond it the node slips, its force ``mu f_n`` against its stretch (Algorithm 1 at rest).
        The spring's stiffness is ``mu f_n / s_e`` at the rest of the solve's first pass: the
        node slips once it has moved about its elastic slip ``s_e`` (:data:`ELASTIC_SLIP` of its
        edges' length, as finite-element codes regularise Coulomb's law) from where it stuck,
        whatever its load, so that the kink of the law lies at a scale Newton's steps resolve and
        a node with no normal force holds nothing. Within a pass the limits stay as they were at
        its start (Tresca's law: the forces are minus the gradient of :meth:`energy`, a
        potential), and a node that touches only during the pass is held by the penalty-scaled
        spring ``k_t`` without a limit; after the pass (:meth:`static_update`) the limits are
        taken again at the rest, and the static solver repeats passes until the forces balance
        under them. (Without a limit, a node at the edge of the contact patch can hold a
        tangential force with no normal force, and where balance needs the table to pull it down
        no rest exists: a soft, heavy ball's closing found none.) The stick stiffnesses stay those
        of the first pass's rest for the rest of the solve (:meth:`static_update`): were they to
        follow the normal forces from pass to pass, a ball rolling a little on the table would load
        the nodes its stick forces already push it towards, and roll on (the passes of a fine
        sphere's settle drifted so by 1 % each, and found no rest)."""
        _, _, pen = self._geometry(x, t)
        cap = np.where(pen > 0, self.mu * self.stiffness(body) * np.maximum(pen, 0.0), np.nan)
        return replace(state, cap=cap)

    def _friction(
        self,
        k: NDArray[np.float64],
        s: NDArray[np.float64],
        cap: NDArray[np.float64],
        stick: NDArray[np.float64],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]:
        """Per touching node (penalty stiffness k, stretch s, limit cap or NaN, stick stiffness):
        the stretch's length [m], the limit (0 for NaN) [N], whether it slips, and the friction's
        secant stiffness [N/m] (its force over its stretch)."""
        r = np.linalg.norm(s, axis=1)
        new = np.isnan(cap)
        c = np.where(new, 0.0, cap)
        kt = np.where(new, 0.0, stick)
        slips = ~new & (kt * r > c)
        secant = np.where(new, self.tangential_ratio * k, np.where(slips, c / np.maximum(r, 1e-300), kt))
        return r, c, slips, secant

    def energy(self, body: Body, x: NDArray[np.float64], t: float, state: PlaneState) -> float:
        """Potential [J] of the normal penalty springs and of the friction: ``K |s|^2 / 2`` while
        a node sticks, ``c (|s| - c / (2 K))`` once it slips (c its limit, K its stick
        stiffness; ``k_t |s|^2 / 2`` for a node held without a limit)."""
        on, k, _, pen, s, cap, stick = self._static_touching(body, x, t, state)
        e = 0.5 * float(np.sum(k * pen**2))
        if self.mu > 0:
            r, c, slips, secant = self._friction(k, s, cap, stick)
            e += float(
                np.sum(np.where(slips, c * (r - 0.5 * c / np.maximum(stick, 1e-300)), 0.5 * secant * r**2))
            )
        return e

    def static_forces(
        self, body: Body, x: NDArray[np.float64], t: float, state: PlaneState
    ) -> NDArray[np.float64]:
        """Forces at rest [N], (N, 3): penalty normal force and the elastic-slider friction of
        touching nodes against their stretch, at most ``mu f_n`` (Eq. 15-16 at rest; minus the
        gradient of :meth:`energy`)."""
        on, k, n, pen, s, cap, stick = self._static_touching(body, x, t, state)
        f = np.zeros(x.shape)
        f[on] = (k * pen)[:, None] * n
        if self.mu > 0:
            _, _, _, secant = self._friction(k, s, cap, stick)
            f[on] -= secant[:, None] * s
        return f

    def jacobian_diagonal(
        self, body: Body, x: NDArray[np.float64], t: float, state: PlaneState
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """:meth:`jacobian` by its non-zero diagonal 3x3 blocks (the plane couples no two nodes):
        (the nodes on or beyond the plane (K,), their blocks (K, 3, 3)); every other block is zero.
        Friction: the stick stiffness where a node sticks; where it slips ``mu f_n / |s|`` across
        its stretch and none along it (the Hessian of :meth:`energy`)."""
        _, _, pen = self._geometry(x, t)
        # A node exactly on the plane counts: the penalty's one-sided derivative there is k, and a
        # body resting on the plane must not look unsupported to Newton's method (nor slide); it
        # has no limit yet: held by k_t, as one touching anew.
        on = np.flatnonzero(pen >= 0)
        k, n, _, s, cap, stick = self._static_law(body, x, t, state, on)
        nn = np.outer(n, n)
        blocks = -k[:, None, None] * nn[None]
        if self.mu > 0:
            r, _, slips, secant = self._friction(k, s, cap, stick)
            u = s / np.maximum(r, 1e-300)[:, None]
            along = np.where(slips[:, None, None], np.einsum("ki,kj->kij", u, u), 0.0)
            blocks = blocks - secant[:, None, None] * ((np.eye(3) - nn)[None] - along)
        return on, blocks

    def jacobian(self, body: Body, x: NDArray[np.float64], t: float, state: PlaneState) -> sp.csr_matrix:
        """``d f / d x`` of :meth:`static_forces` (block diagonal), sparse (3N, 3N)."""
        on, blocks = self.jacobian_diagonal(body, x, t, state)
        return assemble_blocks(body.n_nodes, on, on, blocks)

    def update(
        self, body: Body, x: NDArray[np.float64], v: NDArray[np.float64], t: float, state: PlaneState
    ) -> PlaneState:
        """Advance the friction state after an accepted step or static solve (Algorithm 1).

        Free nodes carry their anchor along; a node in contact keeps its anchor (stick) unless its
        tangential spring exceeds ``mu f_n``, in which case it slips: the anchor is dragged so that
        the stretch is exactly ``mu f_n / k_t``. Leaving contact resets the state (the anchor
        follows the node again).
        """
        k, _, kt, _ = self._coeffs(body)
        from softgrasp.physics.planes_compiled import plane_update

        active = np.empty(len(x), np.bool_)
        anchor = np.array(state.anchor, dtype=np.float64, order="C", copy=True)
        plane_update(
            _f64(x), self.plane.point_at(t), self.plane.normal, float(self.mu), k, kt, active, anchor,
            0, len(x),
        )  # fmt: skip
        return replace(state, active=active, anchor=anchor, cap=None, stick=None)

    def refresh(self, body: Body, x: NDArray[np.float64], t: float, state: PlaneState) -> PlaneState:
        """State between Newton steps of a static pass: free nodes carry their anchors along, so a
        node that touches sticks where it entered contact; touching nodes keep their anchors, and
        the limits stay the pass's."""
        p0, n, pen = self._geometry(x, t)
        touching = pen > 0
        rel = x - p0
        rel_t = rel - (rel @ n)[:, None] * n
        anchor = np.where(touching[:, None], state.anchor, rel_t)
        return replace(state, anchor=anchor, active=touching.copy())

    def static_update(self, body: Body, x: NDArray[np.float64], t: float, state: PlaneState) -> PlaneState:
        """State after a Newton pass of a static solve: :meth:`refresh`, with the limits at ``x``
        (:meth:`static_begin`), under which the solver checks the balance; after the first pass,
        the stick stiffnesses frozen at its rest (the limits there over the elastic slips). The
        anchors stay those of the solve's start until it ends (:meth:`static_finish`), as a
        return mapping takes each load increment's slip from the rest before it."""
        state = self.static_begin(body, x, t, self.refresh(body, x, t, state))
        if state.stick is None and self.mu > 0:
            assert state.cap is not None
            state = replace(state, stick=_stick_stiffness(body, state.cap, slice(None)))
        return state

    def static_finish(self, body: Body, x: NDArray[np.float64], t: float, state: PlaneState) -> PlaneState:
        """State at the end of a static solve: each touching node's anchor moved so that the law
        outside a solve (its limit at ``x`` over its elastic slip for stick stiffness) gives it
        the friction force it has at the rest (a slipping node's is dragged to its elastic slip:
        Algorithm 1's slip, u); the limits and stick stiffnesses dropped (they hold within a
        solve)."""
        if self.mu == 0:
            return replace(state, cap=None, stick=None)
        on, k, _, pen, s, cap, stick = self._static_touching(body, x, t, state)
        _, _, _, secant = self._friction(k, s, cap, stick)
        force = secant[:, None] * s  # minus the friction force
        outside = _stick_stiffness(body, self.mu * k * pen, on)  # the stick stiffness outside a solve
        stretch = np.where((outside > 0)[:, None], force / np.maximum(outside, 1e-300)[:, None], 0.0)
        anchor = np.array(state.anchor, dtype=np.float64, copy=True)
        anchor[on] += s - stretch
        return replace(state, anchor=anchor, cap=None, stick=None)

    def normal_reaction(
        self, body: Body, x: NDArray[np.float64], v: NDArray[np.float64], t: float, state: PlaneState
    ) -> float:
        """Total force [N] the plane exerts on the body along its normal."""
        return float(self.forces(body, x, v, t, state).sum(axis=0) @ self.plane.normal)
