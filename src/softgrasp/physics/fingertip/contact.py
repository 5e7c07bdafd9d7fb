"""The fingertip-object contact interaction (paper Sec. 3): forces, friction state, distribution.

For every touching (fingertip, facet) pair j (Sec. 3.1, :func:`softgrasp.physics.fingertip.geometry.detect`):

* normal force ``f_n = w_j max(0, K delta^n + C delta_dot)`` along the facet's inward normal
  (Eq. 9-14), with the rule's weight w_j (:class:`ContactParams`);
* friction by an elastic slider per pair (Eq. 15-16, Algorithm 1): an anchor (a material point of the
  facet, kept in barycentric coordinates, where the pair started) and the stick displacement v,
  how far the fingertip centre has moved relative to it since (tangentially to the facet), so that
  neither the facet's rotation nor the contact point's sliding along an edge counts as stick;
  stick force ``-w (k_t v + c_t V_t)`` while its norm <= mu f_n, otherwise Coulomb slip
  ``-mu f_n V_t / |V_t|`` and the stick is cut back to the limit (slip displacement u). Both reset
  when the finger leaves the object. A pair that starts while its finger is already sliding on a
  neighbouring facet inherits the finger's stick displacement, so friction is continuous across
  facet edges;
* the pair's force on the object is spread on the facet's nodes by the shape functions H (Eq. 17-20),
  ``f_l = (A_l / A_G) f_pj``, so nodal forces balance the fingertip's force and moment exactly.

Static solves use the same laws at zero velocity; between Newton steps the anchors of new pairs are
registered (:meth:`FingertipContact.refresh`), and after each converged pass the slip return of
Algorithm 1 is applied (:meth:`FingertipContact.update`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp import backend
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.fingertip.geometry import (
    INSIDE_TOL,
    ContactPairs,
    FacetIndex,
    broad_phase_reach,
    detect,
    pair_geometry,
    relative_velocity,
)
from softgrasp.physics.fingertip.laws import (
    contact_damping,
    contact_stiffness,
    effective_modulus,
    mindlin_ratio,
    normal_force,
    normal_force_derivative,
    slip_force,
)
from softgrasp.errors import ContactError
from softgrasp.physics.forces import assemble_blocks

__all__ = ["FingertipContact", "FingerState", "FingerReport"]


@dataclass(frozen=True)
class FingerState:
    """Contact state of all (fingertip, facet) pairs, arrays over (n_fingers, F).

    Attributes
    ----------
    active: pair in contact at the last update, bool.
    anchor: barycentric coordinates of the stick anchor X_a on the facet, a material point (the
        pair's contact point when it started), (n_f, F, 3).
    offset: the fingertip centre's position relative to the anchor when the pair was last in
        equilibrium with its stick (its start, or its last slip) [m], (n_f, F, 3): the stick
        displacement v of Eq. 16 is the tangential part of (c - X_a) - offset, how far the
        fingertip has moved over the material since.
    slip: accumulated slip displacement u [m], (n_f, F, 3).
    memory: each finger's weighted mean stick displacement at the last update [m], (n_f, 3).
    """

    active: NDArray[np.bool_]
    anchor: NDArray[np.float64]
    offset: NDArray[np.float64]
    slip: NDArray[np.float64]
    memory: NDArray[np.float64]


@dataclass(frozen=True)
class FingerReport:
    """Per-fingertip totals at one instant.

    Attributes
    ----------
    force: force of each fingertip on the object [N], (n_f, 3).
    moment: moment of those forces about each fingertip centre [N m], (n_f, 3).
    normal: sum of the normal force magnitudes [N], (n_f,).
    tangential: norm of the summed friction force [N], (n_f,).
    contacts: number of touched facets, (n_f,).
    depth: largest facet penetration delta [m], (n_f,).
    """

    force: NDArray[np.float64]
    moment: NDArray[np.float64]
    normal: NDArray[np.float64]
    tangential: NDArray[np.float64]
    contacts: NDArray[np.int64]
    depth: NDArray[np.float64]


@dataclass(frozen=True)
class _Eval:
    pairs: ContactPairs
    fn: NDArray[np.float64]  # weighted normal force magnitude per pair [N]
    ft: NDArray[np.float64]  # friction on the finger per pair [N], (k, 3)
    w: NDArray[np.float64]
    kt: NDArray[np.float64]
    stick: NDArray[np.float64]  # tangential stick displacement per pair [m], (k, 3)
    cap: NDArray[np.float64]
    slipping: NDArray[np.bool_]


def _pair_normal_forces(
    tri: NDArray[np.float64],
    centre: NDArray[np.float64],
    radius: NDArray[np.float64],
    coef: NDArray[np.float64],
    n_exp: float,
    closest: bool,
) -> NDArray[np.float64]:
    """Static normal forces on the three nodes of each facet, (k, 3, 3): ``-coef delta^n b_l n``
    for triangles ``tri`` (k, 3, 3) and fingertip centres (k, 3), with each pair's contact point
    (b), normal and penetration as :func:`~softgrasp.physics.fingertip.geometry.pair_geometry` follows them
    (``closest`` as in :func:`~softgrasp.physics.fingertip.geometry.detect`)."""
    k = tri.shape[0]
    ids = np.arange(k)
    own = np.arange(3 * k).reshape(k, 3)  # each pair its own triangle
    pr = pair_geometry(tri.reshape(-1, 3), own, centre, radius, ids, ids, closest=closest)
    mag = coef * np.where(pr.depth > 0, np.abs(pr.depth) ** n_exp, 0.0)
    return -(mag[:, None, None] * pr.bary[:, :, None]) * pr.normal[:, None, :]


def _normal_jacobian_blocks(
    tri: NDArray[np.float64],
    centre: NDArray[np.float64],
    radius: NDArray[np.float64],
    coef: NDArray[np.float64],
    n_exp: float,
    closest: bool,
) -> NDArray[np.float64]:
    """d(nodal normal forces)/d(node positions) per pair by central differences, symmetrised,
    (k, 3, 3, 3, 3) indexed [pair, node_l, node_m, axis_l, axis_m]."""
    k = tri.shape[0]
    h = 1e-7 * np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1)  # (k,)
    # All 18 perturbed copies (+-h on each node's axis) in one evaluation: (2, 3, 3, k, 3, 3)
    # indexed [sign, node m, axis, pair, node, axis].
    moved = np.broadcast_to(tri, (2, 3, 3, k, 3, 3)).copy()
    for m in range(3):
        for ax in range(3):
            moved[0, m, ax, :, m, ax] += h
            moved[1, m, ax, :, m, ax] -= h
    reps = 18
    F = _pair_normal_forces(
        moved.reshape(-1, 3, 3),
        np.tile(centre, (reps, 1)),
        np.tile(radius, reps),
        np.tile(coef, reps),
        n_exp,
        closest,
    ).reshape(2, 3, 3, k, 3, 3)
    dF = (F[0] - F[1]) / (2 * h)[None, None, :, None, None]  # [m, ax, pair, node l, axis l]
    J = np.ascontiguousarray(dF.transpose(2, 3, 0, 4, 1))  # [pair, l, m, axis l, axis m]
    return 0.5 * (J + J.transpose(0, 2, 1, 4, 3))


@dataclass(frozen=True, eq=False)
class FingertipContact:
    """Contact between rigid (or stiff) spherical fingertips and the body's boundary facets.

    Parameters
    ----------
    fingertips: the fingertips.
    params: contact parameters (defaults documented in :mod:`softgrasp.physics.fingertip.params`).
    name: interaction label.
    """

    fingertips: tuple[Fingertip, ...]
    params: ContactParams = ContactParams()
    name: str = "fingers"
    #: :meth:`jacobian` is a symmetrised approximation (friction anchored on a rotating facet and the
    #: patch rule's weights are not a potential): Newton solvers multiply by the exact derivative
    #: through :meth:`static_forces` (finite differences along the direction) where it matters.
    symmetric_jacobian: ClassVar[bool] = False

    def __post_init__(self) -> None:
        if not self.fingertips:
            raise ContactError("a fingertip contact needs at least one fingertip")

    # ------------------------------------------------------------------ constants
    def stiffness(self, body: Body) -> NDArray[np.float64]:
        """K of each fingertip [N/m^n] (Eq. 11-12)."""
        m = body.material
        return np.array(
            [
                contact_stiffness(effective_modulus(f.E, f.nu, m.E, m.nu), f.radius, self.params.prefactor)
                for f in self.fingertips
            ]
        )

    def damping(self) -> NDArray[np.float64]:
        """C of each fingertip [N s/m] (Eq. 13)."""
        return np.array([contact_damping(f.radius, self.params.gamma) for f in self.fingertips])

    def _ratio(self, body: Body) -> float:
        p = self.params
        return p.tangential_ratio if p.tangential_ratio is not None else mindlin_ratio(body.material.nu)

    def _radii(self) -> NDArray[np.float64]:
        return np.array([f.radius for f in self.fingertips])

    def centres(self, t: float) -> NDArray[np.float64]:
        """Fingertip centres at time t [m], (n_f, 3)."""
        return np.array([f.centre_at(t) for f in self.fingertips])

    def _closest(self) -> bool:
        """Detection mode (:func:`~softgrasp.physics.fingertip.geometry.detect`): the sphere's overlap with
        each facet for the patch rule, the paper's projection test for the literal one."""
        return self.params.rule == "patch"

    def pairs(self, body: Body, x: NDArray[np.float64], t: float) -> ContactPairs:
        """Touching pairs at positions x and time t."""
        index = FacetIndex.of(body.mesh)
        centres, radii = self.centres(t), self._radii()
        return detect(x, body.mesh.facets, centres, radii, closest=self._closest(), index=index)

    # ------------------------------------------------------------------ core evaluation
    def _patch_weights(self, pairs: ContactPairs) -> NDArray[np.float64]:
        if self.params.rule == "facet" or len(pairs) == 0:
            return np.ones(len(pairs))
        nf = len(self.fingertips)
        a = pairs.area * pairs.depth * pairs.facing
        return a / np.bincount(pairs.finger, weights=a, minlength=nf)[pairs.finger]

    def _deepest(self, pairs: ContactPairs) -> NDArray[np.int64]:
        """Index of each pair's finger's deepest pair (largest depth), (k,)."""
        deep = np.zeros(len(pairs), np.int64)
        for i in np.unique(pairs.finger):
            idx = np.flatnonzero(pairs.finger == i)
            deep[idx] = idx[np.argmax(pairs.depth[idx])]
        return deep

    def _depths(self, pairs: ContactPairs) -> NDArray[np.float64]:
        """Penetration at which each pair's normal law is evaluated [m], (k,): the pair's own
        delta_j (literal rule), or its fingertip's overlap with the surface, max_j (R - |c - Q_j|)
        = R - dist(c, surface) (patch rule: the fingertip's elastic normal force is
        K delta_max^n, shared among its facets by the weights w_j)."""
        if self.params.rule == "facet" or len(pairs) == 0:
            return pairs.depth
        return pairs.depth[self._deepest(pairs)]

    def _anchor_points(self, body: Body, x, pairs: ContactPairs, state: FingerState, t: float):
        """Stick anchors in space (k, 3), the centre's offsets from them (k, 3) and the mask of
        continuing pairs: kept for continuing pairs; a new pair is anchored at its contact point,
        its offset set so that its stick displacement is the finger's remembered one (zero
        unless the finger slides on from a neighbouring facet)."""
        fac = body.mesh.facets[pairs.facet]
        cont = state.active[pairs.finger, pairs.facet]
        kept = np.einsum("ki,kij->kj", state.anchor[pairs.finger, pairs.facet], x[fac])
        Xa = np.where(cont[:, None], kept, pairs.point)
        c = self.centres(t)[pairs.finger]
        fresh = c - pairs.point - state.memory[pairs.finger]
        off = np.where(cont[:, None], state.offset[pairs.finger, pairs.facet], fresh)
        return Xa, off, cont

    def _stick(self, body: Body, x, pairs: ContactPairs, state: FingerState, t: float):
        """Tangential stick displacement v of each pair [m], (k, 3) (Eq. 16), the anchors in
        space and the mask of pairs that continue from the last update."""
        Xa, off, cont = self._anchor_points(body, x, pairs, state, t)
        s = self.centres(t)[pairs.finger] - Xa - off
        return s - np.einsum("ij,ij->i", s, pairs.normal)[:, None] * pairs.normal, Xa, cont

    def _tangential_stiffness(self, body: Body, pairs: ContactPairs, K) -> NDArray[np.float64]:
        """k_t of each pair [N/m]: Mindlin's ratio times dF_n/d delta at the pair's penetration
        (not below ``min_depth_ratio`` R)."""
        p = self.params
        depth = np.maximum(self._depths(pairs), p.min_depth_ratio * self._radii()[pairs.finger])
        return self._ratio(body) * normal_force_derivative(depth, K, p.exponent)

    def _evaluate(
        self, body: Body, x, v, t: float, state: FingerState, static: bool, pairs: ContactPairs | None = None
    ) -> _Eval:
        p = self.params
        if pairs is None:
            pairs = self.pairs(body, x, t)
        K = self.stiffness(body)[pairs.finger]
        C = self.damping()[pairs.finger]
        n_exp = p.exponent
        if static:
            vt = np.zeros((len(pairs), 3))
            rate = np.zeros(len(pairs))
        else:
            vr, _, vt = relative_velocity(
                pairs,
                body.mesh.facets,
                v,
                self.centres(t),
                np.array([f.velocity for f in self.fingertips]),
                np.array([f.omega for f in self.fingertips]),
            )
            rate = -np.einsum("ij,ij->i", vr, pairs.normal)  # d delta / dt
        raw = normal_force(self._depths(pairs), rate, K, C, n_exp, damping=p.damping)
        w = self._patch_weights(pairs)
        fn = w * raw
        ft = np.zeros((len(pairs), 3))
        stick = np.zeros((len(pairs), 3))
        cap = np.zeros(len(pairs))
        slipping = np.zeros(len(pairs), bool)
        kt = np.zeros(len(pairs))
        if p.mu > 0 and len(pairs):
            s, _, _ = self._stick(body, x, pairs, state, t)
            stick = s
            kt = self._tangential_stiffness(body, pairs, K)
            ct = self._ratio(body) * C
            trial = -(w * kt)[:, None] * s - (w * ct)[:, None] * vt
            cap = p.mu * fn
            mag = np.linalg.norm(trial, axis=1)
            slipping = mag > cap
            ft = trial.copy()
            if slipping.any():
                speed = np.linalg.norm(vt, axis=1)
                moving = slipping & (speed > 0)
                still = slipping & ~moving
                ft[moving] = slip_force(fn[moving], vt[moving], p.mu)  # Eq. 15
                ft[still] = trial[still] * (cap[still] / mag[still])[:, None]
        return _Eval(pairs, fn, ft, w, kt, stick, cap, slipping)

    def _nodal(self, body: Body, x, ev: _Eval) -> NDArray[np.float64]:
        """Forces on the nodes [N], (N, 3): H^T f_pj per pair (Eq. 17-20) at its contact point,
        which lies in the triangle: the shape functions are >= 0, and the pair's force and moment
        are exact."""
        f = np.zeros_like(x)
        if len(ev.pairs):
            F = -ev.fn[:, None] * ev.pairs.normal - ev.ft  # on the object
            fac = body.mesh.facets[ev.pairs.facet]
            np.add.at(f, fac.ravel(), (ev.pairs.bary[:, :, None] * F[:, None, :]).reshape(-1, 3))
        return f

    # ------------------------------------------------------------------ Interaction protocol
    def init_state(self, body: Body, x: NDArray[np.float64], t: float = 0.0) -> FingerState:
        """Empty contact state; refuses fingertips whose centre starts inside the object."""
        self._check_outside(body, x, t)
        nf, F = len(self.fingertips), len(body.mesh.facets)
        empty = FingerState(
            active=np.zeros((nf, F), bool),
            anchor=np.zeros((nf, F, 3)),
            offset=np.zeros((nf, F, 3)),
            slip=np.zeros((nf, F, 3)),
            memory=np.zeros((nf, 3)),
        )
        return self.update(body, x, np.zeros_like(x), t, empty)

    def _check_outside(self, body: Body, x: NDArray[np.float64], t: float) -> None:
        p = x[body.mesh.tets]
        T = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)  # (M, 3, 3)
        Tinv = np.linalg.inv(T)
        for f, c in zip(self.fingertips, self.centres(t), strict=True):
            lam = np.einsum("mij,mj->mi", Tinv, c[None, :] - p[:, 0])
            inside = (lam >= -1e-12).all(axis=1) & (lam.sum(axis=1) <= 1 + 1e-12)
            if inside.any():
                raise ContactError(
                    f"fingertip {f.name!r} starts with its centre inside the object (its penetration "
                    f"would exceed its radius {f.radius * 1e3:.1f} mm); start it outside the surface"
                )

    def forces(self, body: Body, x, v, t: float, state: FingerState) -> NDArray[np.float64]:
        """Contact forces on the nodes during dynamics (Eq. 9-20).

        With the compiled kernels selected (:mod:`softgrasp.backend`) the whole evaluation is one
        compiled call (:func:`softgrasp.physics.fingertip.compiled.fingertip_forces`); the NumPy code of
        :meth:`_evaluate` and :meth:`_nodal` is the reference."""
        if backend.compiled():
            return self._forces_compiled(body, x, v, t, state)
        return self._nodal(body, x, self._evaluate(body, x, v, t, state, static=False))

    def _compiled_kwargs(self, body: Body, t: float) -> dict[str, Any]:
        """Geometry and parameters shared by the compiled forces and update."""
        p = self.params
        patch = p.rule == "patch"
        index = FacetIndex.of(body.mesh)
        return {
            "facets": body.mesh.facets,
            "boundary_nodes": index.boundary_nodes,
            "indptr": index.indptr,
            "indices": index.indices,
            "reach": broad_phase_reach(index),
            "centres": self.centres(t),
            "radii": self._radii(),
            "K": self.stiffness(body),
            "closest": self._closest(),
            "inside_tol": INSIDE_TOL,
            "mu": p.mu,
            "exponent": p.exponent,
            "patch": patch,
            "ratio": self._ratio(body),
            "min_depth_ratio": p.min_depth_ratio,
        }

    def _forces_compiled(self, body: Body, x, v, t: float, state: FingerState) -> NDArray[np.float64]:
        from softgrasp.physics.fingertip.compiled import fingertip_forces

        return fingertip_forces(
            x,
            v,
            velocities=np.array([f.velocity for f in self.fingertips]),
            omegas=np.array([f.omega for f in self.fingertips]),
            C=self.damping(),
            hunt_crossley=self.params.damping == "hunt-crossley",
            active=state.active,
            anchor=state.anchor,
            offset=state.offset,
            memory=state.memory,
            **self._compiled_kwargs(body, t),
        )

    def _update_compiled(self, body: Body, x, t: float, state: FingerState) -> FingerState:
        from softgrasp.physics.fingertip.compiled import fingertip_update

        active, anchor, offset, slip, memory = fingertip_update(
            x,
            active=state.active,
            anchor=state.anchor,
            offset=state.offset,
            slip=state.slip,
            memory=state.memory,
            **self._compiled_kwargs(body, t),
        )
        return replace(state, active=active, anchor=anchor, offset=offset, slip=slip, memory=memory)

    def static_forces(self, body: Body, x, t: float, state: FingerState) -> NDArray[np.float64]:
        """Contact forces at rest with lagged weights, limits and k_t (one compiled call with the
        compiled kernels selected; :meth:`_evaluate` and :meth:`_nodal` are the reference)."""
        if backend.compiled():
            return self._static_compiled(body, t, state)(x)
        return self._nodal(body, x, self._evaluate(body, x, None, t, state, static=True))

    def _static_compiled(
        self, body: Body, t: float, state: FingerState, pairs: ContactPairs | None = None
    ) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
        """The compiled static forces as a function of the node positions (the geometry and
        parameters gathered once): of the pairs touching there, or of ``pairs`` followed there."""
        from softgrasp.physics.fingertip.compiled import fingertip_static_forces

        kwargs = self._compiled_kwargs(body, t)
        fixed = None if pairs is None else (np.asarray(pairs.finger), np.asarray(pairs.facet))
        st = {"active": state.active, "anchor": state.anchor, "offset": state.offset, "memory": state.memory}

        def forces(x: NDArray[np.float64]) -> NDArray[np.float64]:
            return fingertip_static_forces(x, pairs=fixed, **st, **kwargs)

        return forces

    def pinned_static_forces(
        self, body: Body, x_ref: NDArray[np.float64], t: float, state: FingerState
    ) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
        """The static contact forces as a function of the node positions near ``x_ref``, with the
        touching pairs fixed to those at ``x_ref`` (their geometry followed, none added or
        dropped): what the Newton solver differentiates along a direction. Without pinning, a
        perturbation can cross a contact knife edge (a fingertip right over a vertex touches all
        the facets around it or none)."""
        ref = self.pairs(body, x_ref, t)
        if backend.compiled():
            return self._static_compiled(body, t, state, ref)
        closest = self._closest()
        finger, facet = np.array(ref.finger), np.array(ref.facet)
        centres, radii = self.centres(t), self._radii()

        def forces(x: NDArray[np.float64]) -> NDArray[np.float64]:
            pairs = pair_geometry(x, body.mesh.facets, centres, radii, finger, facet, closest=closest)
            return self._nodal(body, x, self._evaluate(body, x, None, t, state, static=True, pairs=pairs))

        return forces

    def energy(self, body: Body, x, t: float, state: FingerState) -> float:
        """Elastic energy of the normal contact springs [J], sum of w K delta^(n+1) / (n+1).

        Friction is dissipative and the patch rule's weights depend on the configuration, so the
        contact is not a potential: the static solver does not use this for its line search."""
        pr = self.pairs(body, x, t)
        if not len(pr):
            return 0.0
        K = self.stiffness(body)[pr.finger]
        n = self.params.exponent
        return float(np.sum(self._patch_weights(pr) * K * self._depths(pr) ** (n + 1) / (n + 1)))

    def jacobian(self, body: Body, x, t: float, state: FingerState) -> sp.csr_matrix:
        """``d f / d x`` at rest, symmetrised: the normal forces' per-pair derivative (central
        differences of the 9 facet coordinates, so the facet's rotation and the moving contact
        point are included; exact for the literal rule; for the patch rule with the weights w_j
        held fixed, plus the magnitude's dependence on the deepest facet) and the friction
        springs' ``w k_t H^T P_t H`` (or the slip tangent)."""
        ev = self._evaluate(body, x, None, t, state, static=True)
        N = body.n_nodes
        if not len(ev.pairs):
            return sp.csr_matrix((3 * N, 3 * N))
        pr = ev.pairs
        K = self.stiffness(body)[pr.finger]
        fac = body.mesh.facets[pr.facet]
        centres = self.centres(t)[pr.finger]
        radii = self._radii()[pr.finger]
        n_exp = self.params.exponent
        patch = self.params.rule == "patch"
        if patch:
            # Pair force w_j K delta_max^n along its facet's normal at its contact point: their
            # motion with the facet at fixed magnitude (central differences, exponent 0), plus the
            # magnitude's dependence on the finger's deepest facet, d delta_max / d x_l =
            # b_l (c - Q) / |c - Q| with b and Q that facet's contact point (the closest point
            # slides on the surface at no first-order cost); the weights are lagged.
            deep = self._deepest(pr)
            dmax = pr.depth[deep]
            Jn = _normal_jacobian_blocks(x[fac], centres, radii, ev.w * K * dmax**n_exp, 0.0, True)
        else:
            # Exact per-pair blocks (facet rotation and the moving contact point included).
            Jn = _normal_jacobian_blocks(x[fac], centres, radii, ev.w * K, n_exp, False)
        blk_t = np.zeros((len(pr), 3, 3))
        if self.params.mu > 0:
            nn = pr.normal[:, :, None] * pr.normal[:, None, :]
            Pt = np.eye(3)[None] - nn
            s = np.linalg.norm(ev.stick, axis=1)
            ktan = np.where(ev.slipping, ev.cap / np.maximum(s, 1e-300), ev.w * ev.kt)
            blk_t = ktan[:, None, None] * Pt
        bb = pr.bary[:, :, None] * pr.bary[:, None, :]  # (k, 3, 3)
        blocks = Jn - bb[:, :, :, None, None] * blk_t[:, None, None, :, :]
        rows = np.repeat(fac, 3, axis=1).ravel()
        cols = np.tile(fac, (1, 3)).ravel()
        blocks = blocks.reshape(-1, 3, 3)
        if patch:
            gap = centres - pr.point[deep]
            gdir = gap / np.maximum(np.linalg.norm(gap, axis=1), 1e-300)[:, None]
            g = ev.w * K * n_exp * dmax ** (n_exp - 1.0)
            bd = pr.bary[deep]
            cpl = (
                -(g[:, None, None] * pr.bary[:, :, None] * bd[:, None, :])[:, :, :, None, None]
                * (pr.normal[:, :, None] * gdir[:, None, :])[:, None, None, :, :]
            )  # (k, own node, deep node, 3, 3)
            r1 = np.repeat(fac, 3, axis=1).ravel()
            c1 = np.tile(fac[deep], (1, 3)).ravel()
            half = 0.5 * cpl.reshape(-1, 3, 3)
            rows = np.concatenate([rows, r1, c1])
            cols = np.concatenate([cols, c1, r1])
            blocks = np.concatenate([blocks, half, half.transpose(0, 2, 1)])
        return assemble_blocks(N, rows, cols, blocks)

    def update(self, body: Body, x, v, t: float, state: FingerState) -> FingerState:
        """Advance the contact state after an accepted step or static solve (Algorithm 1).

        New pairs start sticking (inheriting their finger's stick displacement when it slides on
        from a neighbouring facet); a pair whose stick force exceeds mu f_n slips: its anchor is
        dragged so that the stick force is exactly mu f_n and the drag is added to the slip
        displacement u; pairs that separate are reset.

        One compiled call (:func:`softgrasp.physics.fingertip.compiled.fingertip_update`) with the compiled
        kernels selected; the NumPy code below is the reference.
        """
        if backend.compiled():
            return self._update_compiled(body, x, t, state)
        p = self.params
        pairs = self.pairs(body, x, t)
        nf, F = state.active.shape
        active = np.zeros((nf, F), bool)
        anchor = np.zeros((nf, F, 3))
        offset = np.zeros((nf, F, 3))
        slip = np.zeros((nf, F, 3))
        memory = np.zeros((nf, 3))
        if len(pairs):
            i, j = pairs.finger, pairs.facet
            K = self.stiffness(body)[i]
            w = self._patch_weights(pairs)
            elastic = normal_force(self._depths(pairs), np.zeros(len(pairs)), K, 0.0, p.exponent)
            kt = self._tangential_stiffness(body, pairs, K)
            s, Xa, cont = self._stick(body, x, pairs, state, t)
            u = np.where(cont[:, None], state.slip[i, j], 0.0)
            if p.mu > 0:
                lim = p.mu * w * elastic
                s_norm = np.linalg.norm(s, axis=1)
                keff = w * kt
                over = keff * s_norm > lim
                if over.any():
                    new_s = s[over] * (lim[over] / (keff[over] * s_norm[over]))[:, None]
                    u[over] += s[over] - new_s  # the stick is cut back: slip displacement
                    s[over] = new_s
            else:
                s = np.zeros_like(s)
            anchor[i, j] = np.where(cont[:, None], state.anchor[i, j], pairs.bary)
            offset[i, j] = self.centres(t)[i] - Xa - s
            active[i, j] = True
            slip[i, j] = u
            ws = np.bincount(i, weights=w, minlength=nf)
            for k in range(3):
                memory[:, k] = np.bincount(i, weights=w * s[:, k], minlength=nf) / np.maximum(ws, 1e-300)
        return replace(state, active=active, anchor=anchor, offset=offset, slip=slip, memory=memory)

    def refresh(self, body: Body, x, t: float, state: FingerState) -> FingerState:
        """Light update between Newton steps of a static solve: continuing pairs keep their
        anchors, pairs that start are anchored where they start (minus their finger's stick
        displacement), pairs that end are dropped; no slip return."""
        pairs = self.pairs(body, x, t)
        nf, F = state.active.shape
        active = np.zeros((nf, F), bool)
        anchor = np.zeros((nf, F, 3))
        offset = np.zeros((nf, F, 3))
        slip = np.zeros((nf, F, 3))
        if len(pairs):
            i, j = pairs.finger, pairs.facet
            _, off, cont = self._anchor_points(body, x, pairs, state, t)
            anchor[i, j] = np.where(cont[:, None], state.anchor[i, j], pairs.bary)
            offset[i, j] = off
            active[i, j] = True
            slip[i, j] = np.where(cont[:, None], state.slip[i, j], 0.0)
        return replace(state, active=active, anchor=anchor, offset=offset, slip=slip)

    def stiffness_bound(self, body: Body) -> NDArray[np.float64]:
        """Largest contact stiffness a node may see [N/m] (at a penetration of half the radius)."""
        K = self.stiffness(body)
        kmax = float(np.max(normal_force_derivative(0.5 * self._radii(), K, self.params.exponent)))
        if self.params.rule == "facet":
            kmax *= 6.0  # a node shares its force with up to ~6 touched facets
        return np.full(body.n_nodes, kmax * (1.0 + self._ratio(body)))

    def damping_bound(self, body: Body) -> NDArray[np.float64]:
        """Largest contact damping a node may see [N s/m]."""
        C = float(self.damping().max())
        if self.params.damping == "hunt-crossley":
            C *= float((0.5 * self._radii().max()) ** self.params.exponent)
        return np.full(body.n_nodes, C * (1.0 + self._ratio(body)))

    # ------------------------------------------------------------------ reporting
    def contact_frames(
        self, body: Body, x, t: float, state: FingerState
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Each fingertip's contact as one point contact, at rest: the normal-force-weighted mean
        contact point [m] (n_f, 3), the unit direction of its resultant normal force on the object
        (pointing into the object) (n_f, 3), and that resultant's magnitude [N] (n_f,). A finger
        without contact gets zeros."""
        ev = self._evaluate(body, x, None, t, state, static=True)
        nf = len(self.fingertips)
        pr = ev.pairs
        point = np.zeros((nf, 3))
        push = np.zeros((nf, 3))
        total = np.bincount(pr.finger, weights=ev.fn, minlength=nf)
        for k in range(3):
            point[:, k] = np.bincount(pr.finger, weights=ev.fn * pr.point[:, k], minlength=nf)
            push[:, k] = np.bincount(pr.finger, weights=-ev.fn * pr.normal[:, k], minlength=nf)
        mag = np.linalg.norm(push, axis=1)
        has = total > 0
        point[has] /= total[has, None]
        push[has] /= mag[has, None]
        return point, push, np.where(has, mag, 0.0)

    def friction_usage(self, body: Body, x, t: float, state: FingerState) -> NDArray[np.float64]:
        """Largest |f_t| / (mu f_n) among each fingertip's contact pairs at rest, (n_f,): 1 when a
        pair slips (Algorithm 1 caps it at the Coulomb limit), < 1 when all stick; 0 without
        contact or friction."""
        ev = self._evaluate(body, x, None, t, state, static=True)
        use = np.zeros(len(self.fingertips))
        if len(ev.pairs) and self.params.mu > 0:
            ratio = np.linalg.norm(ev.ft, axis=1) / np.maximum(ev.cap, 1e-300)
            ratio = np.where(ev.slipping, 1.0, np.minimum(ratio, 1.0))
            np.maximum.at(use, ev.pairs.finger, ratio)
        return use

    def report(self, body: Body, x, v, t: float, state: FingerState, *, static: bool = False) -> FingerReport:
        """Per-fingertip totals: force and moment on the object, normal and friction parts."""
        ev = self._evaluate(body, x, v, t, state, static=static)
        nf = len(self.fingertips)
        pr = ev.pairs
        F = -ev.fn[:, None] * pr.normal - ev.ft
        force = np.zeros((nf, 3))
        moment = np.zeros((nf, 3))
        ftan = np.zeros((nf, 3))
        c = self.centres(t)
        for k in range(3):
            force[:, k] = np.bincount(pr.finger, weights=F[:, k], minlength=nf)
            ftan[:, k] = np.bincount(pr.finger, weights=-ev.ft[:, k], minlength=nf)
        M = np.cross(pr.point - c[pr.finger], F)
        for k in range(3):
            moment[:, k] = np.bincount(pr.finger, weights=M[:, k], minlength=nf)
        depth = np.zeros(nf)
        if len(pr):
            np.maximum.at(depth, pr.finger, self._depths(pr))
        return FingerReport(
            force=force,
            moment=moment,
            normal=np.bincount(pr.finger, weights=ev.fn, minlength=nf),
            tangential=np.linalg.norm(ftan, axis=1),
            contacts=np.bincount(pr.finger, minlength=nf).astype(np.int64),
            depth=depth,
        )
