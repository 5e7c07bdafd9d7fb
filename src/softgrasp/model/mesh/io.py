"""Reading and writing tetrahedral meshes; tet-meshing closed surface files with gmsh.

Volume files (``.msh``, ``.vtu``, ``.vtk``, ``.xdmf``, ``.mesh``, ``.med``, ``.inp``, ...) are read
with meshio and their tetrahedra taken as they are. Surface files (``.stl``, ``.obj``, ``.ply``,
``.off``) must describe a closed surface; it is remeshed and filled with tetrahedra by gmsh.
Coordinates in files are taken in metres unless a ``scale`` is given. meshio and gmsh are imported
only when a file is read or written.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import secrets
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import MeshError
from softgrasp.model.mesh._gmsh import (
    check_mesh_size,
    compact_nodes,
    default_mesh_size,
    gmsh_session,
    tet_mesh_from_model,
)
from softgrasp.model.mesh.tetmesh import TetMesh
from softgrasp.model.ranges import check_object_size

__all__ = ["load_mesh", "save_mesh"]

#: Surface formats: suffix -> meshio reader module.
_SURFACE_FORMATS: dict[str, str] = {".stl": "stl", ".obj": "obj", ".ply": "ply", ".off": "off"}
#: Volume formats: suffix -> meshio reader modules, tried in order.
_VOLUME_FORMATS: dict[str, tuple[str, ...]] = {
    ".msh": ("gmsh", "ansys"),
    ".vtu": ("vtu",),
    ".vtk": ("vtk",),
    ".xdmf": ("xdmf",),
    ".xmf": ("xdmf",),
    ".mesh": ("medit",),
    ".meshb": ("medit",),
    ".med": ("med",),
    ".inp": ("abaqus",),
    ".vol": ("netgen",),
    ".vol.gz": ("netgen",),
    ".ele": ("tetgen",),
    ".node": ("tetgen",),
    ".bdf": ("nastran",),
    ".fem": ("nastran",),
    ".nas": ("nastran",),
    ".su2": ("su2",),
    ".ugrid": ("ugrid",),
    ".avs": ("avsucd",),
    ".f3grid": ("flac3d",),
    ".e": ("exodus",),
    ".exo": ("exodus",),
    ".xml": ("dolfin",),
}
#: Writable formats: suffix -> meshio writer module (single-file formats only, so that the write
#: can be made atomic).
_WRITE_FORMATS: dict[str, str] = {
    ".vtu": "vtu",
    ".vtk": "vtk",
    ".msh": "gmsh",
    ".mesh": "medit",
    ".inp": "abaqus",
}
#: meshio's tetrahedral cells (linear; quadratic, whose first four nodes are the corners).
_TET_CELLS = ("tetra", "tetra10")
#: Words in the names of meshio's solid (3-D) cell types.
_SOLID_CELL_WORDS = ("tetra", "hexahedron", "wedge", "pyramid", "polyhedron")
#: Dihedral angle [rad] above which a surface edge is kept as a sharp feature when remeshing.
_FEATURE_ANGLE = math.radians(40.0)


def _suffix(path: Path, known: dict[str, Any]) -> str:
    """The longest known suffix of ``path`` (lower case), else its last suffix."""
    name = path.name.lower()
    matches = [s for s in known if name.endswith(s)]
    return max(matches, key=len) if matches else path.suffix.lower()


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Swallow what meshio prints (it writes warnings straight to stdout/stderr) and numpy
    floating-point warnings raised while it parses."""
    sink = io.StringIO()
    with (
        contextlib.redirect_stdout(sink),
        contextlib.redirect_stderr(sink),
        np.errstate(all="ignore"),
    ):
        yield


def _read(path: Path, formats: tuple[str, ...]) -> Any:
    """Read ``path`` with the first meshio reader in ``formats`` that succeeds."""
    import meshio

    failures = []
    for fmt in formats:
        try:
            with _quiet():
                return getattr(meshio, fmt).read(str(path))
        except Exception as exc:  # meshio raises many types on bad input
            failures.append((fmt, exc))
    detail = "; ".join(f"as {fmt}: {type(e).__name__}" + (f": {e}" if str(e) else "") for fmt, e in failures)
    raise MeshError(
        f"cannot read {path}: the file is corrupt or not in the format its suffix says ({detail})"
    ) from failures[0][1]


def _check_scale(scale: float) -> float:
    try:
        s = float(scale)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"scale must be a number, got {scale!r}") from exc
    if not (math.isfinite(s) and s > 0):
        raise MeshError(f"scale must be positive and finite, got {scale!r}")
    return s


def load_mesh(
    path: str | os.PathLike[str],
    *,
    mesh_size: float | None = None,
    reorient: bool = False,
    name: str | None = None,
    scale: float = 1.0,
    check_size: bool = False,
) -> TetMesh:
    """Load a tetrahedral mesh from a volume mesh file, or tet-mesh a closed surface file.

    Parameters
    ----------
    path:
        The file; its suffix selects the format. Volume formats: ``.msh`` (gmsh or ANSYS),
        ``.vtu``, ``.vtk``, ``.xdmf``/``.xmf``, ``.mesh``/``.meshb`` (Medit), ``.med``, ``.inp``
        (Abaqus), ``.vol`` (netgen), ``.ele``/``.node`` (TetGen), ``.bdf``/``.fem``/``.nas``,
        ``.su2``, ``.ugrid``, ``.avs``, ``.f3grid``, ``.e``/``.exo``, ``.xml`` (DOLFIN); their
        ``tetra`` cells (all blocks; the corner nodes of ``tetra10``) are used and nodes no tet uses
        are dropped. Surface formats: ``.stl``, ``.obj``, ``.ply``, ``.off``; the surface
        (triangles; polygons are split into triangles) must be one closed, orientable piece; it
        is remeshed and filled by gmsh.
    mesh_size:
        Target tet edge length [m] (after scaling) for surface files. Default one eighth of the
        geometric mean of the bounding-box sides. Not allowed for volume files, which are not
        remeshed.
    reorient:
        Flip inverted tets of a volume file instead of raising (see :class:`TetMesh`).
    name:
        Label of the mesh; default the file name without suffix.
    scale:
        Factor turning file coordinates into metres, e.g. ``1e-3`` for a file in millimetres.
    check_size:
        Refuse an object whose size lies outside :data:`~softgrasp.model.ranges.OBJECT_SIZE_M`
        (1 mm to 0.5 m), naming the length unit that would fit; a surface is checked before it is
        tet-meshed.

    Returns
    -------
    TetMesh
        The validated mesh, points in metres. A volume file keeps its node numbering (node
        numbers in softgrasp's outputs are the file's); a surface file's mesh comes numbered for
        memory locality (:meth:`TetMesh.reordered`; a volume mesh numbered scattered, as gmsh
        numbers, gains from it too).

    Raises
    ------
    MeshError
        Missing file, unknown suffix, unreadable or corrupt file, a volume file without
        tetrahedra, an open or non-manifold surface, ``mesh_size`` given for a volume file or too
        small, gmsh failing, or a mesh failing :class:`TetMesh` validation. The message names the
        file.
    """
    p = Path(path)
    factor = _check_scale(scale)
    if not p.exists():
        raise MeshError(f"mesh file not found: {p}")
    if not p.is_file():
        raise MeshError(f"not a file: {p}")
    surface = _suffix(p, _SURFACE_FORMATS)
    volume = _suffix(p, _VOLUME_FORMATS)
    stem = p.name[: len(p.name) - len(max(surface, volume, key=len))]
    label = name if name is not None else stem or "mesh"
    if surface in _SURFACE_FORMATS:
        return _mesh_surface_file(p, _SURFACE_FORMATS[surface], mesh_size, factor, label, check_size)
    if volume not in _VOLUME_FORMATS:
        raise MeshError(
            f"unknown mesh file suffix {volume or '(none)'!r} of {p}; volume formats: "
            f"{', '.join(_VOLUME_FORMATS)}; surface formats: {', '.join(_SURFACE_FORMATS)}"
        )
    if mesh_size is not None:
        raise MeshError(
            f"mesh_size applies to surface files ({', '.join(_SURFACE_FORMATS)}) only; {p} is a "
            "volume mesh and is used as it is"
        )
    data = _read(p, _VOLUME_FORMATS[volume])
    points, tets = _volume_arrays(p, data)
    try:
        mesh = TetMesh(points * factor, tets, reorient=reorient, name=label)
    except MeshError as exc:
        raise MeshError(f"{p}: {exc}") from exc
    if check_size:
        check_object_size(np.ptp(mesh.points, axis=0), f"the object in {p}", factor)
    return mesh


def _volume_arrays(path: Path, data: Any) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Points ``(N, 3)`` and linear tets ``(M, 4)`` of a meshio mesh, unreferenced nodes dropped.
    Surface, line and point cells (boundary groups) are passed over; solid cells other than
    tetrahedra (hexahedra, wedges, pyramids, polyhedra) are refused rather than dropped, which
    would leave holes in the object."""
    others: dict[str, int] = {}
    for c in data.cells:
        if c.type not in _TET_CELLS and any(w in c.type.lower() for w in _SOLID_CELL_WORDS):
            others[c.type] = others.get(c.type, 0) + len(c.data)
    if others:
        found = ", ".join(f"{n} {kind}" for kind, n in sorted(others.items()))
        raise MeshError(
            f"{path}: the mesh has solid cells other than tetrahedra ({found}); softgrasp models "
            "tetrahedra only: split them into tetrahedra (e.g. in gmsh) or give the surface (.stl) "
            "to tet-mesh it"
        )
    blocks = [np.asarray(c.data)[:, :4] for c in data.cells if c.type in _TET_CELLS and len(c.data)]
    if not blocks:
        kinds = sorted({c.type for c in data.cells}) or ["none"]
        raise MeshError(
            f"{path}: file has no tetrahedra (cell types: {', '.join(kinds)}); for a surface give "
            ".stl/.obj to tet-mesh it"
        )
    tets = np.concatenate(blocks).astype(np.int64)
    points = np.asarray(data.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"{path}: points must be 3-D, got an array of shape {points.shape}")
    if tets.min() < 0 or tets.max() >= points.shape[0]:
        raise MeshError(f"{path}: tetrahedra refer to nodes outside 0..{points.shape[0] - 1}")
    return compact_nodes(points, tets)


# ---------------------------------------------------------------------------- surfaces
def _surface_triangles(path: Path, data: Any) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Points ``(N, 3)`` and triangles ``(T, 3)`` of a meshio surface: polygons fanned into
    triangles, coincident points merged, unused points dropped."""
    tris = []
    for block in data.cells:
        faces = np.asarray(block.data)
        if block.type in ("triangle", "quad") or block.type.startswith("polygon"):
            for k in range(1, faces.shape[1] - 1):
                tris.append(faces[:, [0, k, k + 1]])
    points = np.asarray(data.points, dtype=np.float64)
    if not tris or points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"{path}: no surface triangles in 3-D found")
    tri = np.concatenate(tris).astype(np.int64)
    if tri.min() < 0 or tri.max() >= points.shape[0]:
        raise MeshError(f"{path}: faces refer to points outside 0..{points.shape[0] - 1}")
    if not np.isfinite(points).all():
        raise MeshError(f"{path}: the surface has non-finite coordinates")
    unique, inverse = np.unique(points, axis=0, return_inverse=True)
    tri = inverse.ravel()[tri]
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 2] != tri[:, 0])]
    if tri.shape[0] == 0:
        raise MeshError(f"{path}: all surface triangles are degenerate")
    return compact_nodes(unique, tri)


def _orient_closed_surface(path: Path, tri: NDArray[np.int64]) -> NDArray[np.int64]:
    """Check that the triangles ``(T, 3)`` form one closed, orientable 2-manifold and return them
    consistently oriented (some reversed if needed, following triangle 0), shape ``(T, 3)``.

    Raises
    ------
    MeshError
        An edge belongs to one triangle only (a hole) or to more than two (non-manifold), the
        surface falls apart into separate pieces, or it cannot be oriented.
    """
    # Half-edge k runs along triangle k % T.
    half = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    keys = np.sort(half, axis=1)
    _, edge_id, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    edge_id = edge_id.ravel()
    problems = []
    if (counts == 1).any():
        problems.append(f"{int((counts == 1).sum())} edge(s) belong to one triangle only (holes)")
    if (counts > 2).any():
        n_multi = int((counts > 2).sum())
        problems.append(f"{n_multi} edge(s) are shared by more than two triangles (non-manifold)")
    if problems:
        raise MeshError(
            f"{path}: the surface is not closed: {' and '.join(problems)}; a solid needs a closed, "
            "watertight surface"
        )
    order = np.argsort(edge_id, kind="stable")
    partner = np.empty_like(order)
    partner[order[0::2]] = order[1::2]
    partner[order[1::2]] = order[0::2]
    # Two triangles agree in orientation when they run their shared edge in opposite directions.
    disagree = (half[:, 0] == half[partner, 0]).tolist()
    n_tri = tri.shape[0]
    neighbour = (partner % n_tri).tolist()
    flip = [-1] * n_tri
    flip[0] = 0
    stack = [0]
    while stack:
        t = stack.pop()
        for k in (t, t + n_tri, t + 2 * n_tri):
            u, want = neighbour[k], flip[t] ^ disagree[k]
            if flip[u] < 0:
                flip[u] = want
                stack.append(u)
            elif flip[u] != want:
                raise MeshError(
                    f"{path}: the surface is not orientable (it is one-sided, which a closed "
                    "surface can only be if it passes through itself)"
                )
    if -1 in flip:
        raise MeshError(
            f"{path}: the surface consists of several separate closed pieces; give one object per file"
        )
    flipped = np.asarray(flip, dtype=bool)
    out = tri.copy()
    out[flipped] = out[flipped][:, ::-1]
    return out


def _outward(points: NDArray[np.float64], tri: NDArray[np.int64]) -> NDArray[np.int64]:
    """Consistently oriented closed triangles ``(T, 3)``, all reversed if needed so that their
    normals point outwards (positive enclosed volume): the mesh must not depend on the file's
    choice of orientation."""
    p = points[tri]
    enclosed = np.einsum("ij,ij->", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6.0
    return tri if enclosed > 0 else tri[:, ::-1].copy()


def _mesh_surface_file(
    path: Path, fmt: str, mesh_size: float | None, factor: float, label: str, check_size: bool = False
) -> TetMesh:
    """Tet-mesh the closed surface in ``path`` with gmsh (its size checked first if ``check_size``)."""
    points, tri = _surface_triangles(path, _read(path, (fmt,)))
    points = points * factor
    tri = _outward(points, _orient_closed_surface(path, tri))
    extent = np.ptp(points, axis=0)
    box_volume = float(np.prod(extent))
    if box_volume <= 0.0:
        raise MeshError(f"{path}: the surface is flat (extent {extent.tolist()} m) and encloses nothing")
    if check_size:
        check_object_size(extent, f"the object in {path}", factor)
    h = min(default_mesh_size(box_volume), 0.25 * float(extent.min())) if mesh_size is None else mesh_size
    h = check_mesh_size(h, box_volume, f"{path}:", extent=float(extent.min()))
    try:
        with gmsh_session(h) as gmsh:
            _fill_surface(gmsh, points, tri)
            return tet_mesh_from_model(gmsh, label)
    except MeshError as exc:
        raise MeshError(f"{path}: cannot tet-mesh the surface: {exc}") from exc


def _fill_surface(gmsh: Any, points: NDArray[np.float64], tri: NDArray[np.int64]) -> None:
    """Give gmsh the triangles as a discrete surface, rebuild a geometry split at sharp edges,
    bound a volume by it and mesh that volume."""
    surface = gmsh.model.addDiscreteEntity(2)
    gmsh.model.mesh.addNodes(2, surface, np.arange(1, points.shape[0] + 1), points.ravel())
    gmsh.model.mesh.addElementsByType(surface, 2, [], (tri + 1).ravel())
    gmsh.model.mesh.classifySurfaces(_FEATURE_ANGLE, True, True, math.pi)
    gmsh.model.mesh.createGeometry()
    patches = [tag for _, tag in gmsh.model.getEntities(2)]
    loop = gmsh.model.geo.addSurfaceLoop(patches)
    gmsh.model.geo.addVolume([loop])
    gmsh.model.geo.synchronize()
    gmsh.model.mesh.generate(3)


# ---------------------------------------------------------------------------- writing
def save_mesh(
    mesh: TetMesh,
    path: str | os.PathLike[str],
    *,
    point_data: Mapping[str, NDArray[np.float64]] | None = None,
    cell_data: Mapping[str, NDArray[np.float64]] | None = None,
    points: NDArray[np.float64] | None = None,
) -> None:
    """Write ``mesh`` (points in metres, tetra cells) to a volume mesh file, atomically, with
    named arrays per node (``point_data``: (N,) or (N, 3)) and per tet (``cell_data``: (M,)).
    ``points`` [m] (N, 3), when given, are written instead of the mesh's own: a deformed state of
    it (written as it is; a state may be squeezed beyond what a mesh to simulate must be).

    The file is written under a temporary name in the target directory and renamed over ``path``
    only once complete, so an error never leaves a half-written file.

    Parameters
    ----------
    mesh:
        The mesh to write.
    path:
        Target file; its suffix selects the format: ``.vtu``, ``.vtk``, ``.msh`` (gmsh 4.1),
        ``.mesh`` (Medit) or ``.inp`` (Abaqus).
    point_data, cell_data:
        Arrays by name (``.vtu`` and ``.vtk`` only): ParaView shows them on the mesh.
    points:
        Node positions to write instead of ``mesh.points``.

    Raises
    ------
    MeshError
        Unsupported suffix, missing directory, arrays of the wrong length or a format without
        them, or the write failing.
    """
    import meshio

    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in _WRITE_FORMATS:
        raise MeshError(
            f"cannot write {p}: unsupported suffix {suffix or '(none)'!r}; use one of "
            f"{', '.join(_WRITE_FORMATS)}"
        )
    if not p.parent.is_dir():
        raise MeshError(f"cannot write {p}: directory {p.parent} does not exist")
    fmt = _WRITE_FORMATS[suffix]
    if (point_data or cell_data) and fmt not in ("vtu", "vtk"):
        raise MeshError(f"cannot write {p}: data arrays go to .vtu or .vtk files only")
    xyz = np.asarray(mesh.points if points is None else points, dtype=np.float64)
    if xyz.shape != (mesh.n_nodes, 3):
        raise MeshError(f"cannot write {p}: points of shape {xyz.shape}, not ({mesh.n_nodes}, 3)")
    cells_data: dict[str, list[NDArray[Any]]] = {}
    nodes: dict[str, NDArray[Any]] = {}
    for kind, given, n in (("point", point_data, mesh.n_nodes), ("cell", cell_data, mesh.n_tets)):
        for name, a in (given or {}).items():
            arr = np.ascontiguousarray(a, dtype=np.float64)
            if arr.shape[0] != n:
                raise MeshError(f"cannot write {p}: {kind} data {name!r} has {arr.shape[0]} rows, not {n}")
            if kind == "point":
                nodes[name] = arr
            else:
                cells_data[name] = [arr]
    if fmt == "gmsh":
        tags = np.ones(mesh.n_tets, dtype=np.int32)
        cells_data = {"gmsh:physical": [tags], "gmsh:geometrical": [tags]}
    cells = [("tetra", np.asarray(mesh.tets))]
    data = meshio.Mesh(xyz, cells, point_data=nodes, cell_data=cells_data)
    tmp = p.with_name(f".{p.name}.{secrets.token_hex(4)}.tmp")
    done = False
    try:
        os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
        with _quiet():
            getattr(meshio, fmt).write(str(tmp), data)
        os.replace(tmp, p)
        done = True
    except Exception as exc:
        raise MeshError(f"cannot write {p}: {type(exc).__name__}: {exc}") from exc
    finally:
        if not done:
            with contextlib.suppress(OSError):
                tmp.unlink()
