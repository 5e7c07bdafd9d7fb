"""Tests of the tet mesh, its generators and file I/O (softgrasp.model.mesh)."""

from __future__ import annotations

import os
import subprocess
import sys

import meshio
import numpy as np
import pytest

from softgrasp.errors import MeshError
from softgrasp.model.mesh import TetMesh, box, cylinder, load_mesh, save_mesh, sphere

R = 0.064  # sphere radius [m] used throughout


# ---------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def coarse_sphere() -> TetMesh:
    return sphere(R, 0.032, on_table=False)


@pytest.fixture(scope="module")
def default_sphere() -> TetMesh:
    return sphere()


@pytest.fixture(scope="module")
def cyl() -> TetMesh:
    return cylinder(0.03, 0.08, 0.01, on_table=False)


@pytest.fixture(scope="module")
def sphere_stl(tmp_path_factory: pytest.TempPathFactory, coarse_sphere: TetMesh):
    """An ASCII STL of the boundary of the coarse sphere mesh."""
    path = tmp_path_factory.mktemp("stl") / "ball.stl"
    meshio.write(path, meshio.Mesh(coarse_sphere.points, [("triangle", coarse_sphere.facets)]))
    return path


@pytest.fixture(scope="module", params=["box", "sphere", "cylinder", "stl"])
def any_mesh(request: pytest.FixtureRequest) -> TetMesh:
    if request.param == "box":
        return box((0.03, 0.05, 0.07), (3, 4, 5))
    if request.param == "sphere":
        return request.getfixturevalue("default_sphere")
    if request.param == "cylinder":
        return request.getfixturevalue("cyl")
    return load_mesh(request.getfixturevalue("sphere_stl"))


def one_tet() -> tuple[np.ndarray, np.ndarray]:
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float) * 0.01
    return points, np.array([[0, 1, 2, 3]])


def boundary_edges(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray]:
    f = mesh.facets
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)


# ---------------------------------------------------------------------------- geometry
def test_box_volume_is_product_of_sizes() -> None:
    m = box((0.03, 0.05, 0.07), (3, 4, 5))
    assert m.volume == pytest.approx(0.03 * 0.05 * 0.07, rel=1e-12)
    assert np.all(m.volumes > 0)


def test_boundary_normals_point_outward(any_mesh: TetMesh) -> None:
    # Divergence theorem with F(x) = x / 3: volume = sum over facets of area * (centroid . n) / 3.
    c = any_mesh.points[any_mesh.facets].mean(axis=1)
    flux = np.sum(any_mesh.facet_areas * np.einsum("ij,ij->i", c, any_mesh.facet_normals)) / 3.0
    assert flux == pytest.approx(any_mesh.volume, rel=1e-12)
    assert np.all(any_mesh.volumes > 0)


def test_boundary_is_closed_sphere_like_2_manifold(any_mesh: TetMesh) -> None:
    edges, counts = boundary_edges(any_mesh)
    assert np.all(counts == 2)
    n_vertices = len(any_mesh.boundary_nodes)
    assert n_vertices - len(edges) + len(any_mesh.facets) == 2


def test_sphere_boundary_nodes_lie_on_sphere(coarse_sphere: TetMesh) -> None:
    r = np.linalg.norm(coarse_sphere.points[coarse_sphere.boundary_nodes], axis=1)
    assert np.max(np.abs(r - R)) <= 1e-9 * R
    interior = np.setdiff1d(np.arange(coarse_sphere.n_nodes), coarse_sphere.boundary_nodes)
    assert interior.size > 0
    assert np.all(np.linalg.norm(coarse_sphere.points[interior], axis=1) < R * (1 - 1e-6))


def test_sphere_on_table(default_sphere: TetMesh) -> None:
    assert default_sphere.bounds[0, 2] == pytest.approx(0.0, abs=1e-15)
    assert default_sphere.bounds[1, 2] == pytest.approx(2 * R, rel=1e-12)
    assert np.allclose(default_sphere.centroid[:2], 0.0, atol=1e-12)
    assert 200 <= default_sphere.n_nodes <= 800
    assert default_sphere.name == "sphere"


def test_sphere_volume_converges_from_below() -> None:
    exact = 4.0 / 3.0 * np.pi * R**3
    errors = [exact - sphere(R, h).volume for h in (0.032, 0.016, 0.008)]
    assert all(e > 0 for e in errors)  # an inscribed polyhedron is smaller than the ball
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.01 * exact


def test_sphere_is_deterministic() -> None:
    a = sphere(0.05, 0.02)
    b = sphere(0.05, 0.02)
    assert np.array_equal(a.points, b.points)
    assert np.array_equal(a.tets, b.tets)


def test_cylinder_volume_and_boundary(cyl: TetMesh) -> None:
    r, h = 0.03, 0.08
    exact = np.pi * r**2 * h
    assert exact * 0.97 < cyl.volume < exact
    assert cyl.bounds[0, 2] == pytest.approx(-h / 2, rel=1e-12)
    assert cyl.bounds[1, 2] == pytest.approx(h / 2, rel=1e-12)
    p = cyl.points[cyl.boundary_nodes]
    on_side = np.abs(np.linalg.norm(p[:, :2], axis=1) - r) <= 1e-9 * r
    on_cap = np.abs(np.abs(p[:, 2]) - h / 2) <= 1e-12
    assert np.all(on_side | on_cap)
    assert on_side.sum() > 50 and on_cap.sum() > 50


def test_cylinder_on_table() -> None:
    m = cylinder(0.02, 0.05, 0.01)
    assert m.bounds[0, 2] == pytest.approx(0.0, abs=1e-15)
    assert m.bounds[1, 2] == pytest.approx(0.05, rel=1e-12)
    assert np.allclose(m.centroid[:2], 0.0, atol=1e-12)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: sphere(0.0), "sphere radius must be positive"),
        (lambda: sphere(-0.01), "sphere radius must be positive"),
        (lambda: sphere(float("nan")), "sphere radius must be positive"),
        (lambda: sphere("big"), "sphere radius must be a number"),  # type: ignore[arg-type]
        (lambda: sphere(R, 0.0), "sphere mesh_size must be positive"),
        (lambda: sphere(R, -0.01), "sphere mesh_size must be positive"),
        (lambda: sphere(R, 1e-4), r"too small: about .* tetrahedra"),
        (
            lambda: sphere(R, 0.07),
            r"coarser than half the object's thinnest dimension \(128 mm\).*<= 0.064 m",
        ),
        (lambda: cylinder(0.02, 0.1, 0.03), r"thinnest dimension \(40 mm\).*<= 0.02 m"),
        (lambda: cylinder(0.02, 0.0), "cylinder height must be positive"),
        (lambda: cylinder(-0.02, 0.1), "cylinder radius must be positive"),
        (lambda: cylinder(0.02, 0.1, float("inf")), "cylinder mesh_size must be positive"),
    ],
)
def test_generator_argument_errors(call, match: str) -> None:
    with pytest.raises(MeshError, match=match):
        call()


def test_a_thin_disc_meshes_at_its_default_size_and_a_refused_size_names_one_that_is_accepted() -> None:
    """The default element size of a thin object is capped below its thinnest dimension (a disc
    of radius 50 mm, 5 mm thick, meshes with elements across its thickness and its volume); a
    size refused as too coarse names the largest size accepted, and that one meshes."""
    import re

    disc = cylinder(0.05, 0.005, on_table=False)
    assert np.ptp(disc.points[:, 2]) == pytest.approx(0.005)
    assert len(np.unique(np.round(disc.points[:, 2], 7))) >= 3  # nodes inside the thickness
    assert disc.volume == pytest.approx(np.pi * 0.05**2 * 0.005, rel=0.02)
    with pytest.raises(MeshError) as err:
        cylinder(0.05, 0.005, 0.004, on_table=False)
    largest = float(re.search(r"use mesh_size <= ([0-9.e-]+) m", str(err.value)).group(1))
    assert "write" not in str(err.value)  # 0.004 is no size meant in millimetres
    assert cylinder(0.05, 0.005, largest, on_table=False).n_nodes > 0


def test_core_imports_without_gmsh_or_meshio() -> None:
    code = (
        "import sys, softgrasp, softgrasp.model.mesh; "
        "sys.exit(int('gmsh' in sys.modules or 'meshio' in sys.modules))"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    assert subprocess.run([sys.executable, "-c", code], env=env).returncode == 0


# ---------------------------------------------------------------------------- TetMesh validation
def test_tetmesh_empty() -> None:
    with pytest.raises(MeshError, match="empty mesh"):
        TetMesh(np.zeros((0, 3)), np.zeros((0, 4), dtype=int))


@pytest.mark.parametrize(
    ("points", "tets", "match"),
    [
        (np.zeros((4, 2)), np.array([[0, 1, 2, 3]]), r"points must have shape \(N, 3\)"),
        (np.zeros(12), np.array([[0, 1, 2, 3]]), r"points must have shape \(N, 3\)"),
        (one_tet()[0], np.array([[0, 1, 2]]), r"tets must have shape \(M, 4\)"),
        (one_tet()[0], np.array([0, 1, 2, 3]), r"tets must have shape \(M, 4\)"),
        (one_tet()[0], np.array([[0, 1, 2, 3.5]]), "integer node indices"),
    ],
)
def test_tetmesh_wrong_shapes(points: np.ndarray, tets: np.ndarray, match: str) -> None:
    with pytest.raises(MeshError, match=match):
        TetMesh(points, tets)


def test_tetmesh_nan_coordinate() -> None:
    p, t = one_tet()
    p[2, 1] = np.nan
    with pytest.raises(MeshError, match="node 2 has a non-finite coordinate"):
        TetMesh(p, t)


def test_tetmesh_index_out_of_range() -> None:
    p, _ = one_tet()
    with pytest.raises(MeshError, match=r"outside 0\.\.3"):
        TetMesh(p, np.array([[0, 1, 2, 4]]))
    with pytest.raises(MeshError, match=r"outside 0\.\.3"):
        TetMesh(p, np.array([[0, -1, 2, 3]]))


def test_tetmesh_repeated_node() -> None:
    p, _ = one_tet()
    with pytest.raises(MeshError, match="repeats a node"):
        TetMesh(p, np.array([[0, 1, 1, 3]]))


def test_tetmesh_unreferenced_node() -> None:
    p, t = one_tet()
    match = r"1 node\(s\) are not used by any tetrahedron \(first: node 4\)"
    with pytest.raises(MeshError, match=match):
        TetMesh(np.vstack([p, [[1.0, 1.0, 1.0]]]), t)


def test_tetmesh_zero_volume() -> None:
    p, t = one_tet()
    p[3] = [0.005, 0.005, 0.0]  # in the plane of the other three
    with pytest.raises(MeshError, match="tetrahedra have zero volume"):
        TetMesh(p, t)


def test_tetmesh_inverted_and_reorient() -> None:
    p, _ = one_tet()
    t = np.array([[0, 2, 1, 3]])
    with pytest.raises(MeshError, match=r"1 of 1 tetrahedra are inverted.*reorient=True"):
        TetMesh(p, t)
    m = TetMesh(p, t, reorient=True)
    assert np.all(m.volumes > 0)
    assert m.volume == pytest.approx(0.01**3 / 6, rel=1e-12)


def test_tetmesh_edge_only_contact_is_non_manifold() -> None:
    # Two tets sharing only the edge 0-1: that edge bounds four boundary facets.
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, -1, 0], [0, 0, -1]], dtype=float)
    t = np.array([[0, 1, 2, 3], [0, 1, 4, 5]])
    with pytest.raises(MeshError, match=r"boundary edge \[0, 1\] is shared by 4 boundary facets"):
        TetMesh(p, t, reorient=True)


def test_tetmesh_face_shared_by_three_tets() -> None:
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [0.2, 0.2, 2]], dtype=float)
    t = np.array([[0, 1, 2, 3], [0, 1, 2, 4], [0, 1, 2, 5]])
    with pytest.raises(MeshError, match=r"face \[0, 1, 2\] is shared by 3 tetrahedra"):
        TetMesh(p, t, reorient=True)


# ---------------------------------------------------------------------------- files
@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".vtk", ".mesh", ".inp"])
def test_save_load_round_trip(tmp_path, coarse_sphere: TetMesh, suffix: str) -> None:
    path = tmp_path / f"ball{suffix}"
    save_mesh(coarse_sphere, path)
    assert os.listdir(tmp_path) == [path.name]  # no temporary file left behind
    back = load_mesh(path)
    assert np.array_equal(back.points, coarse_sphere.points)
    assert np.array_equal(back.tets, coarse_sphere.tets)
    assert back.name == "ball"


def test_save_is_atomic(tmp_path, coarse_sphere: TetMesh, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "ball.vtu"
    save_mesh(coarse_sphere, path)
    before = path.read_bytes()

    def half_write(filename: str, mesh: meshio.Mesh) -> None:
        with open(filename, "w") as f:
            f.write("<VTKFile")
        raise OSError("disk full")

    monkeypatch.setattr(meshio.vtu, "write", half_write)
    with pytest.raises(MeshError, match=r"cannot write .*ball\.vtu: OSError: disk full"):
        save_mesh(box(), path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["ball.vtu"]


def test_save_writes_a_deformed_state(tmp_path, coarse_sphere: TetMesh) -> None:
    """``points`` replace the mesh's own in the file (a squeezed state, even one with an inverted
    tet that no mesh to simulate may have), with the mesh's cells; a wrong shape is refused."""
    squeezed = coarse_sphere.points * np.array([1.0, 1.0, 0.5])
    corners = squeezed[coarse_sphere.tets[0]]
    squeezed[coarse_sphere.tets[0, 0]] = 2.0 * corners[1:].mean(axis=0) - corners[0]  # through its face
    from softgrasp.model.mesh.tetmesh import signed_volumes

    assert (signed_volumes(squeezed, coarse_sphere.tets) < 0).any()
    path = tmp_path / "squeezed.vtu"
    save_mesh(coarse_sphere, path, points=squeezed)
    back = meshio.read(path)
    assert np.array_equal(back.points, squeezed)
    assert np.array_equal(back.cells_dict["tetra"], coarse_sphere.tets)
    with pytest.raises(MeshError, match=r"points of shape \(3, 3\)"):
        save_mesh(coarse_sphere, tmp_path / "bad.vtu", points=squeezed[:3])


def test_save_errors(tmp_path, coarse_sphere: TetMesh) -> None:
    with pytest.raises(MeshError, match=r"unsupported suffix '\.stl'"):
        save_mesh(coarse_sphere, tmp_path / "ball.stl")
    with pytest.raises(MeshError, match="does not exist"):
        save_mesh(coarse_sphere, tmp_path / "nowhere" / "ball.vtu")


def test_load_drops_unreferenced_nodes_and_takes_all_tet_blocks(tmp_path) -> None:
    p, _ = one_tet()
    points = np.vstack([p, [[0.01, 0.01, 0.01], [0.5, 0.5, 0.5]]])  # node 5 is used by no tet
    cells = [
        ("tetra", np.array([[0, 1, 2, 3]])),
        ("vertex", np.array([[5]])),
        ("tetra", np.array([[1, 2, 3, 4]])),
    ]
    meshio.write(tmp_path / "two.vtu", meshio.Mesh(points, cells))
    m = load_mesh(tmp_path / "two.vtu", reorient=True)
    assert m.n_nodes == 5 and m.n_tets == 2
    assert np.array_equal(m.points, points[:5])


def test_load_quadratic_tets_uses_corners(tmp_path) -> None:
    p, _ = one_tet()
    mids = (p[[0, 1, 2, 0, 0, 1]] + p[[1, 2, 0, 3, 2, 3]]) / 2  # VTK tetra10 edge order
    quadratic = meshio.Mesh(np.vstack([p, mids]), [("tetra10", np.arange(10)[None])])
    meshio.write(tmp_path / "q.vtu", quadratic)
    m = load_mesh(tmp_path / "q.vtu")
    assert m.n_nodes == 4
    assert m.volume == pytest.approx(0.01**3 / 6, rel=1e-12)


def test_load_gmsh_native_msh(tmp_path) -> None:
    import gmsh

    path = tmp_path / "native.msh"
    gmsh.initialize(["t", "-nopopup"], readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addBox(0, 0, 0, 0.02, 0.03, 0.04)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.01)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    m = load_mesh(path)
    assert m.volume == pytest.approx(0.02 * 0.03 * 0.04, rel=1e-12)


def test_load_scale(tmp_path, coarse_sphere: TetMesh) -> None:
    save_mesh(coarse_sphere.scaled(1e3), tmp_path / "mm.vtu")
    m = load_mesh(tmp_path / "mm.vtu", scale=1e-3, name="ball")
    assert np.allclose(m.points, coarse_sphere.points, rtol=0, atol=1e-15)
    assert m.name == "ball"
    with pytest.raises(MeshError, match="scale must be positive"):
        load_mesh(tmp_path / "mm.vtu", scale=0.0)


def test_stl_surface_is_tet_meshed(sphere_stl, coarse_sphere: TetMesh) -> None:
    m = load_mesh(sphere_stl, mesh_size=0.02)
    assert m.volume == pytest.approx(coarse_sphere.volume, rel=0.05)
    assert np.all(m.volumes > 0)
    assert m.name == "ball"


def test_surface_orientation_and_format_do_not_matter(tmp_path, coarse_sphere: TetMesh) -> None:
    f = coarse_sphere.facets.copy()
    f[::3] = f[::3, ::-1]  # every third triangle turned inside out
    meshio.write(tmp_path / "mixed.obj", meshio.Mesh(coarse_sphere.points * 1e3, [("triangle", f)]))
    m = load_mesh(tmp_path / "mixed.obj", scale=1e-3)
    assert m.volume == pytest.approx(coarse_sphere.volume, rel=0.05)
    assert m.bounds == pytest.approx(coarse_sphere.bounds, abs=2e-3)


def test_load_inverted_volume_file(tmp_path) -> None:
    p, _ = one_tet()
    meshio.write(tmp_path / "inv.vtu", meshio.Mesh(p, [("tetra", np.array([[0, 2, 1, 3]]))]))
    with pytest.raises(MeshError, match=r"inv\.vtu: 1 of 1 tetrahedra are inverted"):
        load_mesh(tmp_path / "inv.vtu")
    assert np.all(load_mesh(tmp_path / "inv.vtu", reorient=True).volumes > 0)


def write_surface(path, points: np.ndarray, tri: np.ndarray) -> None:
    meshio.write(path, meshio.Mesh(points, [("triangle", tri)]))


def test_load_errors(tmp_path, coarse_sphere: TetMesh, sphere_stl) -> None:
    with pytest.raises(MeshError, match=r"mesh file not found: .*nothing\.vtu"):
        load_mesh(tmp_path / "nothing.vtu")
    with pytest.raises(MeshError, match="not a file"):
        load_mesh(tmp_path)
    (tmp_path / "ball.xyz").write_text("0 0 0\n")
    with pytest.raises(MeshError, match=r"unknown mesh file suffix '\.xyz' of .*ball\.xyz"):
        load_mesh(tmp_path / "ball.xyz")
    (tmp_path / "nosuffix").write_text("0 0 0\n")
    with pytest.raises(MeshError, match=r"unknown mesh file suffix '\(none\)'"):
        load_mesh(tmp_path / "nosuffix")
    save_mesh(coarse_sphere, tmp_path / "ball.vtu")
    with pytest.raises(MeshError, match="mesh_size applies to surface files"):
        load_mesh(tmp_path / "ball.vtu", mesh_size=0.01)
    with pytest.raises(MeshError, match="too small"):
        load_mesh(sphere_stl, mesh_size=1e-5)


@pytest.mark.parametrize("suffix", [".vtu", ".vtk", ".msh", ".mesh", ".stl"])
def test_load_corrupt_file(tmp_path, suffix: str) -> None:
    path = tmp_path / f"junk{suffix}"
    path.write_bytes(b"solid? \x00\x01\x02 this is not a mesh\n1 2 three\n")
    with pytest.raises(MeshError, match=f"cannot read .*junk{suffix}: the file is corrupt"):
        load_mesh(path)


def test_load_truncated_file(tmp_path, coarse_sphere: TetMesh) -> None:
    save_mesh(coarse_sphere, tmp_path / "ball.msh")
    data = (tmp_path / "ball.msh").read_bytes()
    (tmp_path / "cut.msh").write_bytes(data[: len(data) // 2])
    with pytest.raises(MeshError, match=r"cannot read .*cut\.msh"):
        load_mesh(tmp_path / "cut.msh")


def test_load_file_without_tets(tmp_path, coarse_sphere: TetMesh) -> None:
    write_surface(tmp_path / "skin.vtu", coarse_sphere.points, coarse_sphere.facets)
    match = r"file has no tetrahedra \(cell types: triangle\); for a surface give \.stl/\.obj"
    with pytest.raises(MeshError, match=match):
        load_mesh(tmp_path / "skin.vtu")


def test_open_and_broken_surfaces(tmp_path, coarse_sphere: TetMesh) -> None:
    p, f = coarse_sphere.points, coarse_sphere.facets
    write_surface(tmp_path / "open.stl", p, f[1:])
    match = r"open\.stl: the surface is not closed: 3 edge\(s\) belong to one triangle only"
    with pytest.raises(MeshError, match=match):
        load_mesh(tmp_path / "open.stl")
    write_surface(tmp_path / "double.stl", p, np.vstack([f, f[:1]]))
    match = r"not closed: 3 edge\(s\) are shared by more than two triangles"
    with pytest.raises(MeshError, match=match):
        load_mesh(tmp_path / "double.stl")
    n = len(p)
    write_surface(tmp_path / "two.stl", np.vstack([p, p + np.array([0.2, 0, 0])]), np.vstack([f, f + n]))
    with pytest.raises(MeshError, match="several separate closed pieces"):
        load_mesh(tmp_path / "two.stl")
    flat = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], dtype=float)
    write_surface(tmp_path / "flat.stl", flat, np.array([[0, 1, 2], [0, 2, 1]]))
    with pytest.raises(MeshError, match="the surface is flat"):
        load_mesh(tmp_path / "flat.stl")
    # The 6-vertex projective plane: closed and manifold, but one-sided.
    rp2 = (
        np.array(
            [
                [1, 2, 3],
                [1, 3, 4],
                [1, 4, 5],
                [1, 5, 6],
                [1, 6, 2],
                [2, 3, 5],
                [3, 4, 6],
                [4, 5, 2],
                [5, 6, 3],
                [6, 2, 4],
            ]
        )
        - 1
    )
    rng = np.random.default_rng(0)
    write_surface(tmp_path / "rp2.stl", rng.random((6, 3)) * 0.01, rp2)
    with pytest.raises(MeshError, match="not orientable"):
        load_mesh(tmp_path / "rp2.stl")


# ---------------------------------------------------------------------------- numbering
def _edge_spread(mesh: TetMesh) -> float:
    """Mean difference of the two node numbers of an edge."""
    e = mesh.edges
    return float(np.abs(e[:, 1] - e[:, 0]).mean())


def test_reordered_mesh_is_the_same_solid_numbered_locally() -> None:
    """Renumbering moves no node and changes no tet: the same tets as coordinate quadruples (each
    with its own node order, so its orientation), the same boundary, every tet's volume; the
    neighbours' numbers come close (a random numbering of the same mesh as the peer), and tets
    run by their lowest node."""
    rng = np.random.default_rng(7)
    base = box((0.03, 0.05, 0.07), (4, 5, 6))
    perm = rng.permutation(base.n_nodes)  # a scattered numbering of the same solid
    inv = np.empty_like(perm)
    inv[perm] = np.arange(perm.size)
    scattered = TetMesh(base.points[perm], inv[base.tets][rng.permutation(base.n_tets)])
    local = scattered.reordered()

    def solid(m: TetMesh) -> set[bytes]:
        return {m.points[t].tobytes() for t in m.tets}

    assert solid(local) == solid(scattered) == solid(base)
    assert {local.points[f].tobytes() for f in local.facets} == {
        scattered.points[f].tobytes() for f in scattered.facets
    }
    assert sorted(local.volumes) == sorted(scattered.volumes)
    assert local.volume == pytest.approx(scattered.volume, rel=1e-14)
    # RCM numbers the nodes by breadth-first levels, each a cross-section of the solid: an edge
    # joins numbers less than about a cross-section's node count (~n^(2/3)) apart; a random
    # numbering puts them ~n/3 apart
    assert _edge_spread(scattered) > 0.3 * scattered.n_nodes
    assert _edge_spread(local) < local.n_nodes ** (2 / 3)
    assert (np.diff(local.tets.min(axis=1)) >= 0).all()


def test_gmsh_meshes_come_numbered_locally(default_sphere: TetMesh) -> None:
    """The gmsh sphere comes reordered: its edges join numbers less than a cross-section's node
    count apart (gmsh's own numbering: ~n / 3.7, near a random one's n / 3)."""
    assert _edge_spread(default_sphere) < default_sphere.n_nodes ** (2 / 3)
    assert (np.diff(default_sphere.tets.min(axis=1)) >= 0).all()


def test_body_forces_do_not_depend_on_the_numbering() -> None:
    """The body built from the renumbered mesh has the same masses, internal forces and
    Jacobian (permuted) at a deformed state: the numbering is bookkeeping, not physics."""
    from softgrasp.model.material import preset
    from softgrasp.physics.body import build_body

    mesh = sphere(R, 0.024, on_table=False)
    rng = np.random.default_rng(3)
    perm = rng.permutation(mesh.n_nodes)
    inv = np.empty_like(perm)
    inv[perm] = np.arange(perm.size)
    scattered = TetMesh(mesh.points[perm], inv[mesh.tets])
    local = scattered.reordered()
    # local.points = scattered.points[p]: find p from the coordinates
    key = {scattered.points[i].tobytes(): i for i in range(scattered.n_nodes)}
    p = np.array([key[q.tobytes()] for q in local.points])
    a = build_body(scattered, preset("rubber"), mass=0.05)
    b = build_body(local, preset("rubber"), mass=0.05)
    x = scattered.points + 1e-3 * rng.standard_normal(scattered.points.shape)
    np.testing.assert_allclose(b.mass, a.mass[p], rtol=1e-13, atol=0)
    fa = a.internal_forces(x)
    np.testing.assert_allclose(b.internal_forces(x[p]), fa[p], rtol=0, atol=1e-12 * np.abs(fa).max())
    idx = (3 * p[:, None] + np.arange(3)).ravel()
    Ja = a.internal_jacobian(x).toarray()[np.ix_(idx, idx)]
    np.testing.assert_allclose(b.internal_jacobian(x[p]).toarray(), Ja, rtol=0, atol=1e-12 * np.abs(Ja).max())


def test_generated_objects_are_meshed_once_and_stay_read_only() -> None:
    """A built-in object or parametric shape asked for again (a sweep's next case) is the mesh
    already generated: the same nodes and tets, arrays no caller can change; another mesh size
    or shape is meshed anew."""
    from softgrasp.model.objects import make_object

    first = make_object("box:0.03x0.02x0.02", 0.01)[0]
    again = make_object("box:0.03x0.02x0.02", 0.01)[0]
    assert again is first
    with pytest.raises(ValueError):
        first.points[0, 0] = 1.0
    with pytest.raises(ValueError):
        first.tets[0, 0] = 0
    finer = make_object("box:0.03x0.02x0.02", 0.005)[0]
    assert finer is not first and len(finer.points) > len(first.points)
    cube = make_object("cube", 0.025)[0]
    assert make_object("cube", 0.025)[0] is cube


@pytest.mark.parametrize("n", [7, 5_000, 2**21 - 1, 2**21, 3_000_000])
def test_unique_rows_of_node_indices_as_numpy_unique_by_rows(n: int) -> None:
    """The mesh's faces, edges and boundary checks find distinct rows of node indices by one
    integer key a row: the same unique rows, inverse and counts as ``np.unique(axis=0)``, with
    sorted and unsorted rows of two and three indices, as int64, int32 and uint64, the largest
    indices included; up to n = 2^21 - 1 three-index keys fit int64, from n = 2^21 they fall back
    to ``np.unique`` itself."""
    from softgrasp.model.mesh.tetmesh import _row_keys, _unique_rows

    rng = np.random.default_rng(n)
    for width in (2, 3):
        rows = rng.integers(0, n, (4_000, width))
        rows[0] = n - 1
        rows[1, 0] = n - 1
        rows = np.concatenate([rows, rows[::3]])  # repeated rows
        for r in (rows, np.sort(rows, axis=1)):
            want = np.unique(r, axis=0, return_inverse=True, return_counts=True)
            for typed in (r, r.astype(np.uint64)) + ((r.astype(np.int32),) if n < 2**31 else ()):
                got = _unique_rows(typed, n, inverse=True, counts=True)
                (u0, i0, c0), (u1, i1, c1) = want, got
                assert u0.shape == u1.shape and np.array_equal(u0, u1) and np.array_equal(c0, c1)
                assert np.array_equal(np.ravel(i0), i1) and i1.ndim == 1  # callers ravel it too
                assert np.array_equal(np.unique(r, axis=0), _unique_rows(typed, n))
    assert (_row_keys(np.zeros((1, 3), dtype=np.int64), n) is None) == (n >= 2**21)


def test_a_mesh_moved_rigidly_keeps_its_shape_and_a_deformed_or_mirrored_one_is_refused(
    coarse_sphere: TetMesh,
) -> None:
    """``moved`` places the rest shape elsewhere: a rotation and a shift keep the volume, the
    facets and the edge lengths; points that stretch an edge by a micrometre, or mirror the
    mesh (its tets inverted), are refused."""
    c, s = np.cos(0.7), np.sin(0.7)
    turn = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    pts = coarse_sphere.points @ turn.T + [0.01, -0.02, 0.03]
    moved = coarse_sphere.moved(pts)
    assert moved.volume == pytest.approx(coarse_sphere.volume, rel=1e-12)
    assert np.array_equal(moved.facets, coarse_sphere.facets)
    np.testing.assert_allclose(moved.edge_lengths, coarse_sphere.edge_lengths, rtol=1e-12)
    stretched = pts.copy()
    stretched[coarse_sphere.edges[0, 0]] += 1e-6
    with pytest.raises(MeshError, match="not a rigid motion"):
        coarse_sphere.moved(stretched)
    with pytest.raises(MeshError, match="inverted"):
        coarse_sphere.moved(coarse_sphere.points * [-1.0, 1.0, 1.0])
    with pytest.raises(MeshError, match="points"):
        coarse_sphere.moved(pts[:-1])
