"""Fingertip-facet contact detection (paper Sec. 3.1) and the pairs' geometry (Eq. 14).

A fingertip is a sphere of centre c and radius R. With the paper's test (``closest=False``) it
touches boundary facet j when the projection P_j of c on the facet's plane lies inside the triangle
and the distance d_j = (c - P_j)·n_j from the plane, measured along the facet's outward normal,
satisfies 0 < d_j < R; its penetration is delta_j = R - d_j (Eq. 14), its contact point P_j and its
contact normal n_j.

With ``closest=True`` (the patch rule) a pair is the sphere's true overlap with the triangle: its
contact point is the triangle's closest point Q_j to c (P_j when the projection falls inside, else
on an edge) and its penetration delta_j = R - |c - Q_j| > 0, so that no facet of the contact patch
is left out however small the facets are next to the fingertip, and a pair enters or leaves at
zero penetration. The facet must face the centre (d_j > 0); its *facing* cos(n_j, c - Q_j) =
d_j / |c - Q_j| goes to 0 as it turns edge-on to the centre, and the patch rule weights it by that
(its area seen from the centre). At a sharp convex edge the facets on both sides share the edge's
closest point.

The contact normal n_j is the facet's, or, given the mesh's corner normals (``corners``), the
smooth surface's at the contact point (:mod:`softgrasp.model.mesh.normals`): a coarse mesh of a
curved object then pushes along the object's own normal, not along a facet's tilted by up to half
the angle between neighbouring facets. The penetration and the contact point stay the facet's.

Broad phase: the surface nodes near each fingertip and the facets around them (a node-to-facet
index computed once per mesh, :class:`FacetIndex`), so the cost grows with the boundary nodes at a
few microseconds per thousand, not with F log F: with an index, :func:`detect` runs both phases in
one compiled pass (:mod:`softgrasp.physics.fingertip.detect`); without one, a k-d tree of facet
centroids, then the same compiled narrow phase (which :func:`pair_geometry` also follows given
pairs with).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from softgrasp.model.mesh.tetmesh import TetMesh

__all__ = ["ContactPairs", "FacetIndex", "detect", "pair_geometry"]

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
    point: contact point [m], (k, 3): the projection P_j of the centre on the facet (paper's test),
        or the triangle's closest point Q_j to the centre (patch rule; P_j when inside).
    normal: the outward unit contact normal n_j, (k, 3): the facet's, or the smooth surface's at
        the contact point (``corners``).
    distance: |c - point| [m], (k,) (d_j, the centre-to-plane distance, with the paper's test).
    depth: penetration delta_j = R - distance [m], (k,) (Eq. 14).
    area: current facet area [m^2], (k,).
    facing: cosine between the facet's normal and the direction from the contact point to the
        centre, d_j / distance, in (0, 1] (1 with the paper's test), (k,).
    """

    finger: NDArray[np.int64]
    facet: NDArray[np.int64]
    bary: NDArray[np.float64]
    point: NDArray[np.float64]
    normal: NDArray[np.float64]
    distance: NDArray[np.float64]
    depth: NDArray[np.float64]
    area: NDArray[np.float64]
    facing: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.finger.size)


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


def broad_phase_reach(index: FacetIndex) -> float:
    """Margin [m] beyond a fingertip's radius within which a surface node may carry a facet in
    contact: every point of a triangle lies within its longest edge of one of its nodes, and
    surface edges are taken to stretch at most :data:`MAX_STRETCH` times their rest length."""
    return (1.0 + 3.0 * INSIDE_TOL) * MAX_STRETCH * index.max_edge


def _candidates_tree(
    x: NDArray[np.float64], facets: NDArray[np.int64], centres, radii
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(finger, facet) candidates from a k-d tree of all facet centroids, O(F log F)."""
    tri = x[facets]
    cen = tri.mean(axis=1)
    # Every contact point (inside the triangle up to INSIDE_TOL) lies within that factor of the
    # largest centroid-vertex distance of the centroid.
    extent = (1.0 + 3.0 * INSIDE_TOL) * float(np.linalg.norm(tri - cen[:, None, :], axis=2).max())
    tree = cKDTree(cen)
    fi, fj = [], []
    for i, (c, R) in enumerate(zip(centres, radii, strict=True)):
        near = np.asarray(tree.query_ball_point(c, R + extent), dtype=np.int64)
        fj.append(near)
        fi.append(np.full(near.size, i, dtype=np.int64))
    return np.concatenate(fi), np.concatenate(fj)


def detect(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    *,
    closest: bool = False,
    index: FacetIndex | None = None,
    corners: NDArray[np.float64] | None = None,
) -> ContactPairs:
    """All touching (fingertip, facet) pairs (Sec. 3.1).

    Parameters
    ----------
    x: node positions [m], (N, 3).  facets: boundary facets (F, 3), outward ordering.
    centres: fingertip centres [m], (n_f, 3).  radii: fingertip radii [m], (n_f,).
    closest: False for the paper's test (the centre's projection inside the triangle); True for
        the sphere's overlap with each triangle, measured to its closest point (patch rule; see
        the module notes).
    index: the mesh's :class:`FacetIndex`: the broad phase then looks at the surface nodes near
        each fingertip (cost ~ boundary nodes, a few microseconds per thousand) instead of
        building a k-d tree of all facet centroids (cost ~ F log F).
    corners: the mesh's corner normals (:attr:`TetMesh.facet_corner_normals`): each pair's normal
        is then the smooth surface's at its contact point; None: the facet's.
    """
    if index is not None:
        return _detect_compiled(x, facets, centres, radii, closest, index, corners)
    fi, fj = _candidates_tree(x, facets, centres, radii)
    if fj.size == 0:
        return _empty()
    return _narrow_phase(x, facets, centres, radii, fi, fj, closest, keep_all=False, corners=corners)


def pair_geometry(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    finger: NDArray[np.int64],
    facet: NDArray[np.int64],
    *,
    closest: bool = False,
    corners: NDArray[np.float64] | None = None,
) -> ContactPairs:
    """The geometry of given (fingertip, facet) pairs at ``x``, whether they touch there or not
    (depths may be <= 0, projections outside the triangles): the pairs of an earlier
    :func:`detect`, followed through a small displacement (derivatives along a direction with
    the contact set fixed, as a Jacobian assumes). ``corners`` as in :func:`detect`."""
    if len(facet) == 0:
        return _empty()
    fi, fj = np.asarray(finger), np.asarray(facet)
    return _narrow_phase(x, facets, centres, radii, fi, fj, closest, keep_all=True, corners=corners)


def _narrow_phase(
    x, facets, centres, radii, fi, fj, closest: bool, keep_all: bool, corners=None
) -> ContactPairs:
    """Pair geometry of the candidate pairs (fi, fj) by the compiled narrow phase
    (:func:`softgrasp.physics.fingertip.detect.pair_values`); the touching ones only unless
    ``keep_all``. The float fields are read-only views of one (k, 13) array."""
    from softgrasp.physics.fingertip.detect import pair_values

    fi = np.asarray(fi, dtype=np.int64)
    fj = np.asarray(fj, dtype=np.int64)
    touch, val = pair_values(x, facets, corners, centres, radii, fi, fj, closest, INSIDE_TOL, keep_all)
    if not keep_all:
        fi, fj, val = fi[touch], fj[touch], val[touch]
    return _pairs_of(fi, fj, val)


def _pairs_of(fi: NDArray[np.int64], fj: NDArray[np.int64], val: NDArray[np.float64]) -> ContactPairs:
    """:class:`ContactPairs` of fingers ``fi``, facets ``fj`` and their values (k, 13) (columns
    as :func:`softgrasp.physics.fingertip.detect.detect_arrays`'), read-only views of ``val``."""
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
        facing=val[:, 12],
    )


def _detect_compiled(
    x: NDArray[np.float64],
    facets: NDArray[np.int64],
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    closest: bool,
    index: FacetIndex,
    corners: NDArray[np.float64] | None,
) -> ContactPairs:
    """:func:`detect` with the node-index broad phase, by the compiled kernel
    (:mod:`softgrasp.physics.fingertip.detect`): the same pairs in the same order, fields equal to
    round-off. The float fields are read-only views of one (k, 13) array."""
    from softgrasp.physics.fingertip.detect import detect_arrays

    fi, fj, val = detect_arrays(
        x,
        facets,
        corners,
        index.boundary_nodes,
        index.indptr,
        index.indices,
        broad_phase_reach(index),
        centres,
        radii,
        closest,
        INSIDE_TOL,
    )
    return _pairs_of(fi, fj, val)


def _empty() -> ContactPairs:
    z3 = np.zeros((0, 3))
    z = np.zeros(0)
    return ContactPairs(np.zeros(0, np.int64), np.zeros(0, np.int64), z3, z3, z3, z, z, z, z)
