"""The frozen tetrahedral mesh every softgrasp model is built on.

Conventions: points ``(N, 3) float64`` in metres; tets ``(M, 4) int64`` node indices with positive
orientation (``det[x1-x0, x2-x0, x3-x0] > 0``); boundary facets ``(F, 3) int64`` ordered so that the
right-hand normal points out of the body.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import MeshError

__all__ = ["TetMesh", "signed_volumes", "TET_FACES", "TET_EDGES"]

#: Local node triples of the four faces of a positively oriented tet, each with outward normal.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)
#: Local node pairs of the six edges of a tet.
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)


def signed_volumes(points: NDArray[np.float64], tets: NDArray[np.int64]) -> NDArray[np.float64]:
    """Signed volumes [m^3] of tets, shape ``(M,)``; positive for positive orientation."""
    p = points[tets]
    a = p[:, 1] - p[:, 0]
    b = p[:, 2] - p[:, 0]
    c = p[:, 3] - p[:, 0]
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def _row_keys(rows: NDArray[np.int64], n: int) -> NDArray[np.int64] | None:
    """One int64 key per row of node indices in ``0 .. n - 1``, ordered as the rows are
    lexicographically (``sum rows[:, k] n^(K-1-k)``), or None when ``n^K`` overflows int64.
    ``np.unique`` on these keys gives the rows' unique order, inverse and counts as
    ``np.unique(rows, axis=0)`` does, about ten times faster (a sort of integers instead of one
    of row records)."""
    rows = np.asarray(rows).astype(np.int64, copy=False)  # unsigned rows would turn the keys float
    k = rows.shape[1]
    if float(max(n, 1)) ** k >= 2.0**63:
        return None
    key = rows[:, 0].copy()
    for j in range(1, k):
        key = key * n + rows[:, j]
    return key


def _unique_rows(rows: NDArray[np.int64], n: int, inverse: bool = False, counts: bool = False):
    """``np.unique(rows, axis=0, return_inverse=inverse, return_counts=counts)`` for rows of node
    indices in ``0 .. n - 1``, by :func:`_row_keys` where they fit int64."""
    key = _row_keys(rows, n)
    if key is None:
        return np.unique(rows, axis=0, return_inverse=inverse, return_counts=counts)
    out = np.unique(key, return_index=True, return_inverse=inverse, return_counts=counts)
    uniq = rows[out[1]]
    return (uniq, *out[2:]) if (inverse or counts) else uniq


def _frozen(a: NDArray) -> NDArray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A validated, immutable tetrahedral mesh of a solid object.

    Parameters
    ----------
    points:
        Node coordinates [m], shape ``(N, 3)``, finite.
    tets:
        Node indices of each tetrahedron, shape ``(M, 4)``.
    reorient:
        If true, tets with negative volume are re-oriented (two nodes swapped) instead of raising.
    name:
        A label carried into output files.

    Raises
    ------
    MeshError
        Empty mesh, wrong shapes, NaN/inf coordinates, out-of-range or repeated indices,
        unreferenced nodes, zero-volume tets, inverted tets (unless ``reorient``), a
        non-manifold boundary, or tets falling apart into parts joined by no face.
    """

    points: NDArray[np.float64]
    tets: NDArray[np.int64]
    reorient: bool = field(default=False, repr=False)
    name: str = "mesh"

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=np.float64)
        tets = np.asarray(self.tets)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MeshError(f"points must have shape (N, 3), got {pts.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise MeshError(f"tets must have shape (M, 4), got {tets.shape}")
        if pts.shape[0] == 0 or tets.shape[0] == 0:
            raise MeshError(
                f"empty mesh: {pts.shape[0]} points and {tets.shape[0]} tetrahedra; "
                "a solid needs at least one tetrahedron"
            )
        if not np.issubdtype(tets.dtype, np.integer):
            if not np.all(np.equal(np.mod(tets, 1), 0)):
                raise MeshError("tets must hold integer node indices")
        tets = tets.astype(np.int64)
        bad = ~np.isfinite(pts)
        if bad.any():
            node = int(np.argwhere(bad.any(axis=1))[0, 0])
            raise MeshError(f"node {node} has a non-finite coordinate {pts[node].tolist()}")
        n = pts.shape[0]
        if tets.min() < 0 or tets.max() >= n:
            t = int(np.argwhere((tets < 0).any(axis=1) | (tets >= n).any(axis=1))[0, 0])
            raise MeshError(f"tet {t} refers to node indices {tets[t].tolist()} outside 0..{n - 1}")
        srt = np.sort(tets, axis=1)
        rep = (np.diff(srt, axis=1) == 0).any(axis=1)
        if rep.any():
            t = int(np.argwhere(rep)[0, 0])
            raise MeshError(f"tet {t} repeats a node: {tets[t].tolist()}")
        used = np.zeros(n, dtype=bool)
        used[tets.ravel()] = True
        if not used.all():
            unused = np.flatnonzero(~used)
            raise MeshError(
                f"{unused.size} node(s) are not used by any tetrahedron (first: node {unused[0]}); "
                "remove unreferenced nodes before building a body"
            )
        vol = signed_volumes(pts, tets)
        scale = float(np.ptp(pts, axis=0).max()) or 1.0
        tiny = 1e-12 * scale**3
        degenerate = np.abs(vol) <= tiny
        if degenerate.any():
            t = int(np.argwhere(degenerate)[0, 0])
            raise MeshError(
                f"{int(degenerate.sum())} tetrahedra have zero volume (first: tet {t}, nodes "
                f"{tets[t].tolist()}); fix or remesh the object"
            )
        inverted = vol < 0
        if inverted.any():
            if not self.reorient:
                t = int(np.argwhere(inverted)[0, 0])
                raise MeshError(
                    f"{int(inverted.sum())} of {tets.shape[0]} tetrahedra are inverted (first: tet {t}); "
                    "pass reorient=True (CLI: --reorient) to flip them"
                )
            tets = tets.copy()
            tets[inverted, 1], tets[inverted, 2] = tets[inverted, 2], tets[inverted, 1].copy()
        object.__setattr__(self, "points", _frozen(pts))
        object.__setattr__(self, "tets", _frozen(tets))
        self._check_manifold()

    # ------------------------------------------------------------------ topology
    @cached_property
    def volumes(self) -> NDArray[np.float64]:
        """Tet volumes [m^3], shape ``(M,)``, all positive."""
        return _frozen(signed_volumes(self.points, self.tets))

    @property
    def n_nodes(self) -> int:
        """Number of nodes N."""
        return int(self.points.shape[0])

    @property
    def n_tets(self) -> int:
        """Number of tetrahedra M."""
        return int(self.tets.shape[0])

    @cached_property
    def volume(self) -> float:
        """Total volume [m^3]."""
        return float(self.volumes.sum())

    @cached_property
    def _faces(self) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """All tet faces (outward per tet), their sorted-key inverse index and key counts."""
        faces = self.tets[:, TET_FACES].reshape(-1, 3)
        keys = np.sort(faces, axis=1)
        _, inv, counts = _unique_rows(keys, self.n_nodes, inverse=True, counts=True)
        return faces, inv.ravel(), counts

    @cached_property
    def facets(self) -> NDArray[np.int64]:
        """Boundary facets, shape ``(F, 3)``, node order giving outward right-hand normals."""
        faces, inv, counts = self._faces
        return _frozen(faces[counts[inv] == 1])

    @cached_property
    def facet_tets(self) -> NDArray[np.int64]:
        """Index of the tet owning each boundary facet, shape ``(F,)``."""
        _, inv, counts = self._faces
        return _frozen(np.flatnonzero(counts[inv] == 1) // 4)

    @cached_property
    def node_facets(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Boundary facets around each node, CSR ``(indptr (N+1,), indices)``: the facets of node
        i are ``indices[indptr[i]:indptr[i + 1]]``."""
        flat = self.facets.ravel()
        order = np.argsort(flat, kind="stable")
        counts = np.bincount(flat, minlength=self.n_nodes)
        indptr = np.concatenate([[0], np.cumsum(counts)])
        return _frozen(indptr.astype(np.int64)), _frozen((order // 3).astype(np.int64))

    @cached_property
    def max_facet_edge(self) -> float:
        """Longest edge of a boundary facet at rest [m]."""
        tri = self.points[self.facets]
        return float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max())

    @cached_property
    def boundary_nodes(self) -> NDArray[np.int64]:
        """Sorted indices of the nodes on the boundary surface, shape ``(B,)``."""
        return _frozen(np.unique(self.facets))

    @cached_property
    def _edges(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        pairs = np.sort(self.tets[:, TET_EDGES].reshape(-1, 2), axis=1)
        edges, inv = _unique_rows(pairs, self.n_nodes, inverse=True)
        return edges, inv.ravel()

    @property
    def edges(self) -> NDArray[np.int64]:
        """Unique edges (i < j), shape ``(E, 2)``."""
        return _frozen(self._edges[0])

    @property
    def tet_edges(self) -> NDArray[np.int64]:
        """For each tet, the indices into :attr:`edges` of its six edges, shape ``(M, 6)``."""
        return _frozen(self._edges[1].reshape(-1, 6))

    @cached_property
    def edge_lengths(self) -> NDArray[np.float64]:
        """Rest lengths [m] of :attr:`edges`, shape ``(E,)``."""
        d = self.points[self.edges[:, 1]] - self.points[self.edges[:, 0]]
        return _frozen(np.linalg.norm(d, axis=1))

    @cached_property
    def edge_volumes(self) -> NDArray[np.float64]:
        """Sum of the volumes [m^3] of the tets sharing each edge, shape ``(E,)``."""
        acc = np.zeros(len(self.edges))
        np.add.at(acc, self.tet_edges.ravel(), np.repeat(self.volumes, 6))
        return _frozen(acc)

    @cached_property
    def facet_normals(self) -> NDArray[np.float64]:
        """Outward unit normals of the boundary facets, shape ``(F, 3)``."""
        p = self.points[self.facets]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        return _frozen(n / np.linalg.norm(n, axis=1, keepdims=True))

    @cached_property
    def facet_corner_normals(self) -> NDArray[np.float64]:
        """The smooth surface's unit normal at each corner of each boundary facet, in the facet's
        rest frame, shape ``(F, 3, 3)`` (:func:`softgrasp.model.mesh.normals.corner_normals`)."""
        from softgrasp.model.mesh.normals import corner_normals

        return corner_normals(self.points, self.facets, self.facet_normals, self.node_facets)

    @cached_property
    def facet_areas(self) -> NDArray[np.float64]:
        """Areas [m^2] of the boundary facets, shape ``(F,)``."""
        p = self.points[self.facets]
        return _frozen(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1))

    @cached_property
    def centroid(self) -> NDArray[np.float64]:
        """Volume centroid [m], shape ``(3,)``."""
        c = self.points[self.tets].mean(axis=1)
        return _frozen((c * self.volumes[:, None]).sum(axis=0) / self.volume)

    @cached_property
    def bounds(self) -> NDArray[np.float64]:
        """Axis-aligned bounding box [m], shape ``(2, 3)``: minimum and maximum corners."""
        return _frozen(np.stack([self.points.min(axis=0), self.points.max(axis=0)]))

    @cached_property
    def surface_area(self) -> float:
        """Area [m^2] of the boundary surface."""
        return float(self.facet_areas.sum())

    # ------------------------------------------------------------------ checks
    def _check_manifold(self) -> None:
        faces, inv, counts = self._faces
        if (counts > 2).any():
            k = int(np.argmax(counts))
            f = faces[np.flatnonzero(inv == k)[0]]
            raise MeshError(
                f"non-manifold mesh: face {sorted(f.tolist())} is shared by {int(counts[k])} "
                "tetrahedra (at most 2 allowed); the mesh has overlapping or duplicated elements"
            )
        bf = self.facets
        he = np.sort(np.concatenate([bf[:, [0, 1]], bf[:, [1, 2]], bf[:, [2, 0]]]), axis=1)
        uniq, ecount = _unique_rows(he, self.n_nodes, counts=True)
        bad = ecount != 2
        if bad.any():
            e = uniq[np.argmax(bad)]
            raise MeshError(
                f"non-manifold boundary: boundary edge {e.tolist()} is shared by "
                f"{int(ecount[np.argmax(bad)])} boundary facets (must be 2); parts of the object "
                "touch along an edge or the surface is not closed"
            )
        # Directed half-edges must each appear once for a consistently oriented closed surface.
        directed = np.concatenate([bf[:, [0, 1]], bf[:, [1, 2]], bf[:, [2, 0]]])
        _, dcount = _unique_rows(directed, self.n_nodes, counts=True)
        if (dcount != 1).any():
            raise MeshError("boundary surface is not consistently oriented (a face is folded over)")
        self._check_connected()

    def _check_connected(self) -> None:
        """Refuse a mesh whose tets fall apart into parts joined by no face: separate bodies, or
        parts touching only at a vertex or along an edge (no stiffness holds them together, and
        the body's equations become singular)."""
        if self.n_tets == 1:
            return
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        _, inv, counts = self._faces
        inner = np.flatnonzero(counts[inv] == 2)  # faces of two tets, pairs adjacent by key
        pairs = inner[np.argsort(inv[inner], kind="stable")].reshape(-1, 2) // 4
        m = self.n_tets
        graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
        n_parts, label = connected_components(graph, directed=False)
        if n_parts > 1:
            sizes = np.bincount(label)
            shown = ", ".join(str(int(k)) for k in np.sort(sizes)[::-1][:5])
            shown += ", ..." if n_parts > 5 else ""
            raise MeshError(
                f"the mesh falls apart into {n_parts} parts joined by no shared face ({shown} tetrahedra): "
                "separate bodies, or parts touching only at a vertex or along an edge; give one "
                "connected object"
            )

    # ------------------------------------------------------------------ transforms
    def translated(self, offset: NDArray[np.float64] | list[float]) -> TetMesh:
        """A copy moved by ``offset`` [m], shape ``(3,)``."""
        return TetMesh(self.points + np.asarray(offset, dtype=np.float64), self.tets, name=self.name)

    def moved(self, points: NDArray[np.float64]) -> TetMesh:
        """A copy with its nodes at ``points`` [m], shape ``(N, 3)``: a rigid motion of this mesh
        (its rest shape placed elsewhere, as an object turned onto another face), every edge
        keeping its length to 1e-9 of the mesh's size."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape != self.points.shape:
            raise MeshError(f"a moved mesh needs {self.points.shape} points, got {pts.shape}")
        e = self.edges
        change = np.abs(np.linalg.norm(pts[e[:, 1]] - pts[e[:, 0]], axis=1) - self.edge_lengths)
        size = float(np.ptp(self.points, axis=0).max())
        if not float(change.max()) <= 1e-9 * size:
            raise MeshError(
                f"the points are not a rigid motion of mesh '{self.name}': an edge changes its length "
                f"by {float(change.max()):.3g} m"
            )
        return TetMesh(pts, self.tets, name=self.name)

    def scaled(self, factor: float) -> TetMesh:
        """A copy scaled about the origin by ``factor`` (> 0)."""
        if not factor > 0:
            raise MeshError(f"scale factor must be > 0, got {factor}")
        return TetMesh(self.points * factor, self.tets, name=self.name)

    def reordered(self) -> TetMesh:
        """The same solid numbered for memory locality: nodes in reverse Cuthill-McKee order of
        the edge graph (the nodes of a tet get nearby numbers), tets sorted by their lowest node,
        each tet's own node order (its orientation) kept.

        The force and Jacobian kernels gather and scatter per edge and per tet, and the sparse
        solvers sweep rows of the Jacobian; with gmsh's numbering (the nodes of one edge ~600
        apart on average in a 2 196-node sphere, as far as random numbers) every element touches
        far-apart memory; in this order the body's Jacobian assembles about 2.5 times faster."""
        from scipy.sparse import csr_matrix
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        n = self.n_nodes
        e = self.edges
        graph = csr_matrix(
            (
                np.ones(2 * len(e), dtype=np.int8),
                (np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])),
            ),
            shape=(n, n),
        )
        perm = np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True), dtype=np.int64)
        new = np.empty(n, dtype=np.int64)
        new[perm] = np.arange(n, dtype=np.int64)
        tets = new[self.tets]
        tets = tets[np.lexsort((tets.max(axis=1), tets.min(axis=1)))]
        return TetMesh(self.points[perm], tets, name=self.name)

    def on_table(self) -> TetMesh:
        """A copy translated so that its lowest point lies on the table plane z = 0 and its
        volume centroid is above the origin."""
        c = self.centroid
        return self.translated([-c[0], -c[1], -self.points[:, 2].min()])

    def summary(self) -> str:
        """One line for people: node, tet and facet counts and size in mm."""
        ext = np.ptp(self.points, axis=0) * 1e3
        return (
            f"{self.name}: {self.n_nodes} nodes, {self.n_tets} tets, {len(self.facets)} facets, "
            f"{ext[0]:.1f} x {ext[1]:.1f} x {ext[2]:.1f} mm"
        )
