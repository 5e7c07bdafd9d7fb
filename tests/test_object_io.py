"""A user's own object and the files other tools read: mesh units, density and mass, material
files with overrides, the mesh-to-plan transform, the held state and the closing for ParaView,
the executed scene for MuJoCo, and outputs free of the machine's paths."""

from __future__ import annotations

import json
import os
import re
import shutil
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
import pytest

import softgrasp as sg
from softgrasp.cli import main
from softgrasp.errors import ConfigError, MaterialError, SoftgraspWarning

#: The ellipsoid's semi-axes [mm].
SEMI_AXES_MM = np.array([20.0, 16.0, 13.0])
#: A soft, solid material (the ellipsoid's; density given apart).
STIFF = "E=200e3,nu=0.45"


def _icosphere(levels: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Unit-sphere points (N, 3) and outward triangles (T, 3): an icosahedron split ``levels`` times."""
    t = (1 + 5**0.5) / 2
    pts = [
        (-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
        (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1),
    ]  # fmt: skip
    tri = [
        (0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
        (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
        (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1),
    ]  # fmt: skip
    v = [np.array(p, dtype=float) / np.linalg.norm(p) for p in pts]
    for _ in range(levels):
        mid: dict[tuple[int, int], int] = {}

        def half(a: int, b: int, mid: dict[tuple[int, int], int] = mid) -> int:
            key = (min(a, b), max(a, b))
            if key not in mid:
                m = v[a] + v[b]
                v.append(m / np.linalg.norm(m))
                mid[key] = len(v) - 1
            return mid[key]

        tri = [
            face
            for a, b, c in tri
            for face in ((a, half(a, b), half(c, a)), (b, half(b, c), half(a, b)),
                         (c, half(c, a), half(b, c)), (half(a, b), half(b, c), half(c, a)))
        ]  # fmt: skip
    return np.array(v), np.array(tri)


def write_ascii_stl(path: Path, points: np.ndarray, tri: np.ndarray) -> Path:
    """A closed surface as ASCII STL (shortest round-trip decimals)."""
    lines = ["solid ellipsoid"]
    for a, b, c in tri:
        n = np.cross(points[b] - points[a], points[c] - points[a])
        n /= np.linalg.norm(n)
        lines += [f"facet normal {float(n[0])!r} {float(n[1])!r} {float(n[2])!r}", " outer loop"]
        lines += [f"  vertex {float(p[0])!r} {float(p[1])!r} {float(p[2])!r}" for p in points[[a, b, c]]]
        lines += [" endloop", "endfacet"]
    path.write_text("\n".join([*lines, "endsolid ellipsoid", ""]))
    return path


@pytest.fixture(scope="module")
def ellipsoid(tmp_path_factory) -> dict[str, object]:
    """The same ellipsoid as an STL in millimetres and one in metres, and its surface (mm)."""
    d = tmp_path_factory.mktemp("ellipsoid")
    unit, tri = _icosphere(2)
    mm = unit * SEMI_AXES_MM
    return {
        "mm": write_ascii_stl(d / "ellipsoid_mm.stl", mm, tri),
        "m": write_ascii_stl(d / "ellipsoid_m.stl", mm * 1e-3, tri),
        "points_mm": mm,
        "tri": tri,
    }


def _distance_to_triangles(p: np.ndarray, tri_pts: np.ndarray) -> np.ndarray:
    """Exact distance of each point ``p`` (P, 3) to the nearest of the triangles ``tri_pts`` (T, 3, 3):
    to the plane where the projection falls inside the triangle, else to the nearest edge."""
    a, b, c = (tri_pts[None, :, k] for k in range(3))
    q = p[:, None, :]
    n = np.cross(b - a, c - a)
    nn = np.einsum("ptk,ptk->pt", n, n)
    h = np.einsum("ptk,ptk->pt", q - a, n) / nn
    proj = q - h[..., None] * n
    inside = np.ones(h.shape, dtype=bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ptk,ptk->pt", np.cross(v - u, proj - u), n) >= 0
    best = np.where(inside, np.abs(h) * np.sqrt(nn), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        t = np.clip(np.einsum("ptk,ptk->pt", q - u, e) / np.einsum("ptk,ptk->pt", e, e), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(q - (u + t[..., None] * e), axis=-1))
    return best.min(axis=1)


# ---------------------------------------------------------------------------- density, mass, material
def test_a_mesh_file_without_material_takes_water_and_rubber_with_a_warning(ellipsoid) -> None:
    with pytest.warns(SoftgraspWarning, match=r"--material .* and --density KG_M3 or --mass KG") as rec:
        obj = sg.load_object(ellipsoid["mm"], units="mm")
    assert "1000 kg/m^3" in str(rec[0].message) and "E = 79.3 kPa" in str(rec[0].message)
    assert obj.material.density == pytest.approx(1000.0)
    assert obj.mass_kg == pytest.approx(1000.0 * obj.mesh.volume)
    assert obj.material.E == sg.material("rubber").E


def test_density_or_mass_decides_a_file_objects_mass(ellipsoid) -> None:
    with pytest.warns(SoftgraspWarning, match="stiffness") as rec:
        heavy = sg.load_object(ellipsoid["mm"], units="mm", density_kg_m3=1200.0)
    assert "--density" not in str(rec[0].message)  # only the stiffness was taken by default
    assert heavy.mass_kg == pytest.approx(1200.0 * heavy.mesh.volume)
    obj = sg.load_object(ellipsoid["mm"], units="mm", material=STIFF, mass_kg=0.02)
    assert obj.mass_kg == pytest.approx(0.02) and obj.material.E == 200e3
    with pytest.raises(ConfigError, match="density_kg_m3 or its mass_kg, not both"):
        sg.load_object(ellipsoid["mm"], units="mm", density_kg_m3=1000.0, mass_kg=0.02)
    with pytest.raises(ConfigError, match=r"density_kg_m3 must be a number in \[1, 25000\]"):
        sg.load_object(ellipsoid["mm"], units="mm", material=STIFF, density_kg_m3=1e6)


def test_a_calibrated_material_file_is_usable_on_any_object(ellipsoid, tmp_path) -> None:
    toml = tmp_path / "material.toml"  # as calibrate writes it: no density
    toml.write_text('[material]\nname = "fitted"\nE_Pa = 150000.0\nnu = 0.4\nlaw = "linear"\n')
    a = sg.load_object(ellipsoid["mm"], units="mm", material=str(toml), density_kg_m3=1000.0)
    b = sg.load_object(ellipsoid["mm"], units="mm", material=f"{toml},density=1000")
    c = sg.load_object("sphere", material=f"{toml},mass=0.06")
    assert a.material.E == b.material.E == 150e3 and a.material.name == b.material.name == "fitted"
    assert a.mass_kg == pytest.approx(b.mass_kg) and a.mass_kg == pytest.approx(1000.0 * a.mesh.volume)
    assert c.mass_kg == pytest.approx(0.06) and c.material.E == 150e3
    with pytest.warns(SoftgraspWarning, match="has no density_kg_m3: softgrasp takes the density of water"):
        sg.load_object(ellipsoid["mm"], units="mm", material=str(toml))
    with pytest.raises(ConfigError, match="--density KG_M3 or --mass KG"):
        sg.load_object("ball:0.02", material=str(toml))
    with pytest.raises(ConfigError, match="cannot read 'colour=red'"):
        sg.load_object("sphere", material=f"{toml},colour=red")
    with pytest.raises(MaterialError, match="density"):
        sg.load_object("sphere", material=f"{toml},density=0")


def test_a_shape_without_material_takes_water_and_rubber_with_a_warning() -> None:
    with pytest.warns(SoftgraspWarning, match=r"the shape ball:0.03 is given without a material") as rec:
        obj = sg.load_object("ball:0.03", mesh_size_m=0.015)
    text = str(rec[0].message)
    assert "1000 kg/m^3" in text and "E = 79.3 kPa" in text and "--density KG_M3 or --mass KG" in text
    assert obj.material.density == pytest.approx(1000.0) and obj.material.E == sg.material("rubber").E
    assert obj.mass_kg == pytest.approx(1000.0 * obj.mesh.volume)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SoftgraspWarning)  # stated choices, and objects of their own
        dense = sg.load_object("ball:0.03", mesh_size_m=0.015, density_kg_m3=900.0)
        light = sg.load_object("ball:0.03", mesh_size_m=0.015, mass_kg=0.02)
        rubber = sg.load_object("ball:0.03", mesh_size_m=0.015, material="rubber")
        sphere, cube = sg.load_object("sphere"), sg.load_object("cube", mesh_size_m=0.025)
    assert dense.mass_kg == pytest.approx(900.0 * dense.mesh.volume) and light.mass_kg == pytest.approx(0.02)
    assert dense.material.E == sg.material("rubber").E  # the stated default stiffness
    assert rubber.material.density == sg.material("rubber").density
    assert sphere.mass_kg == pytest.approx(0.05) and cube.mass_kg == pytest.approx(0.0125)
    assert sphere.material.name == "rubber" and cube.material.name == "foam"


def test_the_command_line_warns_of_a_shape_without_material_but_not_with_density(tmp_path, capsys) -> None:
    argv = ["compress", "--object", "box:0.03", "--mesh-size", "0.015", "--strain", "0.02", "--steps", "2"]
    assert main([*argv, "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert "softgrasp: warning: the shape box:0.03 is given without a material" in err
    assert "--material" in err and "--density KG_M3 or --mass KG" in err
    doc = json.loads((tmp_path / "a" / "compress.json").read_text())
    assert doc["object"]["mass_kg"] == pytest.approx(0.027)  # 27 cm^3 of water's density
    assert main([*argv, "--density", "1000", "--out", str(tmp_path / "b")]) == 0
    assert "warning" not in capsys.readouterr().err


def test_the_command_line_takes_density_and_mass(ellipsoid, tmp_path, capsys) -> None:
    out = tmp_path / "c"
    argv = ["compress", "--object", str(ellipsoid["mm"]), "--units", "mm", "--strain", "0.02", "--steps", "2"]
    assert main([*argv, "--density", "900", "--out", str(out)]) == 0
    cap = capsys.readouterr()
    assert "softgrasp: warning: the mesh file ellipsoid_mm.stl is given without a material" in cap.err
    assert "--density" not in cap.err.split("warning:")[1]  # the density was given
    assert json.loads((out / "compress.json").read_text())["softgrasp_version"] == sg.__version__
    try:
        code = main([*argv, "--density", "900", "--mass", "0.1"])
    except SystemExit as exc:  # the argument parser's refusal
        code = int(exc.code or 0)
    assert code == 2 and "--mass: not allowed with argument --density" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--object", "sphere", "--mass", "3"], "weighs 3 kg"),
        (["--object", "ball:0.005", "--density", "2"], "weighs 0.001"),
    ],
)
def test_a_plan_refuses_an_object_the_hand_cannot_lift_or_feel(argv, message, tmp_path, capsys) -> None:
    code = main(["plan", *argv, "--out", str(tmp_path / "p")])
    err = capsys.readouterr().err
    assert code != 0 and message in err and "1 g to 2 kg" in err and "--density KG_M3 or --mass KG" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "p" / "plan.json").exists()


def test_config_files_set_density_and_mass(tmp_path) -> None:
    from softgrasp.api.planning import plan_options

    cfg = tmp_path / "c.toml"
    cfg.write_text('object = "ball:0.03"\nmaterial = "E=1e5,nu=0.4"\ndensity = 950.0\n')
    assert plan_options({}, cfg)["density"] == 950.0
    cfg.write_text("mass = 500.0\n")
    with pytest.raises(ConfigError, match=r"mass must be a number in \[1e-06, 100\] kg"):
        plan_options({}, cfg)


# ---------------------------------------------------------------------------- portable paths
def test_paths_are_recorded_by_package_name_or_relative_to_the_output(tmp_path) -> None:
    from softgrasp.hand.kinematics import HandModel
    from softgrasp.io.portable import portable_path, resolve_path

    hand = HandModel.default().source
    assert portable_path(hand, tmp_path) == "package:softgrasp/hand/shadow_like.urdf"
    packaged = resolve_path("package:softgrasp/hand/shadow_like.urdf", tmp_path)
    from importlib import resources

    assert packaged.is_file()
    assert packaged.read_text() == resources.files("softgrasp.hand").joinpath("shadow_like.urdf").read_text()
    (tmp_path / "in").mkdir()
    toml = tmp_path / "in" / "m.toml"
    toml.write_text("")
    out = tmp_path / "out" / "plan"
    assert portable_path(str(toml), out) == "../../in/m.toml"
    assert portable_path(f"{toml},density=1000", out) == "../../in/m.toml,density=1000"
    assert portable_path("rubber", out) == "rubber" and portable_path("box:0.04", out) == "box:0.04"
    assert resolve_path("../../in/m.toml", out).resolve() == toml.resolve()


# ---------------------------------------------------------------------------- a millimetre STL planned
@pytest.fixture(scope="module")
def planned_ellipsoid(ellipsoid, tmp_path_factory) -> dict[str, object]:
    """The ellipsoid planned from its millimetre STL and from its metre STL, written as plan runs."""
    plans = {}
    for unit in ("mm", "m"):
        obj = sg.load_object(ellipsoid[unit], units=unit, material=STIFF, density_kg_m3=1000.0)
        p = sg.plan(obj)
        out = tmp_path_factory.mktemp(f"plan-{unit}")
        p.write_plan_file(out)
        from softgrasp.io.paraview import write_closing_series

        write_closing_series(out, p.grasp, obj.body)
        plans[unit] = {"plan": p, "out": out, "doc": json.loads((out / "plan.json").read_text())}
    return plans


@pytest.mark.slow
def test_a_millimetre_stl_plans_as_the_same_object_in_metres(planned_ellipsoid) -> None:
    mm, m = planned_ellipsoid["mm"]["doc"], planned_ellipsoid["m"]["doc"]
    assert mm["object"]["mesh_units"] == "mm" and m["object"]["mesh_units"] == "m"
    assert 0.01 < mm["object"]["mass_kg"] < 0.03  # a 40 x 32 x 26 mm solid, not a 40 m one
    for name, sp in mm["setpoints_N"].items():
        assert sp == pytest.approx(m["setpoints_N"][name], rel=1e-6)
    assert [f["setpoint_N"] for f in mm["fingers"]] == list(mm["setpoints_N"].values())
    T_mm = np.array(mm["object"]["transform_mesh_to_plan"])
    T_m = np.array(m["object"]["transform_mesh_to_plan"])
    np.testing.assert_allclose(T_mm[:3, :3] * 1e3, T_m[:3, :3], atol=1e-9)  # the same turn, scaled
    assert "p_plan = T p_mesh" in mm["object"]["transform_note"]


@pytest.mark.slow
def test_the_transform_and_the_contacts_map_onto_the_users_mesh(ellipsoid, planned_ellipsoid) -> None:
    run = planned_ellipsoid["mm"]
    doc, out = run["doc"], run["out"]
    T = np.array(doc["object"]["transform_mesh_to_plan"])
    vtu = meshio.read(out / "object.vtu")
    placed = np.asarray(vtu.points)
    tets = vtu.cells_dict["tetra"]
    # The STL's vertices, taken to the plan frame, lie on object.vtu's surface, to the chords of
    # gmsh's remeshing (0.5 mm on this 40 mm ellipsoid).
    stl_mm = ellipsoid["points_mm"]
    mapped = stl_mm @ T[:3, :3].T + T[:3, 3]
    obj = sg.load_object(ellipsoid["mm"], units="mm", material=STIFF, density_kg_m3=1000.0)
    facets = np.asarray(obj.mesh.facets)
    size = float(np.ptp(placed, axis=0).max())
    assert np.asarray(obj.mesh.tets).shape == tets.shape
    assert _distance_to_triangles(mapped, placed[facets]).max() < 0.025 * size
    # And object.vtu's boundary nodes, taken back, lie exactly on the STL's triangles (millimetres).
    back = np.linalg.inv(T)
    nodes_mm = placed[np.unique(facets)] @ back[:3, :3].T + back[:3, 3]
    assert _distance_to_triangles(nodes_mm, stl_mm[ellipsoid["tri"]]).max() < 1e-9 * SEMI_AXES_MM.max()
    # Every contact in the mesh frame lies on the user's surface (to the remeshing's chords), and
    # is the plan's contact.
    contacts = np.array([f["contact_in_mesh_frame"] for f in doc["fingers"]])
    np.testing.assert_allclose(contacts, doc["initial_grasp"]["contacts_in_mesh_frame"])
    assert _distance_to_triangles(contacts, stl_mm[ellipsoid["tri"]]).max() < 0.025 * 2 * SEMI_AXES_MM.max()
    in_plan = contacts @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(in_plan, doc["initial_grasp"]["contacts_m"], atol=2e-4)


@pytest.mark.slow
def test_the_held_state_and_the_closing_open_in_paraview(planned_ellipsoid) -> None:
    run = planned_ellipsoid["mm"]
    plan, out = run["plan"], run["out"]
    g = plan.grasp
    vtu = meshio.read(out / "object.vtu")
    np.testing.assert_allclose(vtu.points, g.placed)  # the rest geometry execute reads
    np.testing.assert_allclose(vtu.point_data["displacement_m"], g.positions - g.placed)
    held = np.array([f.force for f in g.fingers]).sum(axis=0)
    total = vtu.point_data["contact_force_N"].sum(axis=0)
    np.testing.assert_allclose(total, held, atol=1e-6 * np.abs(held).max())
    strain = vtu.cell_data["max_principal_strain"][0]
    assert strain.shape == (len(vtu.cells_dict["tetra"]),)
    assert strain.max() == pytest.approx(g.damage.strain, rel=1e-9)
    root = ET.parse(out / "closing.pvd").getroot()
    sets = root.findall("./Collection/DataSet")
    assert root.get("type") == "Collection" and len(sets) == len(g.frames.travel) >= 3
    assert [float(s.get("timestep")) for s in sets] == [float(t) for t in g.frames.travel]
    for k, s in enumerate(sets):
        step = meshio.read(out / s.get("file"))
        np.testing.assert_allclose(step.points, g.frames.positions[k])
        assert {"displacement_m", "contact_force_N"} <= set(step.point_data)
        assert "max_principal_strain" in step.cell_data
    last = meshio.read(out / sets[-1].get("file"))
    assert np.abs(last.point_data["contact_force_N"]).sum() > 0


def test_the_users_ellipsoid_is_executed_in_mujoco_without_pressing_past_its_set_points(planned_ellipsoid):
    """The millimetre ellipsoid's plan (a coarse 162-point STL meshed by softgrasp, 200 kPa),
    executed in MuJoCo: its fingertips lose their contacts for single periods on the coarse flex,
    yet no finger presses more than the tolerance past its set-point while it closes, the closing
    reaches the set-points and the object is lifted. (When a lost contact was sought at full
    speed, the thumb pressed 1.8 times its set-point here, the forces spiked to 4-6 times the
    set-points in another run of this plan, and its closing ran 2.3 s instead of 0.65 s.)"""
    plan = planned_ellipsoid["mm"]["plan"]
    run = sg.execute(plan, lift_m=0.03, hold_s=0.5)
    close = run.result.series["phase"] == 1
    for j, name in enumerate(run.result.fingers):
        assert run.result.series["force"][close, j].max() <= 1.05 * plan.setpoints_N[name], name
    assert run.result.reached and run.lifted, run.to_dict()


# ---------------------------------------------------------------------------- outputs of every command
def _files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file()]


@pytest.mark.slow
def test_no_output_holds_the_machines_paths(ellipsoid, tmp_path, capsys) -> None:
    """plan (a mesh file, a material file and a URDF named by absolute paths), execute with
    --save-scene and a sweep: none of their
    files names the temporary folder, the home folder or softgrasp's own folder, and every JSON
    names the softgrasp version."""
    from softgrasp.hand.kinematics import HandModel

    inputs = tmp_path / "inputs"
    inputs.mkdir()
    from softgrasp.hand.packaged import package_file

    urdf = shutil.copy(package_file(HandModel.default().source), inputs / "my_hand.urdf")
    toml = inputs / "material.toml"
    toml.write_text("[material]\nE_Pa = 200000.0\nnu = 0.45\n")
    plan_dir, exe_dir, sweep_dir = tmp_path / "plan", tmp_path / "execute", tmp_path / "sweep"
    # A short hold, lift and sweep hold: the files' names of paths do not depend on them.
    argv = ["plan", "--object", str(ellipsoid["mm"]), "--units", "mm", "--material", str(toml)]
    argv += ["--hold-time", "0.3"]
    assert main([*argv, "--density", "1000", "--hand", str(urdf), "--out", str(plan_dir)]) == 0
    doc = json.loads((plan_dir / "plan.json").read_text())
    assert doc["hand"]["model"] == "../inputs/my_hand.urdf" == doc["parameters"]["hand"]
    scene = tmp_path / "scene" / "scene.xml"
    scene.parent.mkdir()
    argv = ["execute", str(plan_dir / "plan.json"), "--lift", "0.02", "--hold", "0.1", "--out", str(exe_dir)]
    code = main([*argv, "--save-scene", str(scene)])
    assert code in (0, 1)
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(scene))
    assert model.nflex == 1 and model.nkey == 1
    assert json.loads((exe_dir / "execute.json").read_text())["plan"] == "../plan/plan.json"
    spec = inputs / "sweep.toml"
    spec.write_text(
        f'[base]\nobject = "{ellipsoid["mm"]}"\nunits = "mm"\nmaterial = "{toml},density=1000"\n'
        "hold_time = 0.3\n[grid]\nmu = [0.8]\n"
    )
    assert main(["sweep", str(spec), "--out", str(sweep_dir), "--workers", "1"]) == 0
    capsys.readouterr()  # (reproduce's report: tests/test_reproduce.py checks it the same way)
    here = str(Path(sg.__file__).resolve().parents[2])
    machine = [str(tmp_path), os.path.realpath(tmp_path), here, os.path.expanduser("~") + "/"]
    pattern = re.compile("|".join(re.escape(m) for m in machine).encode())
    outputs = [p for d in (plan_dir, exe_dir, sweep_dir) for p in _files(d)] + [scene]
    leaks = {str(p.relative_to(tmp_path)) for p in outputs if pattern.search(p.read_bytes())}
    assert not leaks
    for p in outputs:
        if p.suffix == ".json" and not p.name.startswith("."):
            assert json.loads(p.read_text()).get("softgrasp_version") == sg.__version__, p


def test_compress_indent_and_calibrate_name_their_inputs_from_the_output_folder(
    tmp_path, capsys, monkeypatch
) -> None:
    """compress, indent (with measured data) and calibrate of a mesh file, each named by its
    absolute path: their JSON (and material.toml) name the mesh and data files relative to the
    output folder, never by the machine's paths, and every JSON names the softgrasp version;
    the figures' titles name the object by the file's stem."""
    import softgrasp.viz.plots as plots
    from softgrasp.model.mesh.generate import box
    from softgrasp.model.mesh.io import save_mesh

    titles = []
    for name in ("plot_stress_strain", "plot_force_penetration"):
        drawn = getattr(plots, name)

        def recorded(*args, _drawn=drawn, **kwargs):
            titles.append(kwargs["title"])
            return _drawn(*args, **kwargs)

        monkeypatch.setattr(plots, name, recorded)

    inputs = tmp_path / "inputs"
    inputs.mkdir()
    mesh = inputs / "block.vtu"
    save_mesh(box(0.03, 2), mesh)  # 59 nodes: a few seconds a command
    pen = np.linspace(0.0005, 0.003, 6)
    curve = inputs / "indent.csv"
    curve.write_text("penetration_m,force_N\n" + "".join(f"{a},{2000 * a**1.5}\n" for a in pen))
    d = np.linspace(0.0002, 0.003, 6)
    comp = inputs / "comp.csv"
    comp.write_text("displacement_m,force_N\n" + "".join(f"{a},{60 * a}\n" for a in d))
    obj = ["--object", str(mesh), "--material", "E=200e3,nu=0.45,density=1000"]
    out = {c: tmp_path / "out" / c for c in ("compress", "indent", "calibrate")}
    assert main(["compress", *obj, "--strain", "0.05", "--steps", "2", "--out", str(out["compress"])]) == 0
    argv = ["indent", *obj, "--depth", "0.003", "--steps", "4", "--data", str(curve)]
    assert main([*argv, "--out", str(out["indent"])]) == 0
    argv = ["calibrate", "--object", str(mesh), "--density", "1000", "--compression", str(comp), "--law"]
    assert main([*argv, "linear", "--nu", "0.3", "--steps", "6", "--out", str(out["calibrate"])]) == 0
    capsys.readouterr()
    names = {"compress": "compress.json", "indent": "indent.json", "calibrate": "calibration.json"}
    for c, name in names.items():
        doc = json.loads((out[c] / name).read_text())
        assert doc["softgrasp_version"] == sg.__version__
        assert doc.get("object", doc.get("specimen"))["name"] == "../../inputs/block.vtu", c
    assert json.loads((out["indent"] / "indent.json").read_text())["data_file"] == "../../inputs/indent.csv"
    assert titles[0].startswith("Compression of the block (")
    assert titles[1].startswith("Indentation of the block (")
    cal = json.loads((out["calibrate"] / "calibration.json").read_text())
    assert cal["fits"]["compression"]["data"] == "../../inputs/comp.csv"
    assert "compression ../../inputs/comp.csv" in (out["calibrate"] / "material.toml").read_text()
    here = str(Path(sg.__file__).resolve().parents[2])
    machine = [str(tmp_path), os.path.realpath(tmp_path), here, os.path.expanduser("~") + "/"]
    pattern = re.compile("|".join(re.escape(m) for m in machine).encode())
    leaks = [p for p in _files(tmp_path / "out") if pattern.search(p.read_bytes())]
    assert not leaks
