"""NumPy reference of the fingertip contact (paper Sec. 3, Eq. 1-20), for the tests only.

:class:`OracleFingertipContact` is a :class:`softgrasp.physics.fingertip.contact.FingertipContact`
whose forces, static forces, pinned static forces and friction-state update are computed by
vectorised NumPy from the closed-form laws (:mod:`softgrasp.physics.fingertip.laws`) and the pair
geometry (:mod:`softgrasp.physics.fingertip.geometry`), independently of the compiled kernels of
:mod:`softgrasp.physics.fingertip.compiled`: the tests compare those kernels with it to round-off.
:func:`oracle_scene` swaps a scene's body and fingertip contacts for the oracles (a NumPy reference
trajectory under :func:`softgrasp.sim.simulate` with ``fused=False``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from oracles.forces import OracleBody
from softgrasp.physics.body import Body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.geometry import (
    INSIDE_TOL,
    ContactPairs,
    FacetIndex,
    _empty,
    broad_phase_reach,
)
from softgrasp.physics.fingertip.laws import normal_force_value, slip_force
from softgrasp.physics.fingertip.resolved import elastic_normal_value
from softgrasp.physics.fingertip.state import FingerState, _Eval


def barycentric(
    p: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64], c: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Barycentric coordinates of points p (k, 3) with respect to triangles (a, b, c), each (k, 3),
    after projection on the triangles' planes; shape (k, 3), rows summing to 1."""
    v0, v1, v2 = b - a, c - a, p - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    wb = (d11 * d20 - d01 * d21) / den
    wc = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - wb - wc, wb, wc], axis=1)


def closest_points(
    p: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64], c: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Points of the triangles (a, b, c) (k, 3 each) closest to the points p (k, 3) whose
    projections fall outside them: the nearest of the three edges' closest points (a later edge
    wins only when strictly closer).
    Returns (points (k, 3), their barycentric coordinates (k, 3))."""
    verts = (a, b, c)
    best = np.full(len(p), np.inf)
    q = np.zeros_like(p)
    bary = np.zeros_like(p)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        e = verts[j] - verts[i]
        t = np.clip(np.einsum("ij,ij->i", p - verts[i], e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
        qe = verts[i] + t[:, None] * e
        d2 = np.einsum("ij,ij->i", p - qe, p - qe)
        better = d2 < best
        best[better] = d2[better]
        q[better] = qe[better]
        be = np.zeros_like(p)
        be[:, i] = 1.0 - t
        be[:, j] = t
        bary[better] = be[better]
    return q, bary


def smooth_normals(tri: NDArray[np.float64], corners: NDArray[np.float64], bary: NDArray[np.float64]):
    """Phong's normal (k, 3) of triangles ``tri`` (k, 3, 3) at barycentric coordinates ``bary``
    (k, 3) (clipped to the triangle), from corner normals ``corners`` (k, 3, 3) given in each
    triangle's frame (e1 along its first edge, e2 = n x e1, n): rotated by that frame's matrix."""
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1)[:, None]
    e1 = tri[:, 1] - tri[:, 0]
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    frame = np.stack([e1, np.cross(n, e1), n], axis=2)  # columns e1, e2, n: (k, 3, 3)
    world = np.einsum("kab,kib->kia", frame, corners)  # each corner normal in world axes
    w = np.clip(bary, 0.0, None)
    s = np.einsum("ki,kia->ka", w / w.sum(axis=1)[:, None], world)
    return s / np.linalg.norm(s, axis=1)[:, None]


def _narrow_phase(
    x, facets, centres, radii, fi, fj, closest: bool, keep_all: bool, corners=None
) -> ContactPairs:
    """Pair geometry of the candidate pairs (fi, fj); the touching ones only unless ``keep_all``;
    normals the smooth surface's given the mesh's ``corners`` (F, 3, 3)."""
    tri = x[facets[fj]]  # (k, 3, 3) candidates only
    a, b, c3 = tri[:, 0], tri[:, 1], tri[:, 2]
    nrm = np.cross(b - a, c3 - a)
    twice_area = np.linalg.norm(nrm, axis=1)
    n = nrm / twice_area[:, None]
    ctr = centres[fi]
    d = np.einsum("ij,ij->i", ctr - a, n)
    R = radii[fi]
    point = ctr - d[:, None] * n
    bary = barycentric(point, a, b, c3)
    low = bary.min(axis=1)
    if closest:
        out = np.flatnonzero(low < 0)
        if out.size:
            point[out], bary[out] = closest_points(ctr[out], a[out], b[out], c3[out])
        dist = np.linalg.norm(ctr - point, axis=1)
        fac = np.clip(d / np.where(dist > 0, dist, 1.0), 0.0, 1.0)
        ok = (d > 0) & (dist < R)
    else:
        dist = d
        fac = np.ones(len(fj))
        ok = (d > 0) & (d < R) & (low >= -INSIDE_TOL)
    if keep_all:
        ok = np.ones(len(fj), bool)
    normal = n if corners is None else smooth_normals(tri, corners[fj], bary)
    return ContactPairs(
        finger=fi[ok],
        facet=fj[ok],
        bary=bary[ok],
        point=point[ok],
        normal=normal[ok],
        distance=dist[ok],
        depth=R[ok] - dist[ok],
        area=0.5 * twice_area[ok],
        facing=fac[ok],
    )


def pair_geometry(
    x, facets, centres, radii, finger, facet, *, closest: bool = False, corners=None
) -> ContactPairs:
    """:func:`softgrasp.physics.fingertip.geometry.pair_geometry` by NumPy."""
    if len(facet) == 0:
        return _empty()
    fi, fj = np.asarray(finger), np.asarray(facet)
    return _narrow_phase(x, facets, centres, radii, fi, fj, closest, keep_all=True, corners=corners)


def candidates_nodes(
    x: NDArray[np.float64], index: FacetIndex, centres, radii
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(finger, facet) candidates from the surface nodes near each fingertip, O(B) with a tiny
    constant (see :func:`broad_phase_reach`)."""
    xb = x[index.boundary_nodes]
    reach = broad_phase_reach(index)
    fi, fj = [], []
    for i, (c, R) in enumerate(zip(centres, radii, strict=True)):
        d2 = np.einsum("ij,ij->i", xb - c, xb - c)
        nodes = index.boundary_nodes[d2 < (R + reach) ** 2]
        if nodes.size == 0:
            continue
        starts, ends = index.indptr[nodes], index.indptr[nodes + 1]
        lens = ends - starts
        offs = np.repeat(starts - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens)
        near = np.unique(index.indices[np.arange(lens.sum()) + offs])
        fj.append(near)
        fi.append(np.full(near.size, i, dtype=np.int64))
    if not fj:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(fi), np.concatenate(fj)


def relative_velocity(
    pairs: ContactPairs,
    facets: NDArray[np.int64],
    v: NDArray[np.float64],
    centres: NDArray[np.float64],
    velocities: NDArray[np.float64],
    omegas: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Relative velocity of the fingertip with respect to the facet at each contact point.

    ``V_finger(P) = V_c + Omega x (P - c)`` (Eq. 1); ``V_facet(P) = sum_i (A_i/A_G) V_Ni`` (Eq. 4);
    ``V_r = V_finger - V_facet`` (Eq. 5); normal part ``(V_r·n) n`` (Eq. 6), tangential rest (Eq. 7).

    Returns
    -------
    (V_r (k, 3), V_n (k, 3), V_t (k, 3)) [m/s]
    """
    vf = velocities[pairs.finger] + np.cross(omegas[pairs.finger], pairs.point - centres[pairs.finger])
    vfacet = np.einsum("ki,kij->kj", pairs.bary, v[facets[pairs.facet]])
    vr = vf - vfacet
    vn = np.einsum("ij,ij->i", vr, pairs.normal)[:, None] * pairs.normal
    return vr, vn, vr - vn


def oracle_detect(
    x, facets, centres, radii, *, closest: bool, index: FacetIndex, corners=None
) -> ContactPairs:
    """The touching pairs by NumPy (the node-index broad phase, then the vectorised narrow phase
    of :mod:`softgrasp.physics.fingertip.geometry`), in the compiled detection's order."""
    fi, fj = candidates_nodes(x, index, centres, radii)
    if fj.size == 0:
        return _empty()
    return _narrow_phase(x, facets, centres, radii, fi, fj, closest, keep_all=False, corners=corners)


class OracleFingertipContact(FingertipContact):
    """:class:`~softgrasp.physics.fingertip.contact.FingertipContact` computed by NumPy."""

    def pairs(self, body: Body, x: NDArray[np.float64], t: float) -> ContactPairs:
        """Touching pairs at positions x and time t, detected by NumPy."""
        index = FacetIndex.of(body.mesh)
        return oracle_detect(
            x,
            body.mesh.facets,
            self.centres(t),
            self._radii(),
            closest=self._closest(),
            index=index,
            corners=self.corners(body),
        )

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

    def frozen(self, body: Body, t: float) -> OracleFingertipContact:
        """Held at time t, as the contact's own: the landing computed here at t, kept."""
        out = super().frozen(body, t)
        object.__setattr__(out, "_frozen_t", float(t))
        return out

    def _resolution(self, body: Body, pairs: ContactPairs, t: float) -> NDArray[np.float64]:
        """The mesh's resolution under each pair's finger (h_node, h_land, facet size) [m],
        (k, 3): at the point of the whole rest surface closest to the fingertip centre, (pi / 2)
        over the body's compliance sum b_l b_m / r_lm to a unit load there (r_ll the law's ratio
        times the facet's size); h_node of a load on one node."""
        nf = len(self.fingertips)
        kappa = self.params.resolution
        t = getattr(self, "_frozen_t", t)
        out = np.zeros((nf, 3))
        if self.params.law == "resolved" and kappa > 0:
            pts = np.asarray(body.mesh.points)
            tri = pts[body.mesh.facets]  # (F, 3, 3)
            for i, c in enumerate(self.centres(t)):
                cc = np.broadcast_to(c, (len(tri), 3))
                bary = barycentric(cc, tri[:, 0], tri[:, 1], tri[:, 2])
                inside = (bary >= 0).all(axis=1)
                q_out, b_out = closest_points(cc, tri[:, 0], tri[:, 1], tri[:, 2])
                bary = np.where(inside[:, None], bary, b_out)
                q = np.einsum("ki,kij->kj", bary, tri)
                j = int(np.argmin(np.linalg.norm(cc - q, axis=1)))
                size = np.sqrt(4.0 * 0.5 * np.linalg.norm(np.cross(tri[j, 1] - tri[j, 0], tri[j, 2] - tri[j, 0])) / np.sqrt(3.0))
                r = np.linalg.norm(tri[j][:, None, :] - tri[j][None, :, :], axis=-1)
                r[np.arange(3), np.arange(3)] = kappa * size
                out[i] = (0.5 * np.pi * kappa * size, 0.5 * np.pi / (bary[j] @ (1.0 / r) @ bary[j]), size)
        return out[pairs.finger]

    def _law(self, body: Body, pairs: ContactPairs, depth: NDArray[np.float64], t: float) -> NDArray[np.float64]:
        """The elastic normal law (force, slope, energy) of each pair at ``depth``, (k, 3)."""
        law = self.law_table(body, t)[pairs.finger]
        h = self._resolution(body, pairs, t)
        R = law[:, 5]
        n = self.params.exponent
        out = [elastic_normal_value(float(d), float(r), float(l[0]), n, float(l[1]), *map(float, hh))
               for d, r, l, hh in zip(depth, R, law, h)]  # fmt: skip
        return np.array(out, dtype=np.float64).reshape(-1, 3)

    def _tangential_stiffness(self, body: Body, pairs: ContactPairs, t: float) -> NDArray[np.float64]:
        """k_t of each pair [N/m]: Mindlin's ratio times dF_n/d delta at the pair's penetration
        (not below ``min_depth_ratio`` R)."""
        p = self.params
        depth = np.maximum(self._depths(pairs), p.min_depth_ratio * self._radii()[pairs.finger])
        return self._ratio(body) * self._law(body, pairs, depth, t)[:, 1]

    def _evaluate(
        self, body: Body, x, v, t: float, state: FingerState, static: bool, pairs: ContactPairs | None = None
    ) -> _Eval:
        p = self.params
        if pairs is None:
            pairs = self.pairs(body, x, t)
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
        depth = self._depths(pairs)
        law = self._law(body, pairs, depth, t)
        dn = np.maximum(depth, 0.0) ** n_exp
        vec = np.vectorize(normal_force_value, otypes=[np.float64])
        raw = vec(depth, law[:, 0], dn, rate, C, p.damping == "hunt-crossley") if len(pairs) else np.zeros(0)
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
            kt = self._tangential_stiffness(body, pairs, t)
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
        deep = self._deepest(pairs) if p.rule == "patch" and len(pairs) else np.arange(len(pairs))
        return _Eval(pairs, fn, ft, w, kt, stick, cap, slipping, depth, deep, law[:, 0], law[:, 1], law[:, 2])

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

    def forces(self, body: Body, x, v, t: float, state: FingerState) -> NDArray[np.float64]:
        """Contact forces on the nodes during dynamics (Eq. 9-20)."""
        return self._nodal(body, x, self._evaluate(body, x, v, t, state, static=False))

    def static_forces(self, body: Body, x, t: float, state: FingerState) -> NDArray[np.float64]:
        """Contact forces at rest with lagged weights, limits and k_t."""
        return self._nodal(body, x, self._evaluate(body, x, None, t, state, static=True))

    def pinned_static_forces(self, body: Body, x_ref: NDArray[np.float64], t: float, state: FingerState):
        """The static contact forces of the pairs touching at ``x_ref``, followed to ``x``."""
        ref = self.pairs(body, x_ref, t)
        closest = self._closest()
        finger, facet = np.array(ref.finger), np.array(ref.facet)
        centres, radii = self.centres(t), self._radii()

        def forces(x: NDArray[np.float64]) -> NDArray[np.float64]:
            corners, facets = self.corners(body), body.mesh.facets
            pairs = pair_geometry(x, facets, centres, radii, finger, facet, closest=closest, corners=corners)
            return self._nodal(body, x, self._evaluate(body, x, None, t, state, static=True, pairs=pairs))

        return forces

    def update(self, body: Body, x, v, t: float, state: FingerState) -> FingerState:
        """Algorithm 1's state update."""
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
            w = self._patch_weights(pairs)
            elastic = self._law(body, pairs, self._depths(pairs), t)[:, 0]
            kt = self._tangential_stiffness(body, pairs, t)
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



def oracle_scene(scene):
    """``scene`` with its body an :class:`oracles.forces.OracleBody` and its fingertip contacts
    :class:`OracleFingertipContact` (other interactions as they are)."""
    body = OracleBody.of(scene.body)
    inters = tuple(
        OracleFingertipContact(i.fingertips, i.params, i.name) if type(i) is FingertipContact else i
        for i in scene.interactions
    )
    return dataclasses.replace(scene, body=body, interactions=inters)
