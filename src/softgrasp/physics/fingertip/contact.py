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

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from softgrasp.errors import ContactError
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.geometry import (
    INSIDE_TOL,
    ContactPairs,
    FacetIndex,
    broad_phase_reach,
    detect,
)
from softgrasp.physics.fingertip.laws import (
    contact_damping,
    contact_stiffness,
    effective_modulus,
    mindlin_ratio,
    resolved_share,
    LAW_COLUMNS,
)
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.fingertip.state import FingerReport, FingerState, _Eval

__all__ = ["FingertipContact", "FingerState", "FingerReport"]


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
    #: The normal law held fixed (:meth:`frozen`): what :meth:`law_table` returns at every t.
    frozen_law: NDArray[np.float64] | None = field(default=None, repr=False, compare=False)
    #: The last :meth:`law_table` (its body, t and table).
    _law_cache: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

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

    def law_table(self, body: Body, t: float) -> NDArray[np.float64]:
        """The normal law of each fingertip at time t as the compiled kernels take it, (n_f, 6):
        K [N/m^n] (Eq. 11), the share r of the pair's Hertz compliance that the object's mesh
        resolves (0 under the paper's law), the mesh's resolution under the fingertip, h_node,
        h_land and the facet size [m], and Hertz's radius [m]: the fingertip's under the paper's
        law; under the resolved law the pair's effective radius, 1 / R_eff = 1 / R + the object's
        curvature where the fingertip lands (:mod:`softgrasp.physics.fingertip.landing`,
        :mod:`softgrasp.physics.fingertip.resolved`), with K of R_eff. The last table is kept: a
        static solve or a step asks for it many times at one t."""
        if self.frozen_law is not None:
            return self.frozen_law
        cache = self._law_cache
        if cache.get("body") is body and cache.get("t") == float(t):
            return cache["table"]
        m, p = body.material, self.params
        table = np.zeros((len(self.fingertips), LAW_COLUMNS))
        table[:, 0] = self.stiffness(body)
        table[:, 5] = self._radii()
        if p.law == "resolved":
            from softgrasp.physics.fingertip.landing import facet_curvatures, landing_resolution

            points = np.asarray(body.mesh.points, dtype=np.float64)
            if cache.get("body") is not body:
                cache.clear()
                cache.update(body=body, curvature=facet_curvatures(points, body.mesh.facets))
            obj = effective_modulus(math.inf, 0.0, m.E, m.nu)
            land = landing_resolution(points, body.mesh.facets, cache["curvature"], self.centres(t), p.resolution)
            R = self._radii()
            # a dent conforming to the fingertip: R_eff at most 10 R
            reff = 1.0 / np.maximum(1.0 / R + land[:, 3], 0.1 / R)
            table[:, 0] *= np.sqrt(reff / R)
            table[:, 1] = [resolved_share(effective_modulus(f.E, f.nu, m.E, m.nu), obj) for f in self.fingertips]
            table[:, 2:5] = land[:, :3]
            table[:, 5] = reff
        table.flags.writeable = False
        cache.update(t=float(t), table=table)
        return table

    def frozen(self, body: Body, t: float) -> FingertipContact:
        """This contact with its normal law held at its value at time t (where the fingertips land
        then): a dynamic run integrates one law through its steps, whichever stepper runs it."""
        return replace(self, frozen_law=self.law_table(body, t))

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
        closest, corners = self._closest(), self.corners(body)
        return detect(x, body.mesh.facets, centres, radii, closest=closest, index=index, corners=corners)

    def corners(self, body: Body) -> NDArray[np.float64] | None:
        """The mesh's corner normals when the pairs' normals are the smooth surface's
        (``params.normals``), else None (the facets' own)."""
        return body.mesh.facet_corner_normals if self.params.normals == "smooth" else None

    # ------------------------------------------------------------------ core evaluation
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

    def _evaluate(
        self, body: Body, x, v, t: float, state: FingerState, static: bool, pairs: ContactPairs | None = None
    ) -> _Eval:
        """Each touching pair's contact law at x (at rest with ``static``): one compiled call
        (:func:`softgrasp.physics.fingertip.compiled.fingertip_pair_laws`, the per-pair values of
        :meth:`forces`)."""
        from softgrasp.physics.fingertip.compiled import fingertip_pair_laws

        if pairs is None:
            pairs = self.pairs(body, x, t)
        val = np.column_stack(
            [pairs.bary, pairs.point, pairs.normal, pairs.distance, pairs.depth, pairs.area, pairs.facing]
        )
        p = self.params
        table, slipping = fingertip_pair_laws(
            x,
            None if static else v,
            pairs.finger,
            pairs.facet,
            val,
            body.mesh.facets,
            self.centres(t),
            self._radii(),
            np.array([f.velocity for f in self.fingertips]),
            np.array([f.omega for f in self.fingertips]),
            self.law_table(body, t),
            self.damping(),
            mu=p.mu,
            exponent=p.exponent,
            hunt_crossley=p.damping == "hunt-crossley",
            patch=p.rule == "patch",
            ratio=self._ratio(body),
            min_depth_ratio=p.min_depth_ratio,
            active=state.active,
            anchor=state.anchor,
            offset=state.offset,
            memory=state.memory,
        )
        return _Eval(
            pairs,
            table[:, 0],
            table[:, 1:4],
            table[:, 4],
            table[:, 5],
            table[:, 6:9],
            table[:, 9],
            slipping,
            table[:, 10],
            table[:, 11].astype(np.int64),
            table[:, 12],
            table[:, 13],
            table[:, 14],
        )

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
        """Contact forces on the nodes during dynamics (Eq. 9-20): one compiled call
        (:func:`softgrasp.physics.fingertip.compiled.fingertip_forces`)."""
        return self._forces_compiled(body, x, v, t, state)

    def _compiled_kwargs(self, body: Body, t: float) -> dict[str, Any]:
        """Geometry and parameters shared by the compiled forces and update."""
        p = self.params
        patch = p.rule == "patch"
        index = FacetIndex.of(body.mesh)
        return {
            "facets": body.mesh.facets,
            "corners": self.corners(body),
            "boundary_nodes": index.boundary_nodes,
            "indptr": index.indptr,
            "indices": index.indices,
            "reach": broad_phase_reach(index),
            "centres": self.centres(t),
            "radii": self._radii(),
            "law": self.law_table(body, t),
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
        """Contact forces at rest with lagged weights, limits and k_t: one compiled call
        (:func:`softgrasp.physics.fingertip.compiled.fingertip_static_forces`)."""
        return self._static_compiled(body, t, state)(x)

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
        return self._static_compiled(body, t, state, ref)

    def energy(self, body: Body, x, t: float, state: FingerState) -> float:
        """Elastic energy of the normal contact springs [J], the sum over pairs of w times the
        normal law's energy (K delta^(n+1) / (n+1) under the paper's law).

        Friction is dissipative and the patch rule's weights depend on the configuration, so the
        contact is not a potential: the static solver does not use this for its line search."""
        ev = self._evaluate(body, x, None, t, state, static=True)
        return float(np.sum(ev.w * ev.energy))

    def jacobian(self, body: Body, x, t: float, state: FingerState) -> sp.csr_matrix:
        """``d f / d x`` at rest, symmetrised
        (:func:`softgrasp.physics.fingertip.stiffness.contact_jacobian`): the normal forces'
        per-pair derivative (central differences of the 9 facet coordinates, so the facet's
        rotation and the moving contact point are included; exact for the literal rule; for the
        patch rule with the weights w_j held fixed, plus the magnitude's dependence on the deepest
        facet) and the friction springs' ``w k_t H^T P_t H`` (or the slip tangent)."""
        from softgrasp.physics.fingertip.stiffness import contact_jacobian

        return contact_jacobian(self, body, x, t, state)

    def update(self, body: Body, x, v, t: float, state: FingerState) -> FingerState:
        """Advance the contact state after an accepted step or static solve (Algorithm 1).

        New pairs start sticking (inheriting their finger's stick displacement when it slides on
        from a neighbouring facet); a pair whose stick force exceeds mu f_n slips: its anchor is
        dragged so that the stick force is exactly mu f_n and the drag is added to the slip
        displacement u; pairs that separate are reset.

        One compiled call (:func:`softgrasp.physics.fingertip.compiled.fingertip_update`).
        """
        return self._update_compiled(body, x, t, state)

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
        """Largest contact stiffness a node may see [N/m]: the normal law's slope at a penetration
        of half the radius, at the resolution of the mesh's smallest boundary facet."""
        from softgrasp.physics.fingertip.resolved import elastic_normal_value

        pts = np.asarray(body.mesh.points)[body.mesh.facets]
        area = 0.5 * np.linalg.norm(np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0]), axis=1)
        size = math.sqrt(4.0 * float(area.min()) / math.sqrt(3.0))
        law = self.law_table(body, 0.0)
        kmax = 0.0
        for i, R in enumerate(self._radii()):
            h = 0.5 * math.pi * self.params.resolution * size  # a load on one node: least resolved
            F = elastic_normal_value(0.5 * R, law[i, 5], law[i, 0], self.params.exponent, law[i, 1], h, h, size)
            kmax = max(kmax, F[1])
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
            np.maximum.at(depth, pr.finger, ev.depth)
        return FingerReport(
            force=force,
            moment=moment,
            normal=np.bincount(pr.finger, weights=ev.fn, minlength=nf),
            tangential=np.linalg.norm(ftan, axis=1),
            contacts=np.bincount(pr.finger, minlength=nf).astype(np.int64),
            depth=depth,
        )
