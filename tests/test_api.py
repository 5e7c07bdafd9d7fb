"""The public Python API (``import softgrasp as sg``): the names of its contract, its defaults
(those of the command line), results whose ``save(dir)`` writes the command's files, units of
mesh files, and an import that loads no numerical or plotting module."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import softgrasp as sg
from softgrasp.cli import main
from softgrasp.model.material import Material as ModelMaterial

#: ``softgrasp plan``'s default normal-force set-points [N] (thumb, first, middle).
DEFAULT_NORMAL_N = {"thumb": 0.297, "first": 0.201, "middle": 0.207}


@pytest.fixture(scope="module")
def cli_plan(planned_sphere):
    """``softgrasp plan`` with every default: the session's plan (tests/conftest.py)."""
    return planned_sphere


@pytest.fixture(scope="module")
def api_plan():
    return sg.plan(sg.load_object("sphere"), hand=sg.load_hand("shadow_like"), mu=0.8)


def test_the_contract_names_are_exported():
    for name in (
        "load_object",
        "load_hand",
        "material",
        "Material",
        "plan",
        "execute",
        "compress",
        "indent",
        "calibrate",
        "SoftgraspError",
        "ConfigError",
        "MeshError",
        "MaterialError",
        "InfeasibleGrasp",
        "NotConverged",
        "SimulationUnstable",
        "ContactError",
    ):
        assert name in sg.__all__ and getattr(sg, name) is not None
    assert sg.Material is ModelMaterial
    with pytest.raises(AttributeError):
        sg.no_such_name  # noqa: B018


def test_importing_softgrasp_loads_no_heavy_module():
    code = (
        "import sys, softgrasp, softgrasp.api\n"
        "heavy = [m for m in ('matplotlib', 'mujoco', 'dask', 'distributed', 'numba', 'gmsh', 'meshio') "
        "if m in sys.modules]\n"
        "print(heavy)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_material_takes_keywords_with_units_and_stays_the_model_type():
    m = sg.Material(E_Pa=80e3, nu=0.45, density_kg_m3=950)
    assert isinstance(m, ModelMaterial)
    assert (m.E, m.nu, m.density, m.E_Pa, m.density_kg_m3) == (80e3, 0.45, 950, 80e3, 950)
    assert m == ModelMaterial(80e3, 0.45, 950)  # the positional form of the existing callers
    with pytest.raises(TypeError):
        sg.Material(E=1e5, E_Pa=1e5, nu=0.3)
    with pytest.raises(sg.MaterialError):
        sg.Material(E_Pa=-1.0, nu=0.3)
    rubber = sg.material("rubber")
    assert rubber == ModelMaterial(0.0793e6, 0.45, rubber.density, name="rubber")
    assert sg.material("E=1e5,nu=0.3,density=50").E == 1e5


def test_api_plan_defaults_are_the_command_lines(api_plan, cli_plan):
    """``sg.plan(sg.load_object("sphere"), hand=sg.load_hand("shadow_like"), mu=0.8)`` gives the
    set-points of ``softgrasp plan`` with every default."""
    doc = json.loads((cli_plan / "plan.json").read_text())
    cli = doc["setpoints_N"]
    assert api_plan.setpoints_N == pytest.approx(cli, rel=1e-9)
    held = {f.name: f.normal_force for f in api_plan.grasp.fingers}
    assert held == pytest.approx(DEFAULT_NORMAL_N, abs=5e-4)
    # the set-points: the default safety factor over the least multiple of them that holds
    s = api_plan.grasp.margin.scale
    assert api_plan.setpoints_N == pytest.approx({n: 1.25 * s * v for n, v in held.items()}, rel=1e-12)
    assert list(api_plan.setpoints_N) == ["thumb", "first", "middle"]
    assert sg.plan().setpoints_N == pytest.approx(cli, rel=1e-9)  # every argument's default


def test_plan_save_writes_the_files_of_the_command(api_plan, cli_plan, tmp_path):
    out = api_plan.save(tmp_path / "api")
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in cli_plan.iterdir())
    a = json.loads((out / "plan.json").read_text())
    b = json.loads((cli_plan / "plan.json").read_text())
    for doc in (a, b):
        doc.pop("wall_time_s")
        doc["parameters"].pop("hand")  # the packaged URDF's path: the same file in each
    assert a == b
    assert (out / "history.csv").read_text() == (cli_plan / "history.csv").read_text()
    assert api_plan.directory == out and api_plan.to_dict()["schema"] == "softgrasp.plan/2"


def test_load_object_scales_mesh_files_by_their_units(tmp_path):
    from softgrasp.model.mesh.generate import box
    from softgrasp.model.mesh.io import save_mesh
    from softgrasp.model.mesh.tetmesh import TetMesh

    mesh = box((0.04, 0.03, 0.02), (4, 3, 2))
    save_mesh(TetMesh(mesh.points * 1e3, mesh.tets, name="box"), tmp_path / "box_mm.vtu")
    save_mesh(TetMesh(mesh.points * 1e2, mesh.tets, name="box"), tmp_path / "box_cm.vtu")
    rubber = sg.Material(E_Pa=80e3, nu=0.45, density_kg_m3=950)
    mm = sg.load_object(tmp_path / "box_mm.vtu", units="mm", material=rubber)
    cm = sg.load_object(str(tmp_path / "box_cm.vtu"), units="cm", material=rubber)
    extent = np.ptp(mm.mesh.points, axis=0)
    assert sorted(extent) == pytest.approx([0.02, 0.03, 0.04])
    assert np.ptp(cm.mesh.points, axis=0) == pytest.approx(extent)
    assert mm.mass_kg == pytest.approx(950 * 0.04 * 0.03 * 0.02)
    assert mm.material is rubber and mm.name == "box_mm"
    # a shape's label is its whole spec, decimal points and all (a file's is its stem)
    assert sg.load_object("box:0.05x0.04x0.03", material=rubber).name == "box:0.05x0.04x0.03"
    with pytest.raises(sg.ConfigError, match="units"):
        sg.load_object(tmp_path / "box_mm.vtu", units="inch")
    with pytest.raises(sg.MeshError, match="metres"):
        sg.load_object("sphere", units="mm")


def test_a_material_without_density_keeps_a_builtin_objects_mass():
    obj = sg.load_object("cube", material=sg.Material(E_Pa=1e5, nu=0.3), mesh_size_m=0.025)
    assert obj.mass_kg == pytest.approx(0.0125)
    with pytest.raises(sg.ConfigError, match="density"):
        sg.load_object("box:0.04x0.04x0.02", material=sg.Material(E_Pa=1e5, nu=0.3))


def _visible(folder):
    """The files in ``folder`` but the hidden manifest (:mod:`softgrasp.io.runfolder`)."""
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def test_compress_and_indent_results_save_the_commands_files(tmp_path):
    cube = sg.load_object("cube", mesh_size_m=0.0125)
    test = sg.compress(cube, strain=0.05, steps=3)
    assert test.apparent_E_Pa > 0
    test.save(tmp_path / "api")
    assert main(
        ["compress", "--object", "cube", "--mesh-size", "0.0125", "--strain", "0.05", "--steps", "3"]
        + ["--out", str(tmp_path / "cli")]
    ) == 0
    names = _visible(tmp_path / "cli")
    assert _visible(tmp_path / "api") == names == [
        "compress.csv",
        "compress.json",
        "compress.png",
    ]
    assert (tmp_path / "api" / "compress.csv").read_text() == (tmp_path / "cli" / "compress.csv").read_text()
    a, b = (json.loads((tmp_path / d / "compress.json").read_text()) for d in ("api", "cli"))
    a.pop("wall_time_s"), b.pop("wall_time_s")
    assert a == b
    assert a["apparent_E_Pa"] == test.to_dict()["apparent_E_Pa"]
    ind = sg.indent(cube, depth_m=0.001, steps=2)
    assert ind.force_at_depth_N > 0 and ind.to_dict()["schema"] == "softgrasp.indent/1"
    ind.save(tmp_path / "ind")
    assert _visible(tmp_path / "ind") == ["indent.csv", "indent.json", "indent.png"]
