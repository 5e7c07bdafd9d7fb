"""Compiled fingertip-facet contact detection (paper Sec. 3.1; the penetration of Eq. 14).

:func:`detect_arrays` runs the broad phase (surface nodes near each fingertip, then the facets
around them, through the mesh's :class:`~softgrasp.physics.fingertip.geometry.FacetIndex`) and the
narrow phase (contact point, barycentric coordinates, contact normal, distance, penetration
``delta = R - d``, area, facing factor; the paper's projection test or the sphere's overlap with the
triangle, :mod:`softgrasp.physics.fingertip.geometry` describes both) in one pass. The contact
normal is the facet's, or given the mesh's corner normals
(:attr:`~softgrasp.model.mesh.tetmesh.TetMesh.facet_corner_normals`, (F, 3, 3); an empty (0, 3, 3)
array for the facet's) the smooth surface's at the contact point (:func:`_smooth_normal`). Pairs come out
by fingertip, then by facet index. :func:`pair_values` runs the narrow phase on given pairs (the
candidates of another broad phase, or pairs followed to new positions, touching or not). A pair's values are one row of 13: bary 0-2, point 3-5, normal 6-8, distance 9,
depth 10, area 11, facing 12.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from softgrasp import jitcache

__all__ = ["corner_args", "detect_arrays", "pair_values"]

_jit = jitcache.jit(fastmath=False, error_model="numpy")


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
def _smooth_normal(tri, nx, ny, nz, corners, near, row):  # pragma: no cover - compiled
    """The smooth surface's unit normal at the contact point written to ``row[6:9]``: the facet's
    corner normals ``corners`` (3, 3), given in its rest frame, turned into its current frame
    (e1 along ``tri[1] - tri[0]``, e2 = n x e1, its unit normal n) and interpolated by the
    contact point's barycentric coordinates ``near`` (those outside the triangle clipped to it:
    a pinned pair followed beyond its facet), then normalised (Phong's normal;
    :mod:`softgrasp.model.mesh.normals`)."""
    ex = tri[1, 0] - tri[0, 0]
    ey = tri[1, 1] - tri[0, 1]
    ez = tri[1, 2] - tri[0, 2]
    le = math.sqrt(ex * ex + ey * ey + ez * ez)
    ex /= le
    ey /= le
    ez /= le
    fx = ny * ez - nz * ey
    fy = nz * ex - nx * ez
    fz = nx * ey - ny * ex
    b0 = max(near[0], 0.0)
    b1 = max(near[1], 0.0)
    b2 = max(near[2], 0.0)
    bs = b0 + b1 + b2
    s1 = (b0 * corners[0, 0] + b1 * corners[1, 0] + b2 * corners[2, 0]) / bs
    s2 = (b0 * corners[0, 1] + b1 * corners[1, 1] + b2 * corners[2, 1]) / bs
    s3 = (b0 * corners[0, 2] + b1 * corners[1, 2] + b2 * corners[2, 2]) / bs
    sx = s1 * ex + s2 * fx + s3 * nx
    sy = s1 * ey + s2 * fy + s3 * ny
    sz = s1 * ez + s2 * fz + s3 * nz
    ls = math.sqrt(sx * sx + sy * sy + sz * sz)
    row[6] = sx / ls
    row[7] = sy / ls
    row[8] = sz / ls


@_jit
def _pair_values(tri, cx, cy, cz, R, closest, inside_tol, keep, near, row, corners, j):  # pragma: no cover
    """Narrow phase of the sphere (centre c, radius R) against triangle ``tri`` (3, 3), facet
    ``j`` of the mesh: writes the pair's values to ``row`` (13: bary 0-2, point 3-5, normal 6-8,
    distance 9, depth 10, area 11, facing 12; ``near`` (3) is scratch) and returns whether it
    touches (as :func:`softgrasp.physics.fingertip.geometry.detect` with ``closest`` decides). With
    ``keep`` the values are written whether it touches or not, and it returns True (a pinned pair
    followed through a small displacement, as
    :func:`softgrasp.physics.fingertip.geometry.pair_geometry`: depth may be <= 0). The normal is the
    facet's when ``corners`` is empty, else the smooth surface's (:func:`_smooth_normal` of
    ``corners[j]``); the penetration is the facet's in both."""
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
    if corners.shape[0] > 0:
        _smooth_normal(tri, nx, ny, nz, corners[j], near, row)
    else:
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
    x, facets, corners, boundary, indptr, indices, reach, centres, radii, closest, inside_tol
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
        q = np.int64(0)  # not the literal 0: the narrow phase compiles for int64 only
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
            if not _pair_values(
                tri, cx, cy, cz, R, closest, inside_tol, np.bool_(False), near, real[k], corners, j
            ):
                continue
            finger[k] = f
            facet[k] = j
            k += 1
    return finger[:k].copy(), facet[:k].copy(), real[:k].copy()


def _geometry_args(x, facets, corners, boundary_nodes, indptr, indices, reach, centres, radii) -> tuple:
    """The mesh, broad-phase index and fingertip arguments every compiled contact kernel takes
    first, as the contiguous float64 / int64 arrays (and floats) the kernels are compiled for;
    ``corners`` None for the facets' own normals."""
    f64, i64 = np.float64, np.int64
    return (
        np.ascontiguousarray(x, dtype=f64),
        np.ascontiguousarray(facets, dtype=i64),
        corner_args(corners),
        np.ascontiguousarray(boundary_nodes, dtype=i64),
        np.ascontiguousarray(indptr, dtype=i64),
        np.ascontiguousarray(indices, dtype=i64),
        float(reach),
        np.ascontiguousarray(centres, dtype=f64).reshape(-1, 3),
        np.ascontiguousarray(radii, dtype=f64).ravel(),
    )


def corner_args(corners: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """A mesh's corner normals (F, 3, 3) as the kernels take them (read-only, as the mesh's are:
    one compiled signature); None (the facets' own normals) as an empty (0, 3, 3) array."""
    a = np.zeros((0, 3, 3)) if corners is None else np.ascontiguousarray(corners, dtype=np.float64)
    view = a.reshape(-1, 3, 3).view()
    view.flags.writeable = False
    return view


def detect_arrays(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    corners: NDArray[np.float64] | None,
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
    R + reach from a centre has no facet in contact); ``corners`` the mesh's corner normals for
    the smooth surface's normal, None for the facets'."""
    return _detect(
        *_geometry_args(x, facets, corners, boundary_nodes, indptr, indices, reach, centres, radii),
        bool(closest),
        float(inside_tol),
    )


@_jit
def _candidate_values(
    x, facets, corners, centres, radii, finger, facet, closest, inside_tol, keep
):  # pragma: no cover - compiled
    """The narrow phase (:func:`_pair_values`) of the given (finger, facet) pairs at ``x``:
    (whether each touches (k,), their values (k, 13)); with ``keep`` every pair's values, whether
    it touches or not (all True)."""
    k = finger.shape[0]
    val = np.zeros((k, 13))
    touch = np.zeros(k, np.bool_)
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
        R = radii[f]
        touch[p] = _pair_values(tri, cx, cy, cz, R, closest, inside_tol, keep, near, val[p], corners, j)
    return touch, val


@_jit
def _pinned_values(x, facets, corners, centres, radii, finger, facet, closest):  # pragma: no cover - compiled
    """The values (k, 13) of the given (finger, facet) pairs at ``x`` (:func:`_pair_values` with
    ``keep``), whether they touch there or not."""
    pinned = np.bool_(True)
    return _candidate_values(x, facets, corners, centres, radii, finger, facet, closest, 0.0, pinned)[1]


def pair_values(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    corners: NDArray[np.float64] | None,
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    finger: NDArray[np.int64],
    facet: NDArray[np.int64],
    closest: bool,
    inside_tol: float,
    keep: bool,
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """The narrow phase of given (fingertip, facet) pairs (finger (k,), facet (k,)): (whether each
    touches (k,), its values (k, 13), columns as :func:`detect_arrays`'); with ``keep`` the values
    of every pair, touching or not (a pinned pair followed through a displacement: depth may be
    <= 0, the contact point outside the triangle with the paper's test); ``corners`` as
    :func:`detect_arrays`'."""
    f64, i64 = np.float64, np.int64
    tri = np.require(facets, i64, "C").view()
    tri.flags.writeable = False  # as a mesh's facets are, and x writable as a state's positions
    return _candidate_values(  # are: the kernel compiled for the plan serves this call too
        np.require(x, f64, ("C", "W")),
        tri,
        corner_args(corners),
        np.ascontiguousarray(centres, dtype=f64).reshape(-1, 3),
        np.ascontiguousarray(radii, dtype=f64).ravel(),
        np.ascontiguousarray(finger, dtype=i64),
        np.ascontiguousarray(facet, dtype=i64),
        bool(closest),
        float(inside_tol),
        bool(keep),
    )
