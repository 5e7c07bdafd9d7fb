"""MuJoCo one-fingertip indentation scene (softgrasp.execution.mujoco.indent).

The MuJoCo peer of softgrasp's indentation experiment (benchmarks/bench_indent.py): the rubber
sphere (388 nodes) on the table, a rigid 8 mm fingertip on servo slides pressed 3 mm into its top.
Checks: the scene has the grasp scene's options and object, bad specs are refused, the force is
Hertz's within the coarse mesh's known stiffening, and the forces balance (Newton's third law
between the fingertip and its servo, and the object's equilibrium on the table).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from softgrasp.errors import ConfigError, MaterialError
from softgrasp.execution.mujoco.indent import (
    INDENT_TIP,
    TIP_KP,
    IndentSpec,
    build_indent_mjcf,
    load_indent_scene,
)
from softgrasp.execution.mujoco.options import OBJECT_NAME, SOLVER
from softgrasp.model.objects import SPHERE_RADIUS, make_object
from softgrasp.physics.body import STANDARD_GRAVITY

RADIUS = 0.008


@pytest.fixture(scope="module")
def sphere() -> tuple:
    mesh, material, mass = make_object("sphere")
    assert mass is not None
    return mesh, material, mass


def spec_of(sphere: tuple, **kw) -> IndentSpec:
    mesh, material, mass = sphere
    top = float(mesh.points[:, 2].max())
    args = dict(
        points=mesh.points,
        tets=mesh.tets,
        mass=mass,
        young=material.E,
        poisson=material.nu,
        radius=RADIUS,
        tip_start=np.array([0.0, 0.0, top + RADIUS + 0.005]),
    )
    return IndentSpec(**{**args, **kw})


def test_mjcf_content_and_validation(sphere: tuple) -> None:
    root = ET.fromstring(build_indent_mjcf(spec_of(sphere)))
    opt = root.find("option")
    assert opt is not None and opt.get("integrator") == "discrete" and opt.get("solver") == SOLVER
    flex = root.find("worldbody/flexcomp")
    assert flex is not None and flex.get("name") == OBJECT_NAME and flex.get("dim") == "3"
    tip = root.find(f"worldbody/body[@name='{INDENT_TIP}']")
    assert tip is not None and len(tip.findall("joint")) == 3
    assert root.find("worldbody/geom[@name='table']") is not None
    assert len(root.findall("actuator/position")) == 3
    with pytest.raises(ConfigError, match="inside the object"):
        spec_of(sphere, tip_start=np.array([0.0, 0.0, 0.064]))
    with pytest.raises(ConfigError, match="fingertip radius"):
        spec_of(sphere, radius=0.0)
    with pytest.raises(MaterialError):
        spec_of(sphere, poisson=0.5)


def test_indentation_force_hertz_and_balance(sphere: tuple) -> None:
    """3 mm into the top (over the sphere's centre, on a facet) at 10 mm/s, then 0.1 s still.

    Hertz for the rigid fingertip on the sphere, R_eff = (1/64 + 1/8)^-1 mm, E* = E / (1 - nu^2):
    1.84 N at 3 mm. The 388-node flex is stiffer: its 16 mm linear tets, larger than the contact,
    lock at nu = 0.45 (ratio 1.6 on the top node, ~2 on a facet: tests/test_mujoco_scene.py);
    allowed 0.7-3.
    """
    mesh, material, mass = sphere
    scene = load_indent_scene(spec_of(sphere))
    dt = scene.model.opt.timestep
    scene.step(round(0.2 / dt))
    np.testing.assert_array_equal(scene.fingertip_force(), 0.0)
    x = scene.object_nodes()
    start = np.array([*x[:, :2].mean(axis=0), x[:, 2].max() + RADIUS + 0.5e-3])
    scene.place(start)
    k = 0
    while not np.any(scene.fingertip_force()):
        k += 1
        assert k * dt * 0.01 < 0.003, "no contact"
        scene.command(start - [0.0, 0.0, 0.01 * k * dt])
        scene.step()
    z_first = scene.tip_position()[2]
    target = start - [0.0, 0.0, 0.01 * k * dt + 0.003]
    for j in range(1, round(0.3 / dt) + 1):
        scene.command(start - [0.0, 0.0, 0.01 * (k + j) * dt])
        scene.step()
    scene.command(target)
    scene.step(round(0.1 / dt))
    scene.forward()
    depth = z_first - scene.tip_position()[2]
    F = scene.fingertip_force()
    assert all(w.number == 0 for w in scene.data.warning)
    assert depth == pytest.approx(0.003, abs=1e-4)
    E_star = material.E / (1.0 - material.nu**2)
    R_eff = 1.0 / (1.0 / SPHERE_RADIUS + 1.0 / RADIUS)
    hertz = 4.0 / 3.0 * E_star * math.sqrt(R_eff) * depth**1.5
    ratio = -F[2] / hertz
    print(f"\nF(3 mm) = {-F[2]:.3f} N, Hertz {hertz:.3f} N, ratio {ratio:.2f}")
    assert 0.7 < ratio < 3.0
    # Newton's third law through the servo: the carriage is at rest (and gravity-compensated), so
    # its z servo pushes down with exactly the force the object pushes it up with
    act = scene.model.actuator(f"{INDENT_TIP}_z_servo").id
    servo = float(scene.data.actuator_force[act])
    assert servo == pytest.approx(F[2], rel=0.02)
    assert servo == pytest.approx(
        TIP_KP * (scene.data.ctrl[act] - scene.data.qpos[scene.model.joint(f"{INDENT_TIP}_z").qposadr[0]]),
        rel=1e-6,
    )
    # the object's equilibrium: table + fingertip + weight = 0
    total = scene.table_force() + F + [0.0, 0.0, -mass * STANDARD_GRAVITY]
    assert np.linalg.norm(total) < 0.02 * np.linalg.norm(F)
