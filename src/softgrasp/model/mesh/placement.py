"""Placing an object on the table in a statically stable pose.

A rigid object on a plane rests on a face of its convex hull, the one below its centre of mass.
A meshed sphere "standing" on its lowest node is an inverted pendulum and rolls away in any engine;
turned onto the hull facet under its centroid it stands on a stable tripod.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import ConvexHull

from softgrasp.model.mesh.tetmesh import TetMesh

__all__ = ["rest_on_table", "rest_on_table_transform", "rotation_between", "stable_facet_pose", "rigid_fit"]


def rotation_between(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """The proper rotation matrix (3, 3) turning unit vector ``a`` onto unit vector ``b`` by the
    shortest arc (Rodrigues' formula)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1 + 1e-12:  # opposite: turn by pi about any axis normal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def rest_on_table(mesh: TetMesh) -> TetMesh:
    """A copy of ``mesh`` rotated onto the convex-hull face below its centroid, standing on z = 0
    with its centroid above the origin (:func:`rest_on_table_transform`)."""
    return rest_on_table_transform(mesh)[0]


def rest_on_table_transform(mesh: TetMesh) -> tuple[TetMesh, NDArray[np.float64]]:
    """A copy of ``mesh`` rotated onto the convex-hull face below its centroid, standing on z = 0
    with its centroid above the origin, and the rigid transform (4, 4) that took it there
    (``p_new = T p``, homogeneous, metres).

    The face is the one the downward vertical through the centroid crosses; after the rotation it
    lies flat on the table, so the centroid projects inside the support polygon (a stable pose).
    An object already resting on a flat face (a box on its bottom) is only translated.
    """
    x = np.asarray(mesh.points)
    c = mesh.centroid
    hull = ConvexHull(x)
    normals = hull.equations[:, :3]
    offsets = hull.equations[:, 3]
    down = np.array([0.0, 0.0, -1.0])
    # Ray c + s down leaves the hull through the facet with the smallest positive exit parameter.
    denom = normals @ down
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -(normals @ c + offsets) / denom
    s[denom <= 1e-12] = np.inf
    k = int(np.argmin(s))
    n = normals[k]
    if np.allclose(n, down, atol=1e-9):
        R = np.eye(3)
    else:
        R = rotation_between(n, down)
    xr = (x - c) @ R.T
    lift = xr[:, 2].min()
    xr[:, 2] -= lift
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -(R @ c) - np.array([0.0, 0.0, lift])
    return TetMesh(xr, mesh.tets, name=mesh.name), T


def rigid_fit(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rigid transform (4, 4) taking the points ``a`` (N, 3) onto the points ``b`` (N, 3) in the
    least-squares sense (Kabsch's method; a proper rotation): exact where ``b`` is ``a`` turned
    and moved."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cb - R @ ca
    return T


def stable_facet_pose(x: NDArray[np.float64], com: NDArray[np.float64]) -> NDArray[np.float64]:
    """``x`` (N, 3) turned rigidly about the centre of mass ``com`` so that it stands on the facet
    of its convex hull whose plane is nearest ``com``: the projection of the centre of mass falls
    inside that facet (were it outside, a neighbouring facet's plane would be nearer), so the
    object cannot tip off it. (:func:`rest_on_table` takes the facet under the centroid, which
    suits a mesh already standing; this is the rule for one that balances on a node.)"""
    eq = ConvexHull(x).equations  # n . p + d <= 0 inside, n outward and unit
    n = eq[int(np.argmin(-(eq[:, :3] @ com + eq[:, 3]))), :3]
    R = rotation_between(n, np.array([0.0, 0.0, -1.0]))
    return (x - com) @ R.T + com
