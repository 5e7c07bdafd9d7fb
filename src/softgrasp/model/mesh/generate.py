"""Mesh generators: structured box; sphere, cylinder and (locally refined) cuboid through the
gmsh mesher.

The box uses a body-centred cubic (BCC) tetrahedralisation: corner nodes on a regular grid, one
node at the centre of every cell, and one at the centre of every boundary face. In the bulk it is a
Bravais lattice (every node is a centre of symmetry), so an edge-spring network on it deforms
affinely under homogeneous strain and can be made exactly isotropic (see :mod:`softgrasp.model.network`),
unlike the common 5- or 6-tets-per-cube splits whose springs are strongly anisotropic.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from softgrasp.errors import MeshError
from softgrasp.model.mesh._gmsh import (
    MAX_TETS,
    TETS_PER_H3,
    check_mesh_size,
    default_mesh_size,
    gmsh_session,
    tet_mesh_from_model,
)
from softgrasp.model.mesh.tetmesh import TetMesh, signed_volumes

__all__ = ["GROWTH", "LocalRefinement", "box", "cuboid", "cylinder", "sphere"]

#: How fast a locally refined mesh's elements grow away from the refined zone: the element size
#: rises by this many metres per metre of distance, up to the mesh size. The rubber sphere (nodal
#: volume term) refined to 2 and 1 mm within 8 mm of its top and pressed 3 mm there gives 1.01
#: times the two contacts' Hertz force on both (722 and 1 795 nodes). Meshed with gmsh's Netgen
#: optimiser instead, grading 0.5 gave 1.035 and 1.014 (1 057 and 2 127 nodes), 0.25 gave 1.024
#: and 0.955 (1 330 and 2 967 nodes): the slower grading costs nodes and gains no accuracy.
GROWTH = 0.5


@dataclass(frozen=True)
class LocalRefinement:
    """Finer elements near given points of a gmsh-meshed shape: ``size_m`` [m] within
    ``radius_m`` [m] of each of ``points_m`` [m], growing by :data:`GROWTH` per metre beyond, up
    to the mesh size."""

    points_m: tuple[tuple[float, float, float], ...]
    size_m: float
    radius_m: float

    def __post_init__(self) -> None:
        pts = np.asarray(self.points_m, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or not np.isfinite(pts).all():
            raise MeshError(
                f"local refinement needs one or more finite (x, y, z) points, got {self.points_m!r}"
            )
        _positive("the local element size", self.size_m)
        _positive("the local refinement radius", self.radius_m)

    def tets_estimate(self, mesh_size: float) -> float:
        """An upper bound on the tets the refined zones add: whole balls about the points, at
        :data:`~softgrasp.model.mesh._gmsh.TETS_PER_H3` tets per element size cubed."""
        u = np.linspace(0.0, max(mesh_size - self.size_m, 0.0) / GROWTH, 400)
        grown = np.trapezoid(4.0 * np.pi * (self.radius_m + u) ** 2 / (self.size_m + GROWTH * u) ** 3, u)
        inner = 4.0 / 3.0 * np.pi * (self.radius_m / self.size_m) ** 3
        return TETS_PER_H3 * len(self.points_m) * float(inner + grown)

    def size_expression(self, mesh_size: float, offset: Sequence[float] = (0.0, 0.0, 0.0)) -> str:
        """gmsh's MathEval expression of the element size [m] at (x, y, z), the points moved by
        ``-offset`` [m]."""

        def num(v: float) -> str:  # fixed point in parentheses: gmsh's parser takes no "- -1e-05"
            return f"({v:.12f})"

        terms = [
            f"{num(self.size_m)} + {num(GROWTH)} * Max(0, Sqrt((x - {num(x)})^2 + (y - {num(y)})^2 "
            f"+ (z - {num(z)})^2) - {num(self.radius_m)})"
            for x, y, z in np.asarray(self.points_m, dtype=float) - np.asarray(offset, dtype=float)
        ]
        expr = terms[0]
        for t in terms[1:]:
            expr = f"Min({expr}, {t})"
        return f"Min({num(mesh_size)}, {expr})"


def _refine(
    gmsh, refinement: LocalRefinement | None, mesh_size: float, offset: Sequence[float] = (0.0, 0.0, 0.0)
) -> None:
    """Set the session's size field for ``refinement`` (nothing without one), its points given in
    coordinates ``offset`` [m] from gmsh's; the elements are then no smaller than half the local
    size."""
    if refinement is None:
        return
    if refinement.size_m >= mesh_size:
        raise MeshError(
            f"the local element size ({refinement.size_m * 1e3:.3g} mm) must be smaller than the mesh size "
            f"({mesh_size * 1e3:.3g} mm)"
        )
    estimate = refinement.tets_estimate(mesh_size)
    if estimate > MAX_TETS:
        raise MeshError(
            f"a local element size of {refinement.size_m * 1e3:.3g} mm within "
            f"{refinement.radius_m * 1e3:.3g} mm needs about {estimate:.3g} tets (at most {MAX_TETS}); "
            "give a larger local size"
        )
    field = gmsh.model.mesh.field
    tag = field.add("MathEval")
    field.setString(tag, "F", refinement.size_expression(mesh_size, offset))
    field.setAsBackgroundMesh(tag)
    gmsh.option.setNumber("Mesh.MeshSizeMin", 0.5 * refinement.size_m)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)


def _check_positive(name: str, values: Sequence[float]) -> None:
    for v in values:
        if not (np.isfinite(v) and v > 0):
            raise MeshError(f"{name} must be positive and finite, got {list(values)}")


def _at(
    grid: np.ndarray, axis: int, layer: int, first: tuple[int, np.ndarray], second: tuple[int, np.ndarray]
) -> np.ndarray:
    """Entries of a 3D index grid at ``layer`` along ``axis`` and the given coordinates along the
    two other axes."""
    idx: list[int | np.ndarray] = [0, 0, 0]
    idx[axis] = layer
    idx[first[0]] = first[1]
    idx[second[0]] = second[1]
    return grid[idx[0], idx[1], idx[2]]


def box(
    size: float | Sequence[float] = 0.05,
    divisions: int | Sequence[int] = 6,
    *,
    on_table: bool = True,
    name: str = "box",
) -> TetMesh:
    """A structured BCC tet mesh of a rectangular box.

    Parameters
    ----------
    size:
        Edge lengths [m] along x, y, z (one number for a cube).
    divisions:
        Cells along x, y, z (one number for the same everywhere), each >= 1.
    on_table:
        If true the box stands on z = 0 centred on the z axis; otherwise it spans [0, size].

    Returns
    -------
    TetMesh
        ``(n+1)^3 + n^3 + 2(n_x n_y + n_y n_z + n_z n_x)`` nodes and 12 tets per cell (24 faces...).
    """
    size_v = [float(size)] * 3 if np.isscalar(size) else [float(s) for s in size]  # type: ignore[arg-type]
    div_v = [int(divisions)] * 3 if np.isscalar(divisions) else [int(d) for d in divisions]  # type: ignore[arg-type]
    if len(size_v) != 3 or len(div_v) != 3:
        raise MeshError("box size and divisions take one value or three (x, y, z)")
    _check_positive("box size", size_v)
    if min(div_v) < 1:
        raise MeshError(f"box divisions must be >= 1, got {div_v}")
    nx, ny, nz = div_v
    h = np.array(size_v) / np.array(div_v)

    # Corner grid nodes.
    gi, gj, gk = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij")
    corners = np.stack([gi, gj, gk], axis=-1).reshape(-1, 3).astype(float) * h
    cid = np.arange(corners.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    # Cell-centre nodes.
    ci, cj, ck = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    centres = (np.stack([ci, cj, ck], axis=-1).reshape(-1, 3).astype(float) + 0.5) * h
    eid = corners.shape[0] + np.arange(centres.shape[0]).reshape(nx, ny, nz)
    points = [corners, centres]
    n_pts = corners.shape[0] + centres.shape[0]

    tets: list[np.ndarray] = []
    n = (nx, ny, nz)
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        for p in range(n[axis] + 1):
            # Faces normal to `axis` at layer p, indexed by cell coords (a, b) along u, v.
            A, B = np.meshgrid(np.arange(n[u]), np.arange(n[v]), indexing="ij")
            A = A.ravel()
            B = B.ravel()

            ring = [
                _at(cid, axis, p, (u, A + da), (v, B + db)) for da, db in ((0, 0), (1, 0), (1, 1), (0, 1))
            ]
            if 0 < p < n[axis]:
                lo, hi = _at(eid, axis, p - 1, (u, A), (v, B)), _at(eid, axis, p, (u, A), (v, B))
            else:
                fc = np.zeros((A.size, 3))
                fc[:, axis] = p * h[axis]
                fc[:, u] = (A + 0.5) * h[u]
                fc[:, v] = (B + 0.5) * h[v]
                face_ids = n_pts + np.arange(A.size)
                points.append(fc)
                n_pts += A.size
                if p == 0:
                    lo, hi = face_ids, _at(eid, axis, p, (u, A), (v, B))
                else:
                    lo, hi = _at(eid, axis, p - 1, (u, A), (v, B)), face_ids
            for k in range(4):
                tets.append(np.stack([lo, hi, ring[k], ring[(k + 1) % 4]], axis=1))

    pts = np.concatenate(points)
    t = np.concatenate(tets).astype(np.int64)
    neg = signed_volumes(pts, t) < 0
    t[neg, 2], t[neg, 3] = t[neg, 3], t[neg, 2].copy()
    if on_table:
        pts = pts - np.array([size_v[0] / 2, size_v[1] / 2, 0.0])
    return TetMesh(pts, t, name=name)


def _positive(what: str, value: float) -> float:
    """``value`` as a float, or :class:`MeshError` unless it is a positive finite number."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{what} must be a number in metres, got {value!r}") from exc
    if not (np.isfinite(v) and v > 0):
        raise MeshError(f"{what} must be positive and finite, got {value!r}")
    return v


def sphere(
    radius: float = 0.064,
    mesh_size: float | None = None,
    *,
    on_table: bool = True,
    name: str = "sphere",
    refinement: LocalRefinement | None = None,
) -> TetMesh:
    """An unstructured tet mesh of a ball, made by gmsh (Delaunay, netgen-optimised).

    Boundary nodes lie on the sphere to rounding error. The same arguments always give the same
    mesh (gmsh runs single-threaded with a fixed seed).

    Parameters
    ----------
    radius:
        Radius [m], > 0.
    mesh_size:
        Target edge length [m]; gmsh keeps edges between half of it and it. Default ``radius/4``.
        Measured for ``radius = 0.064`` (nodes / tets / volume error): mesh_size 0.032 ->
        210 / 676 / -3.5 %, 0.016 (default) -> 388 / 1381 / -2.1 %, 0.008 -> 2196 / 9725 /
        -0.53 %, 0.006 -> 4498 / 21204 / -0.31 %, 0.004 -> 14153 / 72066 (about 6 s).
    on_table:
        If true the ball rests on z = 0 with its volume centroid on the z axis (the mesh is not
        exactly symmetric, so its geometric centre is then off the axis by ~1e-5 m); otherwise
        the geometric centre is the origin.
    name:
        Label of the mesh.
    refinement:
        Finer elements near points given in the returned mesh's coordinates
        (:class:`LocalRefinement`; on the table, to the ~1e-5 m of its centring).

    Returns
    -------
    TetMesh
        The meshed ball; its volume approaches ``4/3 pi radius^3`` from below as mesh_size shrinks.

    Raises
    ------
    MeshError
        ``radius`` or ``mesh_size`` not positive and finite, ``mesh_size`` so small that more than
        about two million tets would be needed, gmsh missing or failing.
    """
    r = _positive("sphere radius", radius)
    h = default_mesh_size((2.0 * r) ** 3) if mesh_size is None else mesh_size
    h = check_mesh_size(h, 4.0 / 3.0 * np.pi * r**3, "sphere", extent=2.0 * r)
    with gmsh_session(h) as gmsh:
        gmsh.model.occ.addSphere(0.0, 0.0, 0.0, r)
        gmsh.model.occ.synchronize()
        _refine(gmsh, refinement, h, (0.0, 0.0, r) if on_table else (0.0, 0.0, 0.0))
        gmsh.model.mesh.generate(3)
        mesh = tet_mesh_from_model(gmsh, name)
    return mesh.on_table() if on_table else mesh


def cylinder(
    radius: float,
    height: float,
    mesh_size: float | None = None,
    *,
    on_table: bool = True,
    name: str = "cylinder",
    refinement: LocalRefinement | None = None,
) -> TetMesh:
    """An unstructured tet mesh of a solid circular cylinder with its axis along z, made by gmsh.

    Boundary nodes lie exactly on the side (distance ``radius`` from the axis) or on the flat caps.
    The same arguments always give the same mesh.

    Parameters
    ----------
    radius:
        Radius [m], > 0.
    height:
        Length along z [m], > 0.
    mesh_size:
        Target edge length [m]; gmsh keeps edges between half of it and it. Default
        ``(4 radius^2 height / 500)^(1/3)`` (from the bounding box; radius/4 when height = 2 radius,
        giving 608 nodes for radius 0.064).
    on_table:
        If true the cylinder stands on z = 0 with its volume centroid on the z axis (its
        geometric axis is then off the z axis by ~1e-5 m, the mesh not being exactly symmetric);
        otherwise its axis is the z axis and it spans z from ``-height/2`` to ``height/2``.
    name:
        Label of the mesh.
    refinement:
        Finer elements near points given in the returned mesh's coordinates
        (:class:`LocalRefinement`; on the table, to the ~1e-5 m of its centring).

    Returns
    -------
    TetMesh
        The meshed cylinder; its volume approaches ``pi radius^2 height`` from below.

    Raises
    ------
    MeshError
        ``radius``, ``height`` or ``mesh_size`` not positive and finite, ``mesh_size`` so small
        that more than about two million tets would be needed, gmsh missing or failing.
    """
    r = _positive("cylinder radius", radius)
    length = _positive("cylinder height", height)
    h = (
        min(default_mesh_size(4.0 * r**2 * length), 0.25 * min(2.0 * r, length))
        if mesh_size is None
        else mesh_size
    )
    h = check_mesh_size(h, np.pi * r**2 * length, "cylinder", extent=min(2.0 * r, length))
    with gmsh_session(h) as gmsh:
        gmsh.model.occ.addCylinder(0.0, 0.0, -0.5 * length, 0.0, 0.0, length, r)
        gmsh.model.occ.synchronize()
        _refine(gmsh, refinement, h, (0.0, 0.0, 0.5 * length) if on_table else (0.0, 0.0, 0.0))
        gmsh.model.mesh.generate(3)
        mesh = tet_mesh_from_model(gmsh, name)
    return mesh.on_table() if on_table else mesh


def cuboid(
    size: Sequence[float],
    mesh_size: float,
    *,
    on_table: bool = True,
    name: str = "box",
    refinement: LocalRefinement | None = None,
) -> TetMesh:
    """An unstructured tet mesh of a rectangular box made by gmsh: what :func:`box` meshes on a
    grid, where elements of one size everywhere will not do (``refinement``: finer elements near
    points given in the returned mesh's coordinates, :class:`LocalRefinement`).

    Parameters
    ----------
    size: edge lengths [m] along x, y, z.
    mesh_size: target edge length [m] away from the refined zones.
    on_table: if true the box stands on z = 0 centred on the z axis (as :func:`box`'s); otherwise
        it spans [0, size].

    Raises
    ------
    MeshError
        A size or ``mesh_size`` not positive and finite, too many tets, gmsh missing or failing.
    """
    sx, sy, sz = (_positive("box size", v) for v in size)
    h = check_mesh_size(mesh_size, sx * sy * sz, "box", extent=min(sx, sy, sz))
    x0, y0 = (-0.5 * sx, -0.5 * sy) if on_table else (0.0, 0.0)
    with gmsh_session(h) as gmsh:
        gmsh.model.occ.addBox(x0, y0, 0.0, sx, sy, sz)
        gmsh.model.occ.synchronize()
        _refine(gmsh, refinement, h)
        gmsh.model.mesh.generate(3)
        return tet_mesh_from_model(gmsh, name)
