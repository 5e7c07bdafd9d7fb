"""Built-in objects of the paper's experiments, and loading user objects.

* ``cube`` — the foam cube of the indentation experiment: 50 mm edge (the paper does not give its
  size; 50 mm fits the hand), mass 12.5 g (density 100 kg/m^3, a dense polyurethane foam), material
  ``foam`` (Table 1: E = 4.9284 MPa, nu = 0.39). Meshed as a structured BCC box.
* ``sphere`` — the rubber sphere of the grasp experiment: radius 0.064 m, mass 0.05 kg (Sec. 4.2),
  material ``rubber`` (Table 1: E = 0.0793 MPa, nu = 0.45). Meshed with gmsh.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import astuple, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp import usercache
from softgrasp.errors import MeshError
from softgrasp.model.material import Material, preset
from softgrasp.model.memory import release_freed_memory
from softgrasp.model.mesh.generate import LocalRefinement
from softgrasp.model.mesh.placement import rest_on_table_transform
from softgrasp.model.mesh.tetmesh import TetMesh
from softgrasp.model.ranges import RANGES, check_object_size

__all__ = [
    "ObjectSpec",
    "OBJECTS",
    "CUBE_SIZE",
    "SPHERE_RADIUS",
    "FILE_MATERIAL",
    "make_object",
    "make_placed_object",
    "check_object",
    "is_mesh_file",
    "element_size",
]

#: Edge of the default foam cube [m].
CUBE_SIZE = 0.05
#: Radius of the default rubber sphere [m] (paper, Sec. 4.2).
SPHERE_RADIUS = 0.064
#: The material a mesh file or a shape takes when it is given without one (with a warning from
#: :func:`softgrasp.io.options.load_body`): the rubber preset's stiffness (Table 1) at the density
#: of water, near that of fruit, silicone and most soft solids (900-1 200 kg/m^3).
FILE_MATERIAL = Material(E=preset("rubber").E, nu=preset("rubber").nu, density=1000.0, name="rubber")
#: Generated meshes kept per process (see :func:`_generated`).
GENERATED_KEPT = 4


@dataclass(frozen=True)
class ObjectSpec:
    """A built-in object: its default material, total mass [kg] and default element size [m]."""

    name: str
    material: str
    mass: float
    mesh_size: float
    description: str


OBJECTS: dict[str, ObjectSpec] = {
    "cube": ObjectSpec("cube", "foam", 0.0125, CUBE_SIZE / 6, "50 mm foam cube, 12.5 g"),
    "sphere": ObjectSpec("sphere", "rubber", 0.05, SPHERE_RADIUS / 4, "rubber sphere, radius 64 mm, 50 g"),
}


def make_object(
    name_or_path: str, mesh_size: float | None = None, *, reorient: bool = False, scale: float = 1.0
) -> tuple[TetMesh, Material, float | None]:
    """Mesh, default material and mass [kg] of a built-in object, a shape or a mesh file.

    A file (any tet mesh meshio reads, or a closed .stl/.obj surface) or a shape gets
    :data:`FILE_MATERIAL` and no fixed mass (the material density decides); a file's coordinates
    times ``scale`` are metres (``1e-3`` for a file in millimetres); ``reorient`` flips its
    inverted tets instead of refusing them. A shape's sizes are times ``scale`` as well; the
    built-in objects have their own size (``scale`` 1). An object outside
    :data:`~softgrasp.model.ranges.OBJECT_SIZE_M` (1 mm to 0.5 m) is refused before it is meshed
    where its size is known then (shapes, surface files).
    The mesh rests on the table plane z = 0 in a stable pose
    (:func:`~softgrasp.model.mesh.placement.rest_on_table`).
    """
    mesh, material, mass, _ = make_placed_object(name_or_path, mesh_size, reorient=reorient, scale=scale)
    return mesh, material, mass


def make_placed_object(
    name_or_path: str,
    mesh_size: float | None = None,
    *,
    reorient: bool = False,
    scale: float = 1.0,
    refinement: LocalRefinement | None = None,
) -> tuple[TetMesh, Material, float | None, NDArray[np.float64]]:
    """:func:`make_object`, and the transform (4, 4) from the source's coordinates to the mesh's
    (``p_mesh = T p_source``, homogeneous; metres out): a mesh file's coordinates in its units
    (``scale`` metres each), turned and moved to rest on the table; a built-in object's or a
    shape's coordinates as softgrasp generates them (metres: standing on z = 0, a box about the z
    axis, a sphere, ball or cylinder with its centroid on it). ``refinement``: finer elements
    near points in those coordinates (a built-in object or a shape; a box is then meshed by gmsh)."""
    mesh, material, mass, T = _make_object(name_or_path, mesh_size, reorient, scale, refinement)
    release_freed_memory()
    return mesh, material, mass, T


def _make_object(
    name_or_path: str,
    mesh_size: float | None,
    reorient: bool,
    scale: float = 1.0,
    refinement: LocalRefinement | None = None,
) -> tuple[TetMesh, Material, float | None, NDArray[np.float64]]:
    # A built-in object or a shape is meshed here and refines (a box then by gmsh,
    # generate.cuboid, instead of on its grid); a mesh file does not.
    if refinement is not None and is_mesh_file(name_or_path):
        raise MeshError(
            f"local refinement needs a built-in object or a shape meshed here; {name_or_path} is a mesh "
            "file: refine it where the fingertips press before loading it"
        )
    if mesh_size is not None:
        RANGES["mesh_size"].check("mesh size", mesh_size, MeshError)
    if not (math.isfinite(scale) and scale > 0):
        raise MeshError(f"scale must be positive and finite, got {scale!r}")
    check_object(name_or_path, scale)
    if name_or_path in OBJECTS:
        spec = OBJECTS[name_or_path]
        mesh, T = _generated(name_or_path, mesh_size, 1.0, refinement)
        return mesh, preset(spec.material), spec.mass, T.copy()
    if _is_shape(name_or_path):
        mesh, T = _generated(name_or_path, mesh_size, scale, refinement)
        return mesh, FILE_MATERIAL, None, T.copy()
    path = Path(name_or_path)
    if not path.suffix:
        raise MeshError(
            f"unknown object {name_or_path!r}; built-in objects are {sorted(OBJECTS)}, or give a mesh file"
        )
    from softgrasp.model.mesh.io import load_mesh

    mesh, T = rest_on_table_transform(
        load_mesh(path, mesh_size=mesh_size, reorient=reorient, scale=scale, check_size=True)
    )
    return mesh, FILE_MATERIAL, None, T @ np.diag([scale, scale, scale, 1.0])


def is_mesh_file(name_or_path: str) -> bool:
    """Whether ``name_or_path`` names a mesh file rather than a built-in object or a shape."""
    return name_or_path not in OBJECTS and not _is_shape(name_or_path)


def _is_shape(name_or_path: str) -> bool:
    """Whether ``name_or_path`` is a parametric shape (``KIND:DIMENSIONS``, :data:`SHAPES`)."""
    return ":" in name_or_path and name_or_path.split(":", 1)[0] in SHAPES


def check_object(name_or_path: str, scale: float = 1.0) -> None:
    """Refuse, before any meshing, units (``scale`` metres per unit, 1 for metres) given with a
    built-in object, and a shape that cannot be read or whose size lies outside
    :data:`~softgrasp.model.ranges.OBJECT_SIZE_M`. A mesh file is checked when it is read."""
    if name_or_path in OBJECTS and scale != 1.0:
        raise MeshError(
            f"units apply to mesh files and shapes; the built-in {name_or_path!r} has its own size "
            "in metres: leave --units at m"
        )
    if _is_shape(name_or_path):
        _shape_sizes(name_or_path, scale)


@functools.lru_cache(maxsize=GENERATED_KEPT)
def _generated(
    name: str, mesh_size: float | None, scale: float = 1.0, refinement: LocalRefinement | None = None
) -> tuple[TetMesh, NDArray[np.float64]]:
    """The mesh of a built-in object or parametric shape, generated once per process for each
    (name, mesh size) among the last few asked for: meshing is deterministic, the mesh immutable
    (its arrays read-only), and a sweep or a script planning the same object again (another
    friction coefficient, material or hand) then skips gmsh (0.3 s for the default sphere, 0.8 s
    at 2 196 nodes); with the transform from the generated coordinates to the resting mesh's.
    Across processes the meshes are kept in softgrasp's cache folder (:mod:`softgrasp.usercache`),
    keyed by the parameters, gmsh's version and the meshing modules' sources."""
    key = usercache.entry_key(
        "mesh", name, mesh_size, scale, _gmsh_version(), usercache.source_digest(*MESHING_MODULES),
        *(() if refinement is None else ("refined", *astuple(refinement))),
    )  # fmt: skip
    kept = _kept_mesh(key)
    if kept is not None:
        return kept
    with usercache.making("meshes", key):  # (another process meshing it: its mesh, once made)
        kept = _kept_mesh(key)
        if kept is not None:
            return kept
        mesh, T = _generate(name, mesh_size, scale, refinement)
        usercache.store("meshes", key, {"points": mesh.points, "tets": mesh.tets, "T": T, "name": mesh.name})
    return mesh, T


def _kept_mesh(key: str) -> tuple[TetMesh, NDArray[np.float64]] | None:
    kept = usercache.load("meshes", key)
    if kept is not None and {"points", "tets", "T", "name"} <= kept.keys():
        return TetMesh(kept["points"], kept["tets"], name=str(kept["name"])), kept["T"]
    return None


#: The modules whose sources decide a generated mesh (they key its cache entry).
MESHING_MODULES = (
    "softgrasp.model.objects",
    "softgrasp.model.mesh.generate",
    "softgrasp.model.mesh._gmsh",
    "softgrasp.model.mesh.placement",
    "softgrasp.model.mesh.tetmesh",
)


def _gmsh_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("gmsh")
    except PackageNotFoundError:
        return "none"


def _generate(
    name: str, mesh_size: float | None, scale: float, refinement: LocalRefinement | None = None
) -> tuple[TetMesh, NDArray[np.float64]]:
    from softgrasp.model.mesh import generate

    h = element_size(name, mesh_size, scale)
    if name in OBJECTS:
        spec = OBJECTS[name]
        if spec.name == "cube":
            return _box((CUBE_SIZE,) * 3, h, "cube", refinement), np.eye(4)
        return rest_on_table_transform(
            generate.sphere(SPHERE_RADIUS, h, name="sphere", refinement=refinement)
        )
    return _shape(name, h, scale, refinement)


def element_size(name: str, mesh_size: float | None, scale: float = 1.0) -> float:
    """The element size [m] a built-in object or a shape is meshed at: ``mesh_size``, else its
    default (a shape's: a quarter of its smallest size given, a ball's radius)."""
    if mesh_size is not None:
        return mesh_size
    if name in OBJECTS:
        return OBJECTS[name].mesh_size
    _, vals = _shape_sizes(name, scale)
    return min(vals) / 4


def _box(size: Sequence[float], h: float, name: str, refinement: LocalRefinement | None) -> TetMesh:
    """A box standing on the table meshed at about ``h``: on its grid
    (:func:`~softgrasp.model.mesh.generate.box`), or by gmsh where it is refined locally."""
    from softgrasp.model.mesh import generate

    if refinement is None:
        return generate.box(size, _box_cells(name, size, h), name=name)
    _box_cells(name, size, h)  # the same check of the mesh size against the thinnest edge
    return generate.cuboid(size, h, name=name, refinement=refinement)


def _box_cells(what: str, size: Sequence[float], h: float) -> list[int]:
    """Cells of a box meshed at about ``h`` along each edge (``size``); at least two across its
    thinnest edge, else MeshError (a box one cell thick has no interior node and forces that mean
    nothing: most often a size meant in millimetres given as metres)."""
    cells = [max(1, round(a / h)) for a in size]
    if min(cells) < 2:
        from softgrasp.model.mesh._gmsh import millimetre_hint

        thin = min(size)
        raise MeshError(
            f"{what} mesh_size {h:.4g} m leaves fewer than two cells across its thinnest edge "
            f"({thin * 1e3:.3g} mm); {millimetre_hint(h, thin / 1.5)}use mesh_size <= {thin / 1.5:.3g} m"
        )
    return cells


#: Most cells of a parametric box (each 12 tets): beyond it, a coarser --mesh-size is needed.
MAX_SHAPE_CELLS = 20_000

#: Parametric shapes ``--object KIND:DIMENSIONS`` (in --units, default metres): what each needs.
SHAPES = {
    "box": "box:WxDxH (edge lengths; box:A for a cube)",
    "cylinder": "cylinder:DxH (diameter x height, axis vertical)",
    "ball": "ball:R (radius)",
}


def _shape_sizes(spec: str, scale: float) -> tuple[str, list[float]]:
    """The kind of a shape and its sizes [m] (its numbers times ``scale``), checked: readable,
    positive and finite, and an object of :data:`~softgrasp.model.ranges.OBJECT_SIZE_M`."""
    kind, _, dims = spec.partition(":")
    try:
        vals = [float(v) * scale for v in dims.lower().split("x")]
    except ValueError:
        vals = []
    want = {"box": (1, 3), "cylinder": (2,), "ball": (1,)}[kind]
    if len(vals) not in want or not all(v > 0 and v < float("inf") for v in vals):
        raise MeshError(
            f"cannot read the shape {spec!r}; give {SHAPES[kind]} (sizes in metres, or in --units), "
            "every size > 0"
        )
    extent = {"box": vals * 3 if len(vals) == 1 else vals, "cylinder": [vals[0]] * 2 + vals[1:]}
    check_object_size(extent.get(kind, [2 * vals[0]] * 3), f"the shape {spec}", scale)
    return kind, vals


def _shape(
    spec: str, h: float, scale: float = 1.0, refinement: LocalRefinement | None = None
) -> tuple[TetMesh, NDArray[np.float64]]:
    """A specimen of a given shape and size (``box:0.04x0.04x0.02``, ``cylinder:0.03x0.02``,
    ``ball:0.03``; the sizes times ``scale`` in metres) meshed at element size ``h`` [m]
    (:func:`element_size`)."""
    from softgrasp.model.mesh import generate

    kind, vals = _shape_sizes(spec, scale)
    if kind == "box":
        size = vals * 3 if len(vals) == 1 else vals
        if refinement is None:
            cells = _box_cells(spec, size, h)
            if cells[0] * cells[1] * cells[2] > MAX_SHAPE_CELLS:
                raise MeshError(
                    f"{spec} at {h * 1e3:.3g} mm elements needs {cells[0] * cells[1] * cells[2]} cells (at "
                    f"most {MAX_SHAPE_CELLS}); give a larger --mesh-size"
                )
        return _box(size, h, spec, refinement), np.eye(4)
    if kind == "cylinder":
        D, H = vals
        return rest_on_table_transform(generate.cylinder(D / 2, H, h, name=spec, refinement=refinement))
    R = vals[0]
    return rest_on_table_transform(generate.sphere(R, h, name=spec, refinement=refinement))
