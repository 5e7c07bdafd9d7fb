"""Fingertip-facet contact detection (paper Sec. 3.1) and contact-point kinematics (Eq. 1-8).

A fingertip is a sphere of centre c and radius R. It touches boundary facet j when the projection
P_j of c on the facet's plane lies inside the triangle and the distance d_j = (c - P_j)·n_j from
the plane, measured along the facet's outward normal, satisfies 0 < d_j < R. Its penetration is
delta_j = R - d_j (Eq. 14). With ``fade`` > 0, projections up to ``fade`` outside the triangle in
barycentric units also count, each pair carrying a reach factor that falls linearly from 1 on the
triangle's edge to 0 at that distance (the patch rule weights facets by it, so no facet leaves the
contact at finite weight), and an *overlap* R - |c - Q_j| measured to the closest point Q_j of the
triangle (equal to the depth when the projection falls inside): the true overlap of the sphere with
the facet, so that a facet's plane extended past a convex edge adds no phantom contact.

Broad phase: the surface nodes near each fingertip and the facets around them (a node-to-facet
index computed once per mesh, :class:`FacetIndex`), so the cost grows with the boundary nodes at a
few microseconds per thousand, not with F log F; without an index, a k-d tree of facet centroids.
With an index and the compiled kernels selected (:mod:`softgrasp.kernels`), :func:`detect` runs
both phases in one compiled pass (:mod:`softgrasp.kernels.contact`); the NumPy code here is the
reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from softgrasp import kernels
from softgrasp.mesh.tetmesh import TetMesh

__all__ = ["ContactPairs", "FacetIndex", "detect", "pair_geometry", "barycentric", "relative_velocity"]

#: Tolerance on barycentric coordinates for "inside the triangle" (shared edges count for both).
INSIDE_TOL = 1e-12


@dataclass(frozen=True)
class ContactPairs:
    """Touching (fingertip, facet) pairs at one configuration.

    Attributes
    ----------
    finger: fingertip index of each pair, (k,).
    facet: boundary facet index of each pair, (k,).
    bary: barycentric (area) coordinates A_i / A_G of the contact point, (k, 3) (Eq. 4, 8).
    point: contact point P_j, the projection of the centre on the facet [m], (k, 3).
    normal: outward unit normal of the facet [m], (k, 3).
    distance: d_j, centre-to-plane distance [m], (k,).
    depth: delta_j = R - d_j [m], (k,) (Eq. 14).
    area: current facet area [m^2], (k,).
    reach: 1 when the projection falls inside the facet, fading to 0 at ``fade`` outside it, (k,).
    overlap: R - distance from the centre to the closest point of the triangle [m], (k,); equals
        ``depth`` when the projection falls inside; > 0 for every pair detected with ``fade`` > 0.
    near: barycentric coordinates of that closest point, (k, 3).
    """

    finger: NDArray[np.int64]
    facet: NDArray[np.int64]
    bary: NDArray[np.float64]
    point: NDArray[np.float64]
    normal: NDArray[np.float64]
    distance: NDArray[np.float64]
    depth: NDArray[np.float64]
    area: NDArray[np.float64]
    reach: NDArray[np.float64]
    overlap: NDArray[np.float64]
    near: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.finger.size)


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
    projections fall outside them: the nearest of the three edges' closest points.
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


@dataclass(frozen=True)
class FacetIndex:
    """What the node-based broad phase needs of a mesh, computed once per mesh.

    Attributes
    ----------
    boundary_nodes: nodes on the surface, (B,).
    indptr, indices: boundary facets around each node, CSR (:attr:`TetMesh.node_facets`).
    max_edge: longest facet edge at rest [m].
    """

    boundary_nodes: NDArray[np.int64]
    indptr: NDArray[np.int64]
    indices: NDArray[np.int64]
    max_edge: float

    @classmethod
    def of(cls, mesh: TetMesh) -> FacetIndex:
        indptr, indices = mesh.node_facets
        return cls(mesh.boundary_nodes, indptr, indices, mesh.max_facet_edge)


#: Surface edges may stretch up to this factor of their rest length for the node-based broad phase.
MAX_STRETCH = 3.0


def broad_phase_reach(index: FacetIndex, fade: float) -> float:
    """Margin [m] beyond a fingertip's radius within which a surface node may carry a facet in
    contact: (1 + 3 fade) x the longest rest facet edge x :data:`MAX_STRETCH`."""
    return (1.0 + 3.0 * fade) * MAX_STRETCH * index.max_edge


def _candidates_tree(
    x: NDArray[np.float64], facets: NDArray[np.int64], centres, radii, fade: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(finger, facet) candidates from a k-d tree of all facet centroids, O(F log F)."""
    tri = x[facets]
    cen = tri.mean(axis=1)
    # Projections with barycentric coordinates >= -fade lie in the triangle scaled by 1 + 3 fade
    # about its centroid.
    extent = (1.0 + 3.0 * fade) * float(np.linalg.norm(tri - cen[:, None, :], axis=2).max())
    tree = cKDTree(cen)
    fi, fj = [], []
    for i, (c, R) in enumerate(zip(centres, radii, strict=True)):
        near = np.asarray(tree.query_ball_point(c, R + extent), dtype=np.int64)
        fj.append(near)
        fi.append(np.full(near.size, i, dtype=np.int64))
    return np.concatenate(fi), np.concatenate(fj)


def _candidates_nodes(
    x: NDArray[np.float64], index: FacetIndex, centres, radii, fade: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(finger, facet) candidates from the surface nodes near each fingertip, O(B) with a tiny
    constant: every point of a facet's fade-extended triangle lies within
    (1 + 3 fade) x its longest edge of one of its nodes, and edges are taken to stretch at most
    MAX_STRETCH times their rest length."""
    xb = x[index.boundary_nodes]
    reach = broad_phase_reach(index, fade)
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


def detect(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    *,
    fade: float = 0.0,
    index: FacetIndex | None = None,
) -> ContactPairs:
    """All touching (fingertip, facet) pairs (Sec. 3.1).

    Parameters
    ----------
    x: node positions [m], (N, 3).  facets: boundary facets (F, 3), outward ordering.
    centres: fingertip centres [m], (n_f, 3).  radii: fingertip radii [m], (n_f,).
    fade: how far outside a triangle, in barycentric units, a projection still touches (with a
        reach factor fading to 0 there); 0 is the paper's test.
    index: the mesh's :class:`FacetIndex`: the broad phase then looks at the surface nodes near
        each fingertip (cost ~ boundary nodes, a few microseconds per thousand) instead of
        building a k-d tree of all facet centroids (cost ~ F log F).
    """
    if index is not None and kernels.compiled():
        return _detect_compiled(x, facets, centres, radii, fade, index)
    if index is None:
        fi, fj = _candidates_tree(x, facets, centres, radii, fade)
    else:
        fi, fj = _candidates_nodes(x, index, centres, radii, fade)
    if fj.size == 0:
        return _empty()
    return _narrow_phase(x, facets, centres, radii, fi, fj, fade, keep_all=False)


def pair_geometry(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    finger: NDArray[np.int64],
    facet: NDArray[np.int64],
    *,
    fade: float = 0.0,
) -> ContactPairs:
    """The geometry of given (fingertip, facet) pairs at ``x``, whether they touch there or not
    (depths may be <= 0, projections outside the triangles): the pairs of an earlier
    :func:`detect`, followed through a small displacement (derivatives along a direction with
    the contact set fixed, as a Jacobian assumes)."""
    if len(facet) == 0:
        return _empty()
    return _narrow_phase(
        x, facets, centres, radii, np.asarray(finger), np.asarray(facet), fade, keep_all=True
    )


def _narrow_phase(x, facets, centres, radii, fi, fj, fade: float, keep_all: bool) -> ContactPairs:
    """Pair geometry of the candidate pairs (fi, fj); the touching ones only unless ``keep_all``."""
    tri = x[facets[fj]]  # (k, 3, 3) candidates only
    a, b, c3 = tri[:, 0], tri[:, 1], tri[:, 2]
    nrm = np.cross(b - a, c3 - a)
    twice_area = np.linalg.norm(nrm, axis=1)
    n = nrm / twice_area[:, None]
    ctr = centres[fi]
    d = np.einsum("ij,ij->i", ctr - a, n)
    R = radii[fi]
    P = ctr - d[:, None] * n
    bary = barycentric(P, a, b, c3)
    low = bary.min(axis=1)
    near = bary.copy()
    overlap = R - d
    if fade > 0:
        reach = np.clip(1.0 + low / fade, 0.0, 1.0)
        out = np.flatnonzero((low < 0) & (reach > 0) & (d > 0) & (d < R))
        if out.size:
            q, near[out] = closest_points(ctr[out], a[out], b[out], c3[out])
            overlap[out] = R[out] - np.linalg.norm(ctr[out] - q, axis=1)
        ok = (d > 0) & (d < R) & (reach > 0) & (overlap > 0)
    else:
        reach = np.ones(len(fj))
        ok = (d > 0) & (d < R) & (low >= -INSIDE_TOL)
    if keep_all:
        ok = np.ones(len(fj), bool)
    return ContactPairs(
        finger=fi[ok],
        facet=fj[ok],
        bary=bary[ok],
        point=P[ok],
        normal=n[ok],
        distance=d[ok],
        depth=R[ok] - d[ok],
        area=0.5 * twice_area[ok],
        reach=reach[ok],
        overlap=overlap[ok],
        near=near[ok],
    )


def _detect_compiled(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    fade: float,
    index: FacetIndex,
) -> ContactPairs:
    """:func:`detect` with the node-index broad phase, by the compiled kernel
    (:mod:`softgrasp.kernels.contact`): the same pairs in the same order, fields equal to
    round-off. The float fields are read-only views of one (k, 17) array."""
    from softgrasp.kernels.contact import detect_arrays

    reach = broad_phase_reach(index, fade)
    fi, fj, val = detect_arrays(
        x, facets, index.boundary_nodes, index.indptr, index.indices, reach, centres, radii, fade, INSIDE_TOL
    )
    val.flags.writeable = False
    return ContactPairs(
        finger=fi,
        facet=fj,
        bary=val[:, 0:3],
        point=val[:, 3:6],
        normal=val[:, 6:9],
        distance=val[:, 9],
        depth=val[:, 10],
        area=val[:, 11],
        reach=val[:, 12],
        overlap=val[:, 13],
        near=val[:, 14:17],
    )


def _empty() -> ContactPairs:
    z3 = np.zeros((0, 3))
    z = np.zeros(0)
    return ContactPairs(np.zeros(0, np.int64), np.zeros(0, np.int64), z3, z3, z3, z, z, z, z, z, z3)


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
