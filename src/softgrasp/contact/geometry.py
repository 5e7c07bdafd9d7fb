"""Fingertip-facet contact detection (paper Sec. 3.1) and contact-point kinematics (Eq. 1-8).

A fingertip is a sphere of centre c and radius R. It touches boundary facet j when the projection
P_j of c on the facet's plane lies inside the triangle and the distance d_j = (c - P_j)·n_j from
the plane, measured along the facet's outward normal, satisfies 0 < d_j < R. Its penetration is
delta_j = R - d_j (Eq. 14). With ``fade`` > 0, projections up to ``fade`` outside the triangle in
barycentric units also count, each pair carrying a reach factor that falls linearly from 1 on the
triangle's edge to 0 at that distance (the patch rule weights facets by it, so no facet leaves the
contact at finite weight). A broad phase (a k-d tree on facet centroids) keeps the cost
proportional to the facets near the fingertips.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

__all__ = ["ContactPairs", "detect", "barycentric", "relative_velocity"]

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


def detect(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    *,
    fade: float = 0.0,
) -> ContactPairs:
    """All touching (fingertip, facet) pairs (Sec. 3.1).

    Parameters
    ----------
    x: node positions [m], (N, 3).  facets: boundary facets (F, 3), outward ordering.
    centres: fingertip centres [m], (n_f, 3).  radii: fingertip radii [m], (n_f,).
    fade: how far outside a triangle, in barycentric units, a projection still touches (with a
        reach factor fading to 0 there); 0 is the paper's test.
    """
    tri = x[facets]  # (F, 3, 3)
    cen = tri.mean(axis=1)
    # Projections with barycentric coordinates >= -fade lie in the triangle scaled by 1 + 3 fade
    # about its centroid.
    extent = (1.0 + 3.0 * fade) * float(np.linalg.norm(tri - cen[:, None, :], axis=2).max())
    tree = cKDTree(cen)
    fingers: list[NDArray[np.int64]] = []
    cand: list[NDArray[np.int64]] = []
    for i, (c, R) in enumerate(zip(centres, radii, strict=True)):
        near = np.asarray(tree.query_ball_point(c, R + extent), dtype=np.int64)
        cand.append(near)
        fingers.append(np.full(near.size, i, dtype=np.int64))
    fi = np.concatenate(fingers) if fingers else np.zeros(0, np.int64)
    fj = np.concatenate(cand) if cand else np.zeros(0, np.int64)
    if fj.size == 0:
        return _empty()
    a, b, c3 = tri[fj, 0], tri[fj, 1], tri[fj, 2]
    nrm = np.cross(b - a, c3 - a)
    twice_area = np.linalg.norm(nrm, axis=1)
    n = nrm / twice_area[:, None]
    ctr = centres[fi]
    d = np.einsum("ij,ij->i", ctr - a, n)
    R = radii[fi]
    P = ctr - d[:, None] * n
    bary = barycentric(P, a, b, c3)
    low = bary.min(axis=1)
    if fade > 0:
        reach = np.clip(1.0 + low / fade, 0.0, 1.0)
        ok = (d > 0) & (d < R) & (reach > 0)
    else:
        reach = np.ones(len(fj))
        ok = (d > 0) & (d < R) & (low >= -INSIDE_TOL)
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
    )


def _empty() -> ContactPairs:
    z3 = np.zeros((0, 3))
    z = np.zeros(0)
    return ContactPairs(np.zeros(0, np.int64), np.zeros(0, np.int64), z3, z3, z3, z, z, z, z)


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
