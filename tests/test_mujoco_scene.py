"""MuJoCo scene of a grasp (softgrasp.execution.mujoco): MJCF building, the soft object as a flex, the hand.

Physical checks on softgrasp's rubber sphere (radius 64 mm, 50 g, E = 79.3 kPa, nu = 0.45, 388
nodes): the flex elasticity equals linear elasticity for affine strains, the sphere settles on
the table with a reaction of m g, a fingertip pressed into it gives a force close to Hertz's, the
contact forces obey Newton's third law, and the hand's MuJoCo kinematics equal softgrasp's FK.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
import pytest

import softgrasp
from softgrasp.errors import ConfigError, MaterialError, MeshError
from softgrasp.execution.mujoco.mjcf import build_mjcf
from softgrasp.execution.mujoco.options import DEFAULT_TIMESTEP
from softgrasp.execution.mujoco.scene import MUJOCO_MISSING, MujocoScene, load_scene
from softgrasp.execution.mujoco.spec import SceneSpec
from softgrasp.hand.kinematics import HandModel
from softgrasp.model.mesh.tetmesh import signed_volumes
from softgrasp.model.objects import SPHERE_RADIUS, make_object
from softgrasp.physics.body import STANDARD_GRAVITY

HAND = HandModel.default()
FINGERS = ("thumb", "first", "middle")
TIP_RADIUS = 0.008
#: Palm frame -> world rotation that points the straight fingers (palm +y) down (world -z).
FINGERS_DOWN = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def pose(R: np.ndarray, p: np.ndarray | list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def no_warnings(scene: MujocoScene) -> bool:
    return all(w.number == 0 for w in scene.data.warning)


@pytest.fixture(scope="module")
def sphere() -> tuple:
    mesh, material, mass = make_object("sphere")
    assert mass is not None
    return mesh, material, mass


def sphere_spec(sphere: tuple, palm_pose: np.ndarray, q0: dict | None = None, **kw) -> SceneSpec:
    mesh, material, mass = sphere
    args = dict(
        hand=HAND,
        palm_pose=palm_pose,
        q0=q0 or {},
        points=mesh.points,
        tets=mesh.tets,
        mass=mass,
        young=material.E,
        poisson=material.nu,
        mu=0.8,
        table_z=0.0,
    )
    return SceneSpec(**{**args, **kw})


def pebble_spec(palm_pose: np.ndarray, q0: dict | None = None) -> SceneSpec:
    """The hand with a 2 cm tetrahedron far away: hand-only tests at almost no cost."""
    p = np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, 0.02, 0.0], [0.0, 0.0, 0.02]]) + [0.4, 0.4, 0.0]
    return SceneSpec(
        hand=HAND,
        palm_pose=palm_pose,
        q0=q0 or {},
        points=p,
        tets=np.array([[0, 1, 2, 3]]),
        mass=0.01,
        young=1e5,
        poisson=0.3,
        mu=0.8,
        table_z=0.0,
    )


ABOVE = pose(np.eye(3), [0.0, -0.1, 0.3])  # palm 0.3 m above the table, fingers clear of the object


# ---------------------------------------------------------------------- builder and spec


def test_import_and_build_without_mujoco() -> None:
    """The module and build_mjcf work without MuJoCo; load_scene names the missing dependency."""
    code = (
        "import sys\n"
        "sys.modules['mujoco'] = None\n"
        "import numpy as np\n"
        "from softgrasp.errors import ConfigError\n"
        "from softgrasp.execution.mujoco import mjcf, scene, spec as sp\n"
        "from softgrasp.hand.kinematics import HandModel\n"
        "p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * 0.02\n"
        "spec = sp.SceneSpec(HandModel.default(), np.eye(4), {}, p, np.array([[0, 1, 2, 3]]),\n"
        "                      0.01, 1e5, 0.3, 0.8, 0.0)\n"
        "assert '<flexcomp' in mjcf.build_mjcf(spec)\n"
        "try:\n"
        "    scene.load_scene(spec)\n"
        "except ConfigError as exc:\n"
        "    print(exc)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(Path(softgrasp.__file__).parents[1]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == MUJOCO_MISSING


def test_missing_mujoco_message(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "mujoco", None)
    with pytest.raises(ConfigError) as info:
        load_scene(pebble_spec(ABOVE))
    assert str(info.value) == (
        "MuJoCo is not installed (softgrasp's 'execute' extra): pip install 'softgrasp[execute]'"
    )


def test_spec_validation(sphere: tuple) -> None:
    lo, hi = HAND.limits("first")
    with pytest.raises(ConfigError, match="rigid transform"):
        sphere_spec(sphere, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ConfigError, match="unknown finger 'ring'"):
        sphere_spec(sphere, ABOVE, {"ring": [0.0, 0.0, 0.0]})
    with pytest.raises(ConfigError, match="outside the finger's joint limits"):
        sphere_spec(sphere, ABOVE, {"first": hi + 0.1})
    with pytest.raises(ConfigError, match="3 finite values"):
        sphere_spec(sphere, ABOVE, {"first": [0.0, 0.0]})
    with pytest.raises(ConfigError, match="below the table top"):
        sphere_spec(sphere, ABOVE, table_z=0.01)
    with pytest.raises(MaterialError, match="Poisson"):
        spec = pebble_spec(ABOVE)
        SceneSpec(spec.hand, ABOVE, {}, spec.points, spec.tets, 0.01, 1e5, -0.1, 0.8, 0.0)
    with pytest.raises(MeshError, match="outside"):
        spec = pebble_spec(ABOVE)
        SceneSpec(spec.hand, ABOVE, {}, spec.points, np.array([[0, 1, 2, 4]]), 0.01, 1e5, 0.3, 0.8, 0.0)
    with pytest.raises(ConfigError, match="timestep"):
        sphere_spec(sphere, ABOVE, timestep=0.0)
    spec = sphere_spec(sphere, ABOVE, {"first": lo})
    np.testing.assert_array_equal(spec.q0["first"], lo)
    np.testing.assert_array_equal(spec.q0["thumb"], np.clip(np.zeros(5), *HAND.limits("thumb")))
    assert spec.timestep == DEFAULT_TIMESTEP


def test_mjcf_content(sphere: tuple) -> None:
    spec = sphere_spec(sphere, ABOVE, mu=0.7, table_mu=0.4)
    root = ET.fromstring(build_mjcf(spec))
    flex = root.find(".//flexcomp")
    assert flex is not None and flex.get("type") == "direct" and flex.get("dim") == "3"
    assert len(flex.get("point", "").split()) == 3 * spec.points.shape[0]
    assert len(flex.get("element", "").split()) == 4 * spec.tets.shape[0]
    contact = flex.find("contact")
    assert contact is not None and contact.get("selfcollide") == "none" and contact.get("priority") == "0"
    elasticity = flex.find("elasticity")
    assert elasticity is not None and float(elasticity.get("young", "0")) == spec.young
    table = root.find(".//geom[@name='table']")
    assert table is not None and table.get("priority") == "1" and table.get("friction", "").startswith("0.4 ")
    tips = [g for g in root.iter("geom") if g.get("name", "").endswith("_tip_sphere")]
    assert len(tips) == 3
    assert all(g.get("priority") == "1" and g.get("friction", "").startswith("0.7 ") for g in tips)
    # only the fingertips and the table collide among the geoms
    colliding = {g.get("name") for g in root.iter("geom") if g.get("contype", "1") != "0"}
    assert colliding == {"table", *(g.get("name") for g in tips)}
    mimic = {
        e.get("joint1"): (e.get("joint2"), e.get("polycoef")) for e in root.iter("joint") if e.get("joint1")
    }
    assert mimic == {"FFJ1": ("FFJ2", "0 1 0 0 0"), "MFJ1": ("MFJ2", "0 1 0 0 0")}
    actuators = root.find("actuator")
    assert actuators is not None
    servos = [a.get("joint") for a in actuators]
    assert servos == ["arm_x", "arm_y", "arm_z"] + [n for f in HAND.fingers for n in HAND.joint_names(f)]
    # The palm rides on an arm of three world-axis slides (a dynamic body, not a mocap teleport).
    arm = root.find(".//body[@name='arm']")
    assert [j.get("type") for j in arm.findall("joint")] == ["slide"] * 3
    assert arm.find("body").get("name") == "palm" and arm.find("body").get("mocap") is None


def test_friction_impedance_grows_with_the_cube_root_of_the_node_count(sphere: tuple) -> None:
    """MuJoCo's friction creep under a held weight goes as N / (n_c impratio) (N vertices, n_c ~
    N^(2/3) contact rows in a patch): the scene's impratio is 3 on the default 388-node sphere and
    grows as N^(1/3), so that refining the mesh does not loosen MuJoCo's friction."""
    from softgrasp.execution.mujoco.options import IMPRATIO, IMPRATIO_NODES, impratio

    assert sphere[0].n_nodes == IMPRATIO_NODES and impratio(IMPRATIO_NODES) == IMPRATIO == 3.0
    assert impratio(8 * IMPRATIO_NODES) == pytest.approx(2.0 * IMPRATIO, rel=1e-12)
    assert impratio(IMPRATIO_NODES // 8) < IMPRATIO
    for spec in (sphere_spec(sphere, ABOVE), pebble_spec(ABOVE)):
        option = ET.fromstring(build_mjcf(spec)).find("option")
        assert option is not None
        assert float(option.get("impratio", "nan")) == pytest.approx(impratio(len(spec.points)), rel=1e-6)


# ---------------------------------------------------------------------- compiled scene


def test_scene_indices_masses_and_vertex_order(sphere: tuple) -> None:
    q0 = {"first": [0.1, 0.3, 0.4], "middle": [-0.1, 0.2, 0.5], "thumb": [0.2, 0.3, 0.1, 0.1, 0.2]}
    scene = load_scene(sphere_spec(sphere, ABOVE, q0))
    m, d = scene.model, scene.data
    assert scene.fingers == tuple(HAND.fingers)
    # flex vertex masses: mass / N each, summing to the object's mass
    masses = scene.object_mass()
    assert masses.shape == (sphere[0].n_nodes,)
    assert masses.sum() == pytest.approx(sphere[2], rel=1e-12)
    np.testing.assert_allclose(masses, sphere[2] / sphere[0].n_nodes, rtol=1e-12)
    # MuJoCo keeps the order of `points`
    np.testing.assert_allclose(scene.object_nodes(), sphere[0].points, atol=1e-12)
    np.testing.assert_allclose(scene.object_com(), sphere[0].points.mean(axis=0), atol=1e-12)
    for finger in FINGERS:
        names = HAND.joint_names(finger)
        qadr = scene.joint_qpos_index(finger)
        assert [m.joint(int(np.flatnonzero(m.jnt_qposadr == a)[0])).name for a in qadr] == list(names)
        np.testing.assert_allclose(d.qpos[qadr], q0[finger], atol=1e-12)
        act = scene.actuator_index(finger)
        assert [m.actuator(int(a)).name for a in act] == [f"{n}_servo" for n in names]
        np.testing.assert_allclose(d.ctrl[act], q0[finger], atol=1e-12)
    # the mimic joints start coupled
    j1, j2 = (m.jnt_qposadr[m.joint(n).id] for n in ("FFJ1", "FFJ2"))
    assert d.qpos[j1] == pytest.approx(d.qpos[j2])
    with pytest.raises(ConfigError, match="unknown finger"):
        scene.fingertip_force("ring")


def test_flex_elasticity_equals_linear_elasticity(sphere: tuple) -> None:
    """Patch test: MuJoCo's flex energy of an affine strain equals V (mu tr e^2 + lambda/2 tr(e)^2)."""
    mesh, material, _ = sphere
    scene = load_scene(sphere_spec(sphere, ABOVE))
    m, d = scene.model, scene.data
    verts = m.flex_vertbodyid[m.flex_vertadr[0] : m.flex_vertadr[0] + m.flex_vertnum[0]]
    qadr = m.jnt_qposadr[m.body_jntadr[verts]]
    dadr = m.body_dofadr[verts]
    V = float(signed_volumes(mesh.points, mesh.tets).sum())
    mu, lam = material.shear_modulus, material.lame_lambda
    eps = 1e-5
    for G in (np.diag([0.0, 0.0, eps]), np.eye(3) * eps, np.array([[0.0, eps, 0], [0, 0, 0], [0, 0, 0]])):
        u = (mesh.points - mesh.points.mean(axis=0)) @ G.T
        mujoco.mj_resetDataKeyframe(m, d, 0)
        for k in range(3):
            d.qpos[qadr + k] = u[:, k]
        mujoco.mj_forward(m, d)
        f = np.stack([d.qfrc_passive[dadr + k] for k in range(3)], axis=1)
        S = 0.5 * (G + G.T)
        expected = V * (mu * np.sum(S * S) + 0.5 * lam * np.trace(S) ** 2)
        assert -0.5 * np.sum(f * u) == pytest.approx(expected, rel=1e-3)


def test_object_settles_on_table(sphere: tuple) -> None:
    """After 1 s the table carries m g (2 %), the sphere stays put, nothing blows up."""
    mesh, _, mass = sphere
    scene = load_scene(sphere_spec(sphere, ABOVE))
    com0 = scene.object_com()
    steps = round(1.0 / scene.model.opt.timestep)
    t0 = time.perf_counter()
    scene.step(steps)
    wall = time.perf_counter() - t0
    print(f"\n{mesh.n_nodes} nodes with the hand: {wall:.2f} s wall per simulated second")
    assert no_warnings(scene)
    assert np.all(np.isfinite(scene.data.qpos))
    F = scene.table_force()
    assert F[2] == pytest.approx(mass * STANDARD_GRAVITY, rel=0.02)
    assert np.hypot(F[0], F[1]) < 0.02 * mass * STANDARD_GRAVITY
    drift = scene.object_com() - com0
    assert np.hypot(drift[0], drift[1]) < 1e-3
    assert -1e-3 < drift[2] < 0.0  # sags a little under its weight
    nodes = scene.object_nodes()
    assert np.abs(nodes - mesh.points).max() < 2e-3  # still the same vertex order
    assert nodes[:, 2].min() > -5e-4  # on, not through, the table
    for finger in FINGERS:
        np.testing.assert_array_equal(scene.fingertip_force(finger), 0.0)
    assert scene.steps == steps
    assert scene.solver_capped_share < 0.01  # its contact forces resolved to the solver's tolerance


def test_steps_whose_constraint_solve_stops_at_the_iteration_cap_are_counted(sphere: tuple) -> None:
    """With MuJoCo's constraint solvers allowed one iteration and no tolerance to stop at, every
    CG step of the sphere settling on the table stops at the cap: each is taken again with
    Newton's solver, and while CG keeps stopping at its cap every step goes to Newton
    (:attr:`newton_share`). The steps whose solve stopped at the cap even so are counted one by
    one (:attr:`solver_capped_share`), also when several are taken at once, and the scene's own
    solver is back after each. With the scene's own options no step needs Newton or is capped."""
    scene = load_scene(sphere_spec(sphere, ABOVE))
    scene.step(50)
    assert scene.steps == 50 and scene.capped_steps == 0 and scene.newton_steps == 0
    scene.model.opt.iterations = 1
    scene.model.opt.tolerance = 0.0
    scene.step(100)
    assert scene.newton_steps == 100
    for _ in range(100):
        before = scene.capped_steps
        scene.step()
        assert scene.capped_steps - before == int(scene.data.solver_niter[0] >= 1)
        assert int(scene.model.opt.solver) == int(mujoco.mjtSolver.mjSOL_CG)
    assert scene.steps == 250 and scene.newton_steps == 200
    assert scene.newton_share == pytest.approx(0.8)
    assert scene.capped_steps > 50
    assert scene.solver_capped_share == pytest.approx(scene.capped_steps / 250)


def test_fingertip_indentation_hertz_and_third_law(sphere: tuple) -> None:
    """The first finger, pointing down, pressed 3 mm into the top node of the sphere.

    Hertz (rigid fingertip, R_eff = (1/0.064 + 1/0.008)^-1, E* = E / (1 - nu^2)): F(3 mm) = 1.84 N.
    MuJoCo on the 388-node mesh: 2.94 N (ratio 1.60; 1.09 with 2196 nodes): the coarse mesh
    (16 mm elements under an 8 mm fingertip) is stiffer than the continuum.
    """
    mesh, material, mass = sphere
    top = mesh.points[np.argmax(mesh.points[:, 2])]
    q0 = {"first": np.zeros(3), "middle": np.array([0.0, 1.5, 1.5]), "thumb": np.zeros(5)}
    tip0 = HAND.forward("first", q0["first"])
    T0 = pose(FINGERS_DOWN, top + [0.0, 0.0, TIP_RADIUS + 0.001] - FINGERS_DOWN @ tip0)
    scene = load_scene(sphere_spec(sphere, T0, q0))
    m, d = scene.model, scene.data
    dt = m.opt.timestep
    scene.step(round(0.2 / dt))  # settle on the table
    np.testing.assert_array_equal(scene.fingertip_force("first"), 0.0)
    # approach at 10 mm/s until the first contact force
    z = 0.0
    while not scene.fingertip_force("first")[2] < 0.0:
        z += 0.01 * dt
        assert z < 0.005, "no contact"
        scene.set_palm(pose(FINGERS_DOWN, T0[:3, 3] - [0.0, 0.0, z]))
        scene.step()
    z_contact = scene.fingertip_position("first")[2]
    depth, force = [], []
    for target in np.linspace(0.5e-3, 3e-3, 6):
        scene.set_palm(pose(FINGERS_DOWN, T0[:3, 3] - [0.0, 0.0, z + target]))
        scene.step(round(0.15 / dt))
        depth.append(z_contact - scene.fingertip_position("first")[2])
        force.append(-scene.fingertip_force("first")[2])
    depth_a, force_a = np.array(depth), np.array(force)
    assert no_warnings(scene)
    np.testing.assert_allclose(depth_a, np.linspace(0.5e-3, 3e-3, 6), atol=1e-4)  # the finger barely yields
    assert np.all(force_a > 0.0) and np.all(np.diff(force_a) > 0.0)
    E_star = material.E / (1.0 - material.nu**2)
    R_eff = 1.0 / (1.0 / SPHERE_RADIUS + 1.0 / TIP_RADIUS)
    hertz = 4.0 / 3.0 * E_star * np.sqrt(R_eff) * depth_a[-1] ** 1.5
    ratio = force_a[-1] / hertz
    print(f"\nF(3 mm) = {force_a[-1]:.3f} N, Hertz {hertz:.3f} N, ratio {ratio:.2f}")
    assert 0.5 < ratio < 2.2

    # Newton's third law, checked on MuJoCo's own constraint forces: J' f of the fingertip's contact
    # rows is, on the object's vertex dofs (world-axis slides), the force on the object, and on the
    # finger's dofs the generalized force of minus that force at the contact points
    F_obj = scene.fingertip_force("first")
    assert F_obj[2] < 0.0  # the fingertip pushes the object down
    verts = m.flex_vertbodyid[m.flex_vertadr[0] : m.flex_vertadr[0] + m.flex_vertnum[0]]
    vdof = m.body_dofadr[verts]
    assert [tuple(m.jnt_axis[m.dof_jntid[vdof[0] + k]]) for k in range(3)] == [
        (1, 0, 0),
        (0, 1, 0),
        (0, 0, 1),
    ]
    body = m.geom_bodyid[scene.tip_geom("first")]
    finger_dofs = [m.jnt_dofadr[m.joint(n).id] for n in ("FFJ4", "FFJ3", "FFJ2", "FFJ1")]
    F_sum = np.zeros(3)
    for i in range(d.ncon):
        c = d.contact[i]
        if scene.tip_geom("first") not in c.geom or c.efc_address < 0:
            continue
        rows = slice(c.efc_address, c.efc_address + c.dim)  # elliptic cones: one row per dimension
        f = np.zeros(d.nefc)
        f[rows] = d.efc_force[rows]
        q = np.zeros(m.nv)
        mujoco.mj_mulJacTVec(m, d, q, f)
        F_k = np.array([q[vdof + k].sum() for k in range(3)])
        jacp = np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jacp, None, c.pos, body)
        np.testing.assert_allclose(q[finger_dofs], jacp[:, finger_dofs].T @ -F_k, atol=1e-9)
        F_sum += F_k
    np.testing.assert_allclose(F_sum, F_obj, atol=1e-9 + 1e-9 * np.linalg.norm(F_obj))
    # priorities: fingertip-object contacts use mu, table-object contacts table_mu
    table = m.geom("table").id
    kinds = set()
    for i in range(d.ncon):
        c = d.contact[i]
        if scene.tip_geom("first") in c.geom:
            kinds.add("tip")
            assert c.friction[0] == pytest.approx(0.8) and c.dim == 3
        elif table in c.geom:
            kinds.add("table")
            assert c.friction[0] == pytest.approx(0.5) and c.dim == 3
    assert kinds == {"tip", "table"}
    # the object is in equilibrium: table + fingertip + weight = 0
    total = scene.table_force() + F_obj + [0.0, 0.0, -mass * STANDARD_GRAVITY]
    assert np.linalg.norm(total) < 0.02 * np.linalg.norm(F_obj)


# ---------------------------------------------------------------------- hand


def finger_q(finger: str, q: np.ndarray) -> dict[str, float]:
    chain = HAND.chain(finger)
    return {
        j.name: g * q[k] + b
        for j, k, g, b in zip(
            chain.joints, chain.drive_index, chain.drive_gain, chain.drive_offset, strict=True
        )
        if k >= 0
    }


def test_hand_kinematics_equal_urdf_fk() -> None:
    T = pose(FINGERS_DOWN, [0.05, -0.02, 0.35])
    scene = load_scene(pebble_spec(T))
    m, d = scene.model, scene.data
    rng = np.random.default_rng(1)
    for _ in range(5):
        for finger in FINGERS:
            lo, hi = HAND.limits(finger)
            q = rng.uniform(lo, hi)
            for name, value in finger_q(finger, q).items():
                d.qpos[m.jnt_qposadr[m.joint(name).id]] = value
            mujoco.mj_kinematics(m, d)
            expected = T[:3, :3] @ HAND.forward(finger, q) + T[:3, 3]
            np.testing.assert_allclose(scene.fingertip_position(finger), expected, atol=1e-9)


def test_servos_track_and_mimic_coupling_holds() -> None:
    scene = load_scene(pebble_spec(ABOVE))
    m, d = scene.model, scene.data
    rng = np.random.default_rng(2)
    targets = {f: rng.uniform(*HAND.limits(f)) for f in FINGERS}
    for finger, q in targets.items():
        d.ctrl[scene.actuator_index(finger)] = q
    scene.step(round(0.5 / m.opt.timestep))
    assert no_warnings(scene)
    for finger, q in targets.items():
        q_now = d.qpos[scene.joint_qpos_index(finger)]
        np.testing.assert_allclose(q_now, q, atol=2e-3)
        mujoco.mj_kinematics(m, d)
        tip = ABOVE[:3, :3] @ HAND.forward(finger, q_now) + ABOVE[:3, 3]
        np.testing.assert_allclose(scene.fingertip_position(finger), tip, atol=5e-4)
    for j1, j2 in (("FFJ1", "FFJ2"), ("MFJ1", "MFJ2")):
        a1, a2 = (d.qpos[m.jnt_qposadr[m.joint(n).id]] for n in (j1, j2))
        assert abs(a1 - a2) < 1e-3


def test_servos_stiff_under_fingertip_load() -> None:
    """3 N on a straight, horizontal first finger moves its tip by less than 0.5 mm."""
    scene = load_scene(pebble_spec(ABOVE))
    m, d = scene.model, scene.data
    body = m.geom_bodyid[scene.tip_geom("first")]
    scene.step(round(0.1 / m.opt.timestep))
    before = scene.fingertip_position("first")
    d.xfrc_applied[body, :3] = [0.0, 0.0, -3.0]
    scene.step(round(0.3 / m.opt.timestep))
    moved = np.linalg.norm(scene.fingertip_position("first") - before)
    assert 1e-6 < moved < 5e-4
    a1, a2 = (d.qpos[m.jnt_qposadr[m.joint(n).id]] for n in ("FFJ1", "FFJ2"))
    assert abs(a1 - a2) < 1e-3


def test_set_palm_moves_the_hand_and_the_arm_servos_carry_it() -> None:
    scene = load_scene(pebble_spec(ABOVE))
    T = pose(np.eye(3), [0.1, 0.0, 0.4])
    scene.set_palm(T)
    q = scene.data.qpos[scene.joint_qpos_index("first")]
    expected = T[:3, :3] @ HAND.forward("first", q) + T[:3, 3]
    np.testing.assert_allclose(scene.fingertip_position("first"), expected, atol=1e-9)
    scene.step(10)
    assert np.linalg.norm(scene.fingertip_position("first") - expected) < 1e-3
    # Commanded, the arm's servos take the palm 5 cm up over a few tenths of a second.
    scene.command_palm(T[:3, 3] - ABOVE[:3, 3] + [0.0, 0.0, 0.05])
    scene.step(round(0.5 / scene.model.opt.timestep))
    np.testing.assert_allclose(scene.palm_pose()[:3, 3], T[:3, 3] + [0.0, 0.0, 0.05], atol=1e-4)
    with pytest.raises(ConfigError, match="rigid transform"):
        scene.set_palm(np.zeros((4, 4)))
    with pytest.raises(ConfigError, match="only translates"):
        scene.set_palm(pose(FINGERS_DOWN, [0.1, 0.0, 0.4]))
    with pytest.raises(ConfigError, match="integer >= 1"):
        scene.step(0)


@pytest.mark.slow
def test_fine_sphere_is_stable_and_timed() -> None:
    """2196-node sphere with the hand: stable at the default time step; prints the cost."""
    mesh, material, mass = make_object("sphere", 0.008)
    spec = sphere_spec((mesh, material, mass), ABOVE)
    scene = load_scene(spec)
    steps = round(0.2 / scene.model.opt.timestep)
    t0 = time.perf_counter()
    scene.step(steps)
    wall = (time.perf_counter() - t0) / 0.2
    print(f"\n{mesh.n_nodes} nodes with the hand: {wall:.1f} s wall per simulated second")
    assert no_warnings(scene)
    assert np.all(np.isfinite(scene.data.qpos))
    assert scene.table_force()[2] == pytest.approx(mass * STANDARD_GRAVITY, rel=0.05)
