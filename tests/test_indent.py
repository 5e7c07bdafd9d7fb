"""Indentation by one fingertip (paper Sec. 4.3.1, Figs. 10-11): CLI files, measured-data overlay,
input errors, and the physics of the force-penetration curve."""

from __future__ import annotations

import csv
import json
import re
import subprocess
import sys

import numpy as np
import pytest

from softgrasp.cli import main
from softgrasp.errors import ConfigError
from softgrasp.experiments.indentation import indentation_test, read_force_curve
from softgrasp.model.material import Material
from softgrasp.model.objects import make_object
from softgrasp.physics.body import build_body

HEADER = ["time_s", "penetration_m", "force_N", "normal_force_N", "tangential_force_N", "contacts"]
#: A coarse cube (4 x 4 x 4 cells, not refined at the contacts) and a short path keep the CLI runs
#: at about a second each.
FAST = ["--mesh-size", "0.0125", "--contact-mesh-size", "none", "--depth", "0.002", "--steps", "4"]


def _main(argv: list[str], capsys) -> tuple[int, str]:
    """Run the CLI in-process; return (exit status, stderr)."""
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse errors exit through the parser
        rc = int(exc.code)
    return rc, capsys.readouterr().err


def _rows(path) -> list[dict[str, str]]:
    return list(csv.DictReader(path.open()))


@pytest.fixture(scope="module")
def default_cube_run(tmp_path_factory):
    """The paper's set-up on the default foam cube and mesh, 5 mm in 10 increments."""
    out = tmp_path_factory.mktemp("indent-default")
    assert main(["indent", "--steps", "10", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def fast_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("indent-fast")
    assert main(["indent", *FAST, "--out", str(out)]) == 0
    return out


def test_cli_writes_csv_json_png(default_cube_run):
    out = default_cube_run
    with (out / "indent.csv").open() as f:
        assert f.readline().rstrip("\n") == ",".join(HEADER)
    rows = _rows(out / "indent.csv")
    assert len(rows) == 11
    assert float(rows[0]["penetration_m"]) == 0.0
    assert float(rows[-1]["penetration_m"]) == pytest.approx(0.005)
    assert float(rows[-1]["time_s"]) == pytest.approx(
        float(rows[-1]["penetration_m"]) / 0.005 + float(rows[0]["time_s"])
    )
    data = json.loads((out / "indent.json").read_text())
    assert data["schema"] == "softgrasp.indent/1"
    for key in ("object", "parameters", "contact", "fingertip", "K_N_m1.5", "peak_force_N", "wall_time_s"):
        assert key in data
    assert "mean_abs_error_N" not in data
    assert data["object"]["name"] == "cube" and data["object"]["material"]["E_Pa"] == 4.9284e6
    # by default the mesh resolves the contact patch: a third of Hertz's radius sqrt(R depth)
    assert data["object"]["refinement"]["size_m"] == pytest.approx((0.008 * 0.005) ** 0.5 / 3)
    assert data["contact"]["mu"] == 0.8 and data["contact"]["rule"] == "patch"
    assert data["fingertip"]["radius_m"] == 0.008 and data["fingertip"]["velocity_m_s"] == [0.0, 0.0, -0.005]
    assert data["parameters"]["depth_m"] == 0.005 and data["parameters"]["steps"] == 10
    assert data["peak_force_N"] == pytest.approx(max(float(r["force_N"]) for r in rows))
    assert len(data["contact_depth_m"]) == len(rows)
    assert (out / "indent.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # no temporary files left: of the hidden ones, only the manifest of the files softgrasp wrote
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == [".softgrasp-manifest.json"]


def test_default_cube_force_rises_monotonically_and_non_linearly(default_cube_run):
    rows = _rows(default_cube_run / "indent.csv")
    p = np.array([float(r["penetration_m"]) for r in rows])
    F = np.array([float(r["force_N"]) for r in rows])
    assert F[0] == pytest.approx(0.0, abs=1e-9)
    assert (np.diff(F) > 0).all()
    assert all(int(r["contacts"]) > 0 for r in rows)
    # The paper's point (Sec. 4.3.1): force-penetration is not linear. The Hertz-like contact law
    # gives a log-log slope above 1 (the body's linear compliance in series pulls it below 1.5).
    slope = np.polyfit(np.log(p[1:]), np.log(F[1:]), 1)[0]
    assert 1.1 < slope < 1.5


def test_a_soft_heavy_ball_settles_and_is_indented():
    """A 40 mm ball of E = 5 kPa, nu = 0.45 and water's density: it settles on the table
    (:func:`softgrasp.sim.static.solve_rest`) with the top sagging by more than a millimetre, and
    the fingertip's force then rises from zero at first contact, steadily, with the travel."""
    mesh, _, _ = make_object("ball:0.02")
    body = build_body(mesh, Material(5e3, 0.45, 1000.0))
    res = indentation_test(body, depth=0.004, steps=8)
    assert res.settle_sag_m > 1e-3
    assert abs(res.force_N[0]) < 1e-9 * res.force_N[-1]
    assert (np.diff(res.force_N) > 0).all(), res.force_N


def _tilted(mesh, degrees: float):
    """``mesh`` turned about the x axis by ``degrees`` (balanced on an edge: it would tip over)."""
    from softgrasp.model.mesh.tetmesh import TetMesh

    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    return TetMesh(np.asarray(mesh.points) @ R.T, mesh.tets)


def test_an_object_given_on_an_edge_is_pressed_as_it_stands():
    """A block given balanced on an edge (turned 25 degrees) has no rest there but the rough table's
    stick: it is turned onto its most stable facet, its base, as plan places it, and pressed
    there with the same forces as the block given standing (the same mesh, moved rigidly); the
    surface point above a given press point as meshed turns with it."""
    mesh, _, _ = make_object("box:0.04x0.04x0.03", 0.008)
    material = Material(2e5, 0.3, 500.0)
    standing = indentation_test(build_body(mesh, material), depth=0.002, steps=4)
    tilted_mesh = _tilted(mesh, 25.0)
    tilted = indentation_test(build_body(tilted_mesh, material), depth=0.002, steps=4)
    assert not standing.turned and tilted.turned
    np.testing.assert_allclose(tilted.force_N, standing.force_N, rtol=1e-6, atol=1e-9 * standing.peak_force_N)
    # A press point 8 mm off the centre, named on the tilted mesh by the point of its surface above
    # which that spot of the top face lies.
    spot = np.array([0.008, 0.0, 0.03])
    c, s = np.cos(np.radians(25.0)), np.sin(np.radians(25.0))
    above = np.array([spot[0], c * spot[1] - s * spot[2]])
    off = indentation_test(build_body(mesh, material), depth=0.002, steps=4, point=spot[:2])
    moved = indentation_test(build_body(tilted_mesh, material), depth=0.002, steps=4, point=above)
    # The same spot of the block: as far from the centroid (each run's default point).
    np.testing.assert_allclose(moved.point_m - tilted.point_m, off.point_m - standing.point_m, atol=1e-9)
    np.testing.assert_allclose(moved.force_N, off.force_N, rtol=1e-6, atol=1e-9 * off.peak_force_N)


def test_a_settle_without_rest_says_so_not_to_take_smaller_load_steps(monkeypatch):
    """Where the object finds no rest on the table before the fingertip comes, the refusal names the
    settle and its own remedy, not the load steps of a closing the test has not begun."""
    from softgrasp.errors import NotConverged
    from softgrasp.experiments import indentation
    from softgrasp.sim.static import SMALLER_STEPS

    def cycles(*args, **kwargs):
        raise NotConverged("static solve cycles (the same 2 iterates over and over)", SMALLER_STEPS)

    monkeypatch.setattr(indentation, "solve_rest", cycles)
    mesh, _, _ = make_object("ball:0.02")
    with pytest.raises(NotConverged) as err:
        indentation_test(build_body(mesh, Material(5e3, 0.45, 1000.0)), depth=0.002, steps=2)
    text = str(err.value)
    assert "found no rest on the table: static solve cycles" in text
    assert "--mesh-size" in text and SMALLER_STEPS not in text


def test_stiff_object_follows_contact_law():
    """A fingertip 250 times softer than the foam: the contact's compliance dominates (the mesh
    resolves none of the fingertip's) and the force is Hertz's K delta^1.5, K = 4/3 Psi sqrt(R)
    with the pair's effective modulus (Eq. 11-12), with the travel since first contact as delta
    (patch rule, flat top)."""
    mesh, mat, mass = make_object("cube", 0.0125)
    body = build_body(mesh, mat, mass=mass)
    res = indentation_test(body, depth=0.002, steps=8, fingertip_E=2e4, fingertip_nu=0.3)
    psi = 1.0 / ((1 - 0.3**2) / 2e4 + (1 - mat.nu**2) / mat.E)
    assert res.K_N_m1_5 == pytest.approx(4.0 / 3.0 * psi * np.sqrt(0.008))
    p, F = res.penetration_m[1:], res.force_N[1:]
    np.testing.assert_allclose(F, res.K_N_m1_5 * p**1.5, rtol=0.02)
    assert np.polyfit(np.log(p), np.log(F), 1)[0] == pytest.approx(1.5, abs=0.03)
    # ... whereas the rigid fingertip on the same foam is far stiffer than the contact law alone
    # would make a soft fingertip, and part of its travel is the foam's own deformation.
    rigid = indentation_test(body, depth=0.002, steps=4)
    assert rigid.contact_depth_m[-1] < 0.9 * rigid.penetration_m[-1]


def test_data_overlay_recovers_zero_and_known_offset(fast_run, tmp_path, capsys):
    sim = _rows(fast_run / "indent.csv")
    own = tmp_path / "own.csv"
    own.write_text("penetration_m,force_N\n" + "".join(f"{r['penetration_m']},{r['force_N']}\n" for r in sim))
    out = tmp_path / "a"
    assert _main(["indent", *FAST, "--data", str(own), "--out", str(out)], capsys)[0] == 0
    data = json.loads((out / "indent.json").read_text())
    assert data["measured_points"] == len(sim)
    assert data["mean_abs_error_N"] == pytest.approx(0.0, abs=1e-6)

    shifted = tmp_path / "shifted.csv"  # in mm this time, and +0.1 N on every force
    shifted.write_text(
        "penetration_mm,force_N\n"
        + "".join(f"{float(r['penetration_m']) * 1e3!r},{float(r['force_N']) + 0.1!r}\n" for r in sim[1:])
    )
    out = tmp_path / "b"
    assert _main(["indent", *FAST, "--data", str(shifted), "--out", str(out)], capsys)[0] == 0
    data = json.loads((out / "indent.json").read_text())
    assert data["measured_points"] == len(sim) - 1
    assert data["mean_abs_error_N"] == pytest.approx(0.1, abs=1e-6)
    assert (out / "indent.png").stat().st_size > 0


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        (None, "does not exist"),
        ("", "is empty"),
        ("pen,force\n0.001,1\n0.002,2\n", "must name the columns penetration_m"),
        ("penetration_m,force_N\n0.001,1\n0.0015,abc\n", "line 3: force_N = 'abc' is not a finite number"),
        ("penetration_m,force_N\n0.001,nan\n0.0015,1\n", "line 2: force_N = 'nan'"),
        ("penetration_m,force_N\n0.001,1\n0.0015\n", "line 3: expected 2 values"),
        ("penetration_m,force_N\n0.001,1\n", "at least 2 are needed"),
        ("penetration_mm,force_N\n1,1\n3,2\n", "line 3: penetration 3 mm is outside the simulated range"),
        ("penetration_m,force_N\n-0.001,1\n0.001,2\n", "line 2: penetration -1 mm is outside"),
        (b"\xff\xfe\x00\x81 not text", "is not a UTF-8 text"),
    ],
)
def test_bad_data_file_one_line_exit_2(tmp_path, capsys, content, needle):
    f = tmp_path / "measured.csv"
    if isinstance(content, bytes):
        f.write_bytes(content)
    elif content is not None:
        f.write_text(content)
    out = tmp_path / "out"
    rc, err = _main(["indent", *FAST, "--data", str(f), "--out", str(out)], capsys)
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("softgrasp: error:") and needle in lines[0]
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--depth", "0.05"], "smaller than the object's height 50 mm"),
        (["--depth", "0"], "--depth must be a number in [1e-06, 0.1] m, got 0 m"),
        (["--radius", "-0.008"], "--radius must be a number in [0.0005, 0.1] m"),
        (["--speed", "fast"], "--speed must be a number"),
        (["--steps", "0"], "--steps must be an integer from 1"),
        (["--steps", "2.5"], "--steps must be an integer from 1 to 100000, got '2.5'"),
        (["--mu", "-0.1"], "--mu must be a number in [0, 5], got -0.1"),
        (["--rule", "average"], "invalid choice: 'average'"),
        (["--object", "teapot"], "unknown object 'teapot'"),
    ],
)
def test_bad_options_one_line_exit_2(tmp_path, capsys, args, needle):
    out = tmp_path / "out"
    rc, err = _main(["indent", "--mesh-size", "0.0125", *args, "--out", str(out)], capsys)
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("softgrasp: error:") and needle in lines[0]
    assert not out.exists()


def test_bad_option_from_the_shell_has_no_traceback(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "softgrasp.cli",
            "indent",
            "--data",
            str(tmp_path / "x.csv"),
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.startswith("softgrasp: error:") and len(proc.stderr.strip().splitlines()) == 1
    assert "Traceback" not in proc.stderr and not out.exists()


def test_read_force_curve_converts_mm(tmp_path):
    f = tmp_path / "m.csv"
    f.write_text("# Fig. 11, digitised\nforce_N,penetration_mm,note\n0.5,1,a\n\n1.5,2.5,b\n")
    p, F = read_force_curve(f, max_penetration=0.005)
    np.testing.assert_allclose(p, [0.001, 0.0025])
    np.testing.assert_allclose(F, [0.5, 1.5])


@pytest.mark.parametrize(
    ("kw", "needle"),
    [
        ({"depth": 0.0}, "depth = 0.0 is invalid"),
        ({"depth": 0.05}, "smaller than the object's height"),
        ({"radius": -0.001}, "radius = -0.001 is invalid"),
        ({"speed": float("nan")}, "speed = nan is invalid"),
        ({"steps": 0}, "steps = 0 is invalid"),
        ({"table_mu": -1.0}, "table friction = -1.0 is invalid"),
        ({"point": (0.1, 0.0)}, "is not above the object"),
        ({"point": (0.0,)}, "two finite numbers"),
    ],
)
def test_library_rejects_bad_parameters(kw, needle):
    mesh, mat, mass = make_object("cube", 0.025)
    body = build_body(mesh, mat, mass=mass)
    with pytest.raises(ConfigError, match=re.escape(needle)):
        indentation_test(body, **kw)
