"""Compiled (Numba) fingertip-facet contact: detection (paper Sec. 3.1) and forces.

* :func:`detect_arrays`: the same broad phase (surface nodes near each fingertip, then the facets
  around them, through the mesh's :class:`~softgrasp.physics.fingertip.geometry.FacetIndex`) and narrow phase
  (contact point, barycentric coordinates, contact normal, facing factor) as the NumPy
  reference :func:`softgrasp.physics.fingertip.geometry.detect`, in one pass. Pairs come out in the reference's order
  (by fingertip, then by facet index).
* :func:`fingertip_forces`: detection, relative velocity (Eq. 1-8), normal force (Eq. 9-14) with
  the patch or literal rule, elastic-slider friction with the Coulomb cap (Eq. 15-16, Algorithm 1)
  and the nodal distribution (Eq. 17-20) of
  :meth:`softgrasp.physics.fingertip.contact.FingertipContact.forces`, in one compiled call;
  :func:`fingertip_update` likewise for the friction state update (Algorithm 1) of
  :meth:`~softgrasp.physics.fingertip.contact.FingertipContact.update`, and :func:`fingertip_static_forces`
  for the forces at rest, of the touching pairs or of a pinned pair set (the static solver's
  residual and its exact Newton product, one compiled call each).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["detect_arrays", "fingertip_forces", "fingertip_static_forces", "fingertip_update"]

_jit = numba.njit(cache=True, fastmath=False, error_model="numpy")


@_jit
def _closest_point(px, py, pz, tri, near):  # pragma: no cover - compiled
    """Squared distance from p to the closest point of triangle ``tri`` (3, 3) on its edges (p's
    projection lies outside it); that point's barycentric coordinates are written to ``near``.
    Edges (0, 1), (1, 2), (2, 0) in that order, a later edge winning only when strictly closer."""
    best = math.inf
    for m in range(3):
        i = m
        j = (m + 1) % 3
        ex = tri[j, 0] - tri[i, 0]
        ey = tri[j, 1] - tri[i, 1]
        ez = tri[j, 2] - tri[i, 2]
        t = ((px - tri[i, 0]) * ex + (py - tri[i, 1]) * ey + (pz - tri[i, 2]) * ez) / (
            ex * ex + ey * ey + ez * ez
        )
        t = min(max(t, 0.0), 1.0)
        qx = px - (tri[i, 0] + t * ex)
        qy = py - (tri[i, 1] + t * ey)
        qz = pz - (tri[i, 2] + t * ez)
        d2 = qx * qx + qy * qy + qz * qz
        if d2 < best:
            best = d2
            near[0] = 0.0
            near[1] = 0.0
            near[2] = 0.0
            near[i] = 1.0 - t
            near[j] = t
    return best


@_jit
def _pair_values(tri, cx, cy, cz, R, closest, inside_tol, keep, near, row):  # pragma: no cover
    """Narrow phase of the sphere (centre c, radius R) against triangle ``tri`` (3, 3): writes the
    pair's values to ``row`` (13: bary 0-2, point 3-5, normal 6-8, distance 9, depth 10, area 11,
    facing 12; ``near`` (3) is scratch) and returns whether it touches (as
    :func:`softgrasp.physics.fingertip.geometry.detect` with ``closest`` decides). With ``keep`` the values
    are written whether it touches or not, and it returns True (a pinned pair followed through a
    small displacement, as :func:`softgrasp.physics.fingertip.geometry.pair_geometry`: depth may be <= 0)."""
    ux = tri[1, 0] - tri[0, 0]
    uy = tri[1, 1] - tri[0, 1]
    uz = tri[1, 2] - tri[0, 2]
    wx = tri[2, 0] - tri[0, 0]
    wy = tri[2, 1] - tri[0, 1]
    wz = tri[2, 2] - tri[0, 2]
    Nx = uy * wz - uz * wy
    Ny = uz * wx - ux * wz
    Nz = ux * wy - uy * wx
    twice_area = math.sqrt(Nx * Nx + Ny * Ny + Nz * Nz)
    nx = Nx / twice_area
    ny = Ny / twice_area
    nz = Nz / twice_area
    d = (cx - tri[0, 0]) * nx + (cy - tri[0, 1]) * ny + (cz - tri[0, 2]) * nz
    if not keep and not (d > 0.0 and d < R):  # facing the centre, and within reach of the sphere
        return False
    Px = cx - d * nx
    Py = cy - d * ny
    Pz = cz - d * nz
    # barycentric coordinates of P (as softgrasp.physics.fingertip.geometry.barycentric)
    vx = Px - tri[0, 0]
    vy = Py - tri[0, 1]
    vz = Pz - tri[0, 2]
    d00 = ux * ux + uy * uy + uz * uz
    d01 = ux * wx + uy * wy + uz * wz
    d11 = wx * wx + wy * wy + wz * wz
    d20 = vx * ux + vy * uy + vz * uz
    d21 = vx * wx + vy * wy + vz * wz
    den = d00 * d11 - d01 * d01
    wb = (d11 * d20 - d01 * d21) / den
    wc = (d00 * d21 - d01 * d20) / den
    wa = 1.0 - wb - wc
    low = min(wa, wb, wc)
    near[0] = wa
    near[1] = wb
    near[2] = wc
    dist = d
    fac = 1.0
    Qx = Px
    Qy = Py
    Qz = Pz
    if closest:
        dist = abs(d)  # |c - P| (d > 0 for a touching pair)
        if low < 0.0:  # the closest point lies on an edge
            _closest_point(cx, cy, cz, tri, near)
            Qx = near[0] * tri[0, 0] + near[1] * tri[1, 0] + near[2] * tri[2, 0]
            Qy = near[0] * tri[0, 1] + near[1] * tri[1, 1] + near[2] * tri[2, 1]
            Qz = near[0] * tri[0, 2] + near[1] * tri[1, 2] + near[2] * tri[2, 2]
            ex = cx - Qx
            ey = cy - Qy
            ez = cz - Qz
            dist = math.sqrt(ex * ex + ey * ey + ez * ez)
            if not keep and not dist < R:
                return False
        fac = min(max(d / (dist if dist > 0.0 else 1.0), 0.0), 1.0)
    elif not keep and not low >= -inside_tol:
        return False
    row[0] = near[0]
    row[1] = near[1]
    row[2] = near[2]
    row[3] = Qx
    row[4] = Qy
    row[5] = Qz
    row[6] = nx
    row[7] = ny
    row[8] = nz
    row[9] = dist
    row[10] = R - dist
    row[11] = 0.5 * twice_area
    row[12] = fac
    return True


@_jit
def _detect(
    x, facets, boundary, indptr, indices, reach, centres, radii, closest, inside_tol
):  # pragma: no cover
    """Touching pairs (see :func:`detect_arrays`), per fingertip in increasing facet order."""
    n_fingers = centres.shape[0]
    F = facets.shape[0]
    mark = np.zeros(8 * ((F + 7) // 8), np.uint8)  # scanned eight facets a word
    words = mark.view(np.uint64)
    cap = n_fingers * F  # at most every facet for every finger (np.empty: nothing is touched)
    finger = np.empty(cap, np.int64)
    facet = np.empty(cap, np.int64)
    real = np.empty((cap, 13))  # bary 3, point 3, normal 3, distance, depth, area, facing
    tri = np.empty((3, 3))
    near = np.empty(3)
    grow = 1.0 + 3.0 * inside_tol
    k = 0
    for f in range(n_fingers):
        cx = centres[f, 0]
        cy = centres[f, 1]
        cz = centres[f, 2]
        R = radii[f]
        r2 = (R + reach) ** 2
        # broad phase: facets around the surface nodes within R + reach of the centre
        for b in range(boundary.shape[0]):
            node = boundary[b]
            dx = x[node, 0] - cx
            dy = x[node, 1] - cy
            dz = x[node, 2] - cz
            if dx * dx + dy * dy + dz * dz < r2:
                for p in range(indptr[node], indptr[node + 1]):
                    mark[indices[p]] = 1
        # narrow phase, the marked facets in increasing order (a word of eight unmarked skipped at once)
        q = 0
        while q < F:
            if q % 8 == 0 and words[q // 8] == 0:
                q += 8
                continue
            j = q
            q += 1
            if not mark[j]:
                continue
            mark[j] = 0
            for r in range(3):
                node = facets[j, r]
                tri[r, 0] = x[node, 0]
                tri[r, 1] = x[node, 1]
                tri[r, 2] = x[node, 2]
            # Quick rejection, exact and conservative: every contact point (inside the triangle,
            # up to inside_tol) lies within (1 + 3 inside_tol) x its largest vertex distance of its
            # centroid g, so a pair needs |c - g| < R + that.
            gx = (tri[0, 0] + tri[1, 0] + tri[2, 0]) / 3.0
            gy = (tri[0, 1] + tri[1, 1] + tri[2, 1]) / 3.0
            gz = (tri[0, 2] + tri[1, 2] + tri[2, 2]) / 3.0
            rmax2 = 0.0
            for r in range(3):
                ex = tri[r, 0] - gx
                ey = tri[r, 1] - gy
                ez = tri[r, 2] - gz
                rmax2 = max(rmax2, ex * ex + ey * ey + ez * ez)
            lim = (R + grow * math.sqrt(rmax2)) * (1.0 + 1e-9)
            ex = cx - gx
            ey = cy - gy
            ez = cz - gz
            if ex * ex + ey * ey + ez * ez > lim * lim:
                continue
            if not _pair_values(tri, cx, cy, cz, R, closest, inside_tol, False, near, real[k]):
                continue
            finger[k] = f
            facet[k] = j
            k += 1
    return finger[:k].copy(), facet[:k].copy(), real[:k].copy()


def _geometry_args(x, facets, boundary_nodes, indptr, indices, reach, centres, radii) -> tuple:
    """The mesh, broad-phase index and fingertip arguments every compiled contact kernel takes
    first, as the contiguous float64 / int64 arrays (and floats) the kernels are compiled for."""
    f64, i64 = np.float64, np.int64
    return (
        np.ascontiguousarray(x, dtype=f64),
        np.ascontiguousarray(facets, dtype=i64),
        np.ascontiguousarray(boundary_nodes, dtype=i64),
        np.ascontiguousarray(indptr, dtype=i64),
        np.ascontiguousarray(indices, dtype=i64),
        float(reach),
        np.ascontiguousarray(centres, dtype=f64).reshape(-1, 3),
        np.ascontiguousarray(radii, dtype=f64).ravel(),
    )


def _law_args(K, closest, inside_tol, mu, exponent, patch, ratio, min_depth_ratio) -> tuple:
    """The contact law's arguments of the compiled kernels, as the types they are compiled for."""
    return (
        np.ascontiguousarray(K, dtype=np.float64).ravel(),
        bool(closest),
        float(inside_tol),
        float(mu),
        float(exponent),
        bool(patch),
        float(ratio),
        float(min_depth_ratio),
    )


def _state_args(active, anchor, offset) -> tuple:
    """The friction state's pair arrays (active, anchor, offset) as the compiled kernels take them."""
    f64 = np.float64
    return (
        np.ascontiguousarray(active, dtype=np.bool_),
        np.ascontiguousarray(anchor, dtype=f64),
        np.ascontiguousarray(offset, dtype=f64),
    )


def detect_arrays(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    boundary_nodes: NDArray[np.int64],
    indptr: NDArray[np.int64],
    indices: NDArray[np.int64],
    reach: float,
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    closest: bool,
    inside_tol: float,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """Touching pairs: (finger (k,), facet (k,), values (k, 13)) with values' columns bary 0-2,
    point 3-5, normal 6-8, distance 9, depth 10, area 11, facing 12 (the fields of
    :class:`~softgrasp.physics.fingertip.geometry.ContactPairs`).

    ``reach`` [m] is the broad phase's margin beyond each radius (a surface node farther than
    R + reach from a centre has no facet in contact)."""
    return _detect(
        *_geometry_args(x, facets, boundary_nodes, indptr, indices, reach, centres, radii),
        bool(closest),
        float(inside_tol),
    )


@_jit
def _patch(finger, val, nf):  # pragma: no cover - compiled
    """Each finger's deepest pair (the first of largest depth; -1 without pairs) and the sum of
    its pairs' patch weights ``area x depth x facing``."""
    deep = np.full(nf, -1, np.int64)
    total = np.zeros(nf)
    for p in range(finger.shape[0]):
        f = finger[p]
        if deep[f] < 0 or val[p, 10] > val[deep[f], 10]:
            deep[f] = p
        total[f] += val[p, 11] * val[p, 10] * val[p, 12]
    return deep, total


@_jit
def _finger_powers(deep, val, radii, K, n_exp, ratio, min_depth_ratio):  # pragma: no cover - compiled
    """Per finger, ``max(delta, 0)^n`` and k_t at its deepest pair's depth (0 without pairs): the
    patch rule evaluates every pair of a finger there, so the powers are taken once a finger
    instead of once a pair (the same values)."""
    nf = deep.shape[0]
    dn = np.zeros(nf)
    kt = np.zeros(nf)
    for f in range(nf):
        if deep[f] >= 0:
            d = val[deep[f], 10]
            dn[f] = max(d, 0.0) ** n_exp
            kt[f] = _tangential_stiffness(d, radii[f], K[f], n_exp, ratio, min_depth_ratio)
    return dn, kt


@_jit
def _weight_depth(p, f, val, deep, total, patch):  # pragma: no cover - compiled
    """Pair p's weight w_j and the penetration its normal law is evaluated at."""
    if patch:
        return val[p, 11] * val[p, 10] * val[p, 12] / total[f], val[deep[f], 10]
    return 1.0, val[p, 10]


@_jit
def _stick(p, f, j, val, x, facets, centres, active, anchor, offset, memory):  # pragma: no cover
    """Tangential stick displacement (Eq. 16) of pair p: (c - X_a) - o in the facet's plane, with
    X_a the anchor (a material point of the facet) and o the centre's offset from it when it was
    set; a new pair is anchored at its contact point with the finger's memory as its stick.
    Returns (s_x, s_y, s_z, whether the pair continues, X_a's x, y, z)."""
    cont = active[f, j]
    if cont:
        ax = 0.0
        ay = 0.0
        az = 0.0
        for m in range(3):
            node = facets[j, m]
            ax += anchor[f, j, m] * x[node, 0]
            ay += anchor[f, j, m] * x[node, 1]
            az += anchor[f, j, m] * x[node, 2]
        ox = offset[f, j, 0]
        oy = offset[f, j, 1]
        oz = offset[f, j, 2]
    else:
        ax = val[p, 3]
        ay = val[p, 4]
        az = val[p, 5]
        ox = centres[f, 0] - ax - memory[f, 0]
        oy = centres[f, 1] - ay - memory[f, 1]
        oz = centres[f, 2] - az - memory[f, 2]
    sx = centres[f, 0] - ax - ox
    sy = centres[f, 1] - ay - oy
    sz = centres[f, 2] - az - oz
    sn = sx * val[p, 6] + sy * val[p, 7] + sz * val[p, 8]
    return sx - sn * val[p, 6], sy - sn * val[p, 7], sz - sn * val[p, 8], cont, ax, ay, az


@_jit
def _tangential_stiffness(depth, radius, K, n_exp, ratio, min_depth_ratio):  # pragma: no cover
    """k_t = ratio x d(K delta^n)/d delta at max(delta, min_depth_ratio R)."""
    d = max(max(depth, min_depth_ratio * radius), 0.0)
    return ratio * (n_exp * K * d ** (n_exp - 1.0)) if d > 0.0 else 0.0


@_jit
def _relative_velocity(p, f, j, val, v, facets, centres, velocities, omegas):  # pragma: no cover
    """Tangential relative velocity (3 floats) and the penetration rate d delta / dt of pair p
    (Eq. 1-8)."""
    nx = val[p, 6]
    ny = val[p, 7]
    nz = val[p, 8]
    # relative velocity at the contact point: finger (Eq. 1) minus facet (Eq. 4)
    rx = val[p, 3] - centres[f, 0]
    ry = val[p, 4] - centres[f, 1]
    rz = val[p, 5] - centres[f, 2]
    vrx = velocities[f, 0] + (omegas[f, 1] * rz - omegas[f, 2] * ry)
    vry = velocities[f, 1] + (omegas[f, 2] * rx - omegas[f, 0] * rz)
    vrz = velocities[f, 2] + (omegas[f, 0] * ry - omegas[f, 1] * rx)
    for m in range(3):
        node = facets[j, m]
        vrx -= val[p, m] * v[node, 0]
        vry -= val[p, m] * v[node, 1]
        vrz -= val[p, m] * v[node, 2]
    vn = vrx * nx + vry * ny + vrz * nz
    vtx = vrx - vn * nx
    vty = vry - vn * ny
    vtz = vrz - vn * nz
    return vtx, vty, vtz, -vn


@_jit
def _pair_forces(
    finger, facet, val, x, v, facets, centres, radii, velocities, omegas, K, C, mu, n_exp, hunt_crossley,
    patch, ratio, min_depth_ratio, active, anchor, offset, memory, static, out,
):  # pragma: no cover - compiled
    """Forces of the pairs (finger, facet, val) (as :func:`_detect` gives them) added to ``out``
    (N, 3) (or wider: columns 0-2): normal force (Eq. 9-14, patch or literal rule), elastic-slider
    friction with the Coulomb cap (Eq. 15-16, Algorithm 1), nodal distribution (Eq. 17-20).
    ``static``: at rest (no relative velocity: no damping, a slipping pair capped along its stick), as
    :meth:`softgrasp.physics.fingertip.contact.FingertipContact.static_forces`; ``v``, ``velocities`` and
    ``omegas`` are then not read."""
    deep, total = _patch(finger, val, centres.shape[0])
    dnf, ktf = _finger_powers(deep, val, radii, K, n_exp, ratio, min_depth_ratio)
    for p in range(finger.shape[0]):
        f = finger[p]
        j = facet[p]
        nx = val[p, 6]
        ny = val[p, 7]
        nz = val[p, 8]
        vtx = 0.0
        vty = 0.0
        vtz = 0.0
        rate = 0.0
        if not static:
            vtx, vty, vtz, rate = _relative_velocity(p, f, j, val, v, facets, centres, velocities, omegas)
        w, depth = _weight_depth(p, f, val, deep, total, patch)
        # normal force (Eq. 9), zero unless delta > 0, never pulling
        dn = dnf[f] if patch else max(depth, 0.0) ** n_exp
        if hunt_crossley:
            raw = dn * (K[f] + C[f] * rate)
        else:
            raw = K[f] * dn + C[f] * rate
        raw = max(raw, 0.0) if depth > 0.0 else 0.0
        fn = w * raw
        ftx = 0.0
        fty = 0.0
        ftz = 0.0
        if mu > 0.0:
            sx, sy, sz, _, _, _, _ = _stick(p, f, j, val, x, facets, centres, active, anchor, offset, memory)
            if patch:
                kt = ktf[f]
            else:
                kt = _tangential_stiffness(depth, radii[f], K[f], n_exp, ratio, min_depth_ratio)
            a = -(w * kt)
            b = w * (ratio * C[f])
            ftx = a * sx - b * vtx
            fty = a * sy - b * vty
            ftz = a * sz - b * vtz
            cap = mu * fn
            mag = math.sqrt(ftx * ftx + fty * fty + ftz * ftz)
            if mag > cap:
                speed = math.sqrt(vtx * vtx + vty * vty + vtz * vtz)
                if speed > 0.0:  # Coulomb slip (Eq. 15)
                    ftx = -mu * fn * (vtx / speed)
                    fty = -mu * fn * (vty / speed)
                    ftz = -mu * fn * (vtz / speed)
                else:
                    r = cap / mag
                    ftx *= r
                    fty *= r
                    ftz *= r
        # the pair's force on the object, spread by the shape functions (Eq. 17-20)
        Fx = -fn * nx - ftx
        Fy = -fn * ny - fty
        Fz = -fn * nz - ftz
        for m in range(3):
            node = facets[j, m]
            out[node, 0] += val[p, m] * Fx
            out[node, 1] += val[p, m] * Fy
            out[node, 2] += val[p, m] * Fz


@_jit
def _fingertip_forces(
    x,
    v,
    facets,
    boundary,
    indptr,
    indices,
    reach,
    centres,
    radii,
    velocities,
    omegas,
    K,
    C,
    closest,
    inside_tol,
    mu,
    n_exp,
    hunt_crossley,
    patch,
    ratio,
    min_depth_ratio,
    active,
    anchor,
    offset,
    memory,
    out,
):  # pragma: no cover - compiled
    """Dynamic contact forces added to ``out`` (N, 3) (or wider: columns 0-2); returns the number of
    touching pairs."""
    finger, facet, val = _detect(
        x, facets, boundary, indptr, indices, reach, centres, radii, closest, inside_tol
    )
    _pair_forces(
        finger, facet, val, x, v, facets, centres, radii, velocities, omegas, K, C, mu, n_exp, hunt_crossley,
        patch, ratio, min_depth_ratio, active, anchor, offset, memory, False, out,
    )  # fmt: skip
    return finger.shape[0]


@_jit
def _pinned_values(x, facets, centres, radii, finger, facet, closest):  # pragma: no cover - compiled
    """The values (k, 13) of the given (finger, facet) pairs at ``x`` (:func:`_pair_values` with
    ``keep``), whether they touch there or not."""
    k = finger.shape[0]
    val = np.empty((k, 13))
    tri = np.empty((3, 3))
    near = np.empty(3)
    for p in range(k):
        f = finger[p]
        j = facet[p]
        for r in range(3):
            node = facets[j, r]
            tri[r, 0] = x[node, 0]
            tri[r, 1] = x[node, 1]
            tri[r, 2] = x[node, 2]
        cx, cy, cz = centres[f, 0], centres[f, 1], centres[f, 2]
        _pair_values(tri, cx, cy, cz, radii[f], closest, 0.0, True, near, val[p])
    return val


@_jit
def _static_forces(
    x, facets, boundary, indptr, indices, reach, centres, radii, K, closest, inside_tol, mu, n_exp, patch,
    ratio, min_depth_ratio, active, anchor, offset, memory, pinned, finger, facet, out,
):  # pragma: no cover - compiled
    """Contact forces at rest added to ``out`` (N, 3), of the touching pairs (detected), or with
    ``pinned`` of the given pairs (finger, facet) followed to ``x``."""
    if pinned:
        val = _pinned_values(x, facets, centres, radii, finger, facet, closest)
    else:
        finger, facet, val = _detect(
            x, facets, boundary, indptr, indices, reach, centres, radii, closest, inside_tol
        )
    # At rest (static=True) the loop reads no velocities: x, centres and K stand in for v, the
    # fingertips' velocities and spins, and C (which only multiplies the zero penetration rate).
    _pair_forces(
        finger, facet, val, x, x, facets, centres, radii, centres, centres, K, K, mu, n_exp, False, patch,
        ratio, min_depth_ratio, active, anchor, offset, memory, True, out,
    )  # fmt: skip


@_jit
def _fingertip_update(
    x,
    facets,
    boundary,
    indptr,
    indices,
    reach,
    centres,
    radii,
    K,
    closest,
    inside_tol,
    mu,
    n_exp,
    patch,
    ratio,
    min_depth_ratio,
    active,
    anchor,
    offset,
    slip,
    memory,
    new_active,
    new_anchor,
    new_offset,
    new_slip,
    new_memory,
):  # pragma: no cover - compiled
    """Algorithm 1's state update into the zeroed ``new_*`` arrays; returns the pair count."""
    finger, facet, val = _detect(
        x, facets, boundary, indptr, indices, reach, centres, radii, closest, inside_tol
    )
    return _update_pairs(
        finger, facet, val, x, facets, centres, radii, K, mu, n_exp, patch, ratio, min_depth_ratio, active,
        anchor, offset, slip, memory, new_active, new_anchor, new_offset, new_slip, new_memory,
    )  # fmt: skip


@_jit
def _update_pairs(
    finger, facet, val, x, facets, centres, radii, K, mu, n_exp, patch, ratio, min_depth_ratio, active,
    anchor, offset, slip, memory, new_active, new_anchor, new_offset, new_slip, new_memory,
):  # fmt: skip  # pragma: no cover - compiled
    """:func:`_fingertip_update` on the touching pairs ``finger, facet, val`` found by :func:`_detect`
    (the fused stepper detects once for the update and the forces at the same state)."""
    nf = centres.shape[0]
    deep, total = _patch(finger, val, nf)
    dnf, ktf = _finger_powers(deep, val, radii, K, n_exp, ratio, min_depth_ratio)
    wsum = np.zeros(nf)
    for p in range(finger.shape[0]):
        f = finger[p]
        j = facet[p]
        w, depth = _weight_depth(p, f, val, deep, total, patch)
        elastic = K[f] * (dnf[f] if patch else max(depth, 0.0) ** n_exp) if depth > 0.0 else 0.0
        elastic = max(elastic, 0.0)
        kt = ktf[f] if patch else _tangential_stiffness(depth, radii[f], K[f], n_exp, ratio, min_depth_ratio)
        sx, sy, sz, cont, ax, ay, az = _stick(
            p, f, j, val, x, facets, centres, active, anchor, offset, memory
        )
        ux = slip[f, j, 0] if cont else 0.0
        uy = slip[f, j, 1] if cont else 0.0
        uz = slip[f, j, 2] if cont else 0.0
        if mu > 0.0:
            lim = mu * w * elastic
            s_norm = math.sqrt(sx * sx + sy * sy + sz * sz)
            keff = w * kt
            if keff * s_norm > lim:  # slip: the stick is cut back to the Coulomb limit
                r = lim / (keff * s_norm)
                nsx = sx * r
                nsy = sy * r
                nsz = sz * r
                ux += sx - nsx
                uy += sy - nsy
                uz += sz - nsz
                sx = nsx
                sy = nsy
                sz = nsz
        else:
            sx = 0.0
            sy = 0.0
            sz = 0.0
        # the anchor stays (a new pair's at its contact point); the offset takes the slip
        for m in range(3):
            new_anchor[f, j, m] = anchor[f, j, m] if cont else val[p, m]
        new_offset[f, j, 0] = centres[f, 0] - ax - sx
        new_offset[f, j, 1] = centres[f, 1] - ay - sy
        new_offset[f, j, 2] = centres[f, 2] - az - sz
        new_active[f, j] = True
        new_slip[f, j, 0] = ux
        new_slip[f, j, 1] = uy
        new_slip[f, j, 2] = uz
        wsum[f] += w
        new_memory[f, 0] += w * sx
        new_memory[f, 1] += w * sy
        new_memory[f, 2] += w * sz
    for f in range(nf):
        ws = max(wsum[f], 1e-300)
        new_memory[f, 0] /= ws
        new_memory[f, 1] /= ws
        new_memory[f, 2] /= ws
    return finger.shape[0]


def fingertip_forces(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    facets: NDArray[np.int64],
    boundary_nodes: NDArray[np.int64],
    indptr: NDArray[np.int64],
    indices: NDArray[np.int64],
    reach: float,
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    velocities: NDArray[np.float64],
    omegas: NDArray[np.float64],
    K: NDArray[np.float64],
    C: NDArray[np.float64],
    *,
    closest: bool,
    inside_tol: float,
    mu: float,
    exponent: float,
    hunt_crossley: bool,
    patch: bool,
    ratio: float,
    min_depth_ratio: float,
    active: NDArray[np.bool_],
    anchor: NDArray[np.float64],
    offset: NDArray[np.float64],
    memory: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Contact forces on the nodes [N], (N, 3), of fingertips (centres, radii, velocities, omegas,
    stiffness K [N/m^n] and damping C [N s/m] per fingertip) with friction state (active (n_f, F),
    anchor (n_f, F, 3), offset (n_f, F, 3) [m], memory (n_f, 3) [m]); parameters as in
    :class:`softgrasp.physics.fingertip.params.ContactParams` (``ratio`` = k_t / k_n)."""
    f64 = np.float64
    geometry = _geometry_args(x, facets, boundary_nodes, indptr, indices, reach, centres, radii)
    out = np.zeros_like(geometry[0])
    _fingertip_forces(
        geometry[0],
        np.ascontiguousarray(v, dtype=f64),
        *geometry[1:],
        np.ascontiguousarray(velocities, dtype=f64).reshape(-1, 3),
        np.ascontiguousarray(omegas, dtype=f64).reshape(-1, 3),
        np.ascontiguousarray(K, dtype=f64).ravel(),
        np.ascontiguousarray(C, dtype=f64).ravel(),
        bool(closest),
        float(inside_tol),
        float(mu),
        float(exponent),
        bool(hunt_crossley),
        bool(patch),
        float(ratio),
        float(min_depth_ratio),
        np.ascontiguousarray(active, dtype=np.bool_),
        np.ascontiguousarray(anchor, dtype=f64),
        np.ascontiguousarray(offset, dtype=f64),
        np.ascontiguousarray(memory, dtype=f64),
        out,
    )
    return out


def fingertip_static_forces(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    boundary_nodes: NDArray[np.int64],
    indptr: NDArray[np.int64],
    indices: NDArray[np.int64],
    reach: float,
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    K: NDArray[np.float64],
    *,
    closest: bool,
    inside_tol: float,
    mu: float,
    exponent: float,
    patch: bool,
    ratio: float,
    min_depth_ratio: float,
    active: NDArray[np.bool_],
    anchor: NDArray[np.float64],
    offset: NDArray[np.float64],
    memory: NDArray[np.float64],
    pairs: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None,
) -> NDArray[np.float64]:
    """Contact forces at rest on the nodes [N], (N, 3), as
    :meth:`softgrasp.physics.fingertip.contact.FingertipContact.static_forces` (no relative velocity: no
    damping; a slipping pair's stick force capped at mu f_n): of the touching pairs, or of the
    given ``pairs`` (finger (k,), facet (k,)) followed to ``x`` whether they touch there or not
    (:meth:`~softgrasp.physics.fingertip.contact.FingertipContact.pinned_static_forces`). Arguments as
    :func:`fingertip_forces`."""
    f64, i64 = np.float64, np.int64
    geometry = _geometry_args(x, facets, boundary_nodes, indptr, indices, reach, centres, radii)
    out = np.zeros_like(geometry[0])
    finger, facet = (np.zeros(0, i64), np.zeros(0, i64)) if pairs is None else pairs
    _static_forces(
        *geometry,
        *_law_args(K, closest, inside_tol, mu, exponent, patch, ratio, min_depth_ratio),
        *_state_args(active, anchor, offset),
        np.ascontiguousarray(memory, dtype=f64),
        pairs is not None,
        np.ascontiguousarray(finger, dtype=i64),
        np.ascontiguousarray(facet, dtype=i64),
        out,
    )
    return out


def fingertip_update(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    boundary_nodes: NDArray[np.int64],
    indptr: NDArray[np.int64],
    indices: NDArray[np.int64],
    reach: float,
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    K: NDArray[np.float64],
    *,
    closest: bool,
    inside_tol: float,
    mu: float,
    exponent: float,
    patch: bool,
    ratio: float,
    min_depth_ratio: float,
    active: NDArray[np.bool_],
    anchor: NDArray[np.float64],
    offset: NDArray[np.float64],
    slip: NDArray[np.float64],
    memory: NDArray[np.float64],
) -> tuple[
    NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]
]:
    """The friction state after an accepted step (Algorithm 1, as
    :meth:`softgrasp.physics.fingertip.contact.FingertipContact.update`): new (active (n_f, F), anchor
    (n_f, F, 3), offset (n_f, F, 3) [m], slip (n_f, F, 3) [m], memory (n_f, 3) [m])."""
    f64 = np.float64
    new_active = np.zeros(active.shape, np.bool_)
    new_anchor = np.zeros(anchor.shape)
    new_offset = np.zeros(offset.shape)
    new_slip = np.zeros(slip.shape)
    new_memory = np.zeros(memory.shape)
    _fingertip_update(
        *_geometry_args(x, facets, boundary_nodes, indptr, indices, reach, centres, radii),
        *_law_args(K, closest, inside_tol, mu, exponent, patch, ratio, min_depth_ratio),
        *_state_args(active, anchor, offset),
        np.ascontiguousarray(slip, dtype=f64),
        np.ascontiguousarray(memory, dtype=f64),
        new_active,
        new_anchor,
        new_offset,
        new_slip,
        new_memory,
    )
    return new_active, new_anchor, new_offset, new_slip, new_memory
