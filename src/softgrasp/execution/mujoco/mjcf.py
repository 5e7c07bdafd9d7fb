"""The MJCF text of a grasp scene: a table, the soft object as a 3-D flex and the hand on an arm.

:func:`build_mjcf` writes the MJCF text of a :class:`~softgrasp.execution.mujoco.spec.SceneSpec`;
it is pure Python (no MuJoCo needed). :func:`softgrasp.execution.mujoco.scene.load_scene`
compiles it. The settings and why they were chosen: :mod:`softgrasp.execution.mujoco.options`.

Scene
-----
* **Table**: a static box geom whose top face is at ``table_z``.
* **Object**: a ``flexcomp`` (:mod:`softgrasp.execution.mujoco.flex`).
* **Arm**: a 1 kg body at the palm's position on three world-axis slide joints, each a stiff
  position servo (:data:`~softgrasp.execution.mujoco.options.ARM_KP`), commanded by
  :meth:`~softgrasp.execution.mujoco.scene.MujocoScene.command_palm` (a real motion, with
  velocity: friction carries a grasped object along). A mocap palm would be teleported with
  zero velocity in the contact solver, so friction would hold the object in place while the
  fingers slid up past it (measured: the sphere stayed on the table at any grip). The hand's
  bodies are gravity-compensated by the arm (``gravcomp``).
* **Hand**: the palm (root link) rides on the arm at ``palm_pose``; below it a body per URDF link
  at its joint ``origin``, a hinge (revolute) or slide (prismatic) joint about the URDF ``axis``
  with the joint's own limits (fixed joints weld), a capsule per link segment and a sphere per
  moving joint for looks (and link inertia; density 1000 kg/m^3, no collisions) and a sphere of
  the finger's radius centred on every fingertip link: the only hand geoms that collide, and only
  with the object. A mimic joint is an equality ``q = offset + multiplier q_mimic``; every
  independent joint has a position servo whose ``ctrl`` is its target [rad or m]. The keyframe
  ``initial`` holds ``q0`` and the servo targets, so the XML alone starts where
  :func:`~softgrasp.execution.mujoco.scene.load_scene` does.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from softgrasp.errors import ConfigError
from softgrasp.execution.mujoco.elements import (
    actuator_name,
    add_table,
    contact_attrs,
    element,
    fnum,
    fvec,
    mujoco_root,
    quaternion,
    tip_geom_name,
)
from softgrasp.execution.mujoco.flex import add_object
from softgrasp.execution.mujoco.options import (
    ARM_DAMPING,
    ARM_JOINTS,
    ARM_KP,
    ARM_MASS,
    ARM_NAME,
    EQUALITY_SOLIMP,
    EQUALITY_SOLREF,
    JOINT_ARMATURE,
    JOINT_DAMPING,
    JOINT_KP,
    LINK_RADIUS,
    OBJECT_BIT,
    TIP_BIT,
    impratio,
)
from softgrasp.execution.mujoco.spec import SceneSpec

__all__ = ["build_mjcf"]


def _add_hand(world: ET.Element, spec: SceneSpec) -> list[tuple[str, float]]:
    """Append the arm, the palm and the finger bodies; return ``(joint, q0 value)`` in qpos order."""
    hand = spec.hand
    chains = list(hand.fingers.values())
    roots = {c.joints[0].parent for c in chains}
    if len(roots) != 1:
        raise ConfigError(f"the fingers do not share one palm link: {sorted(roots)}")
    root = roots.pop()
    radius = min(c.radius for c in chains)
    T = spec.palm_pose
    # The arm: a body at the palm's position on three world-axis slides, each a stiff position
    # servo, carrying the palm at its orientation. (A mocap palm would be moved kinematically, with
    # zero velocity in the contact solver: friction then holds the object where it is instead of
    # carrying it along with the fingers.)
    arm = element(world, "body", name=ARM_NAME, pos=fvec(T[:3, 3]))
    element(arm, "inertial", pos="0 0 0", mass=fnum(ARM_MASS), diaginertia=fvec([1e-3, 1e-3, 1e-3]))
    for axis, name in zip(np.eye(3), ARM_JOINTS, strict=True):
        element(arm, "joint", name=name, type="slide", axis=fvec(axis), damping=fnum(ARM_DAMPING))
    palm = element(arm, "body", name=root, quat=fvec(quaternion(T[:3, :3])))

    # a decorative palm plate under the finger bases (palm frame: z = palm normal)
    bases = np.array([c.joints[0].origin[:3, 3] for c in chains])
    lo = np.minimum(bases.min(axis=0), 0.0) - radius
    hi = np.maximum(bases.max(axis=0), 0.0) + radius
    half = 0.5 * (hi - lo)
    centre = 0.5 * (hi + lo)
    half[2], centre[2] = 1.2 * radius, -1.2 * radius
    element(
        palm,
        "geom",
        name=f"{root}_plate",
        type="box",
        size=fvec(half),
        pos=fvec(centre),
        contype="0",
        conaffinity="0",
        group="1",
        rgba="0.55 0.55 0.6 1",
    )

    values: dict[str, float] = {}
    for finger in hand.fingers:
        values.update(spec.joint_values(finger))
    bodies: dict[str, ET.Element] = {root: palm}
    tip_links = {c.tip_link: c for c in chains}
    for chain in chains:
        for joint in chain.joints:
            if joint.child in bodies:
                continue  # a link shared with a finger already built
            parent = bodies[joint.parent]
            p = joint.origin[:3, 3]
            if joint.parent != root and float(np.linalg.norm(p)) > 1e-9:
                element(
                    parent,
                    "geom",
                    type="capsule",
                    fromto=fvec([0.0, 0.0, 0.0, *p]),
                    size=fnum(LINK_RADIUS * radius),
                    contype="0",
                    conaffinity="0",
                    group="1",
                    rgba="0.8 0.7 0.6 1",
                )
            body = element(
                parent, "body", name=joint.child, pos=fvec(p), quat=fvec(quaternion(joint.origin[:3, :3]))
            )
            bodies[joint.child] = body
            if joint.movable:
                element(
                    body,
                    "joint",
                    name=joint.name,
                    type="hinge" if joint.kind == "revolute" else "slide",
                    axis=fvec(joint.axis),
                    range=fvec([joint.lower, joint.upper]),
                    damping=fnum(JOINT_DAMPING),
                    armature=fnum(JOINT_ARMATURE),
                )
                element(
                    body,
                    "geom",
                    type="sphere",
                    size=fnum(LINK_RADIUS * radius),
                    contype="0",
                    conaffinity="0",
                    group="1",
                    rgba="0.7 0.6 0.5 1",
                )
            if joint.child in tip_links:
                tip = tip_links[joint.child]
                element(
                    body,
                    "geom",
                    name=tip_geom_name(tip.tip_link),
                    type="sphere",
                    size=fnum(tip.radius),
                    contype=str(TIP_BIT),
                    conaffinity=str(OBJECT_BIT),
                    rgba="0.9 0.75 0.6 1",
                    **contact_attrs(spec.mu),
                )
    for body in arm.iter("body"):
        body.set("gravcomp", "1")  # the arm carries the hand's weight (a real arm's controller does)
    values.update(dict.fromkeys(ARM_JOINTS, 0.0))
    # MuJoCo numbers the joints in depth-first (document) order of the body tree
    return [(j.get("name", ""), values[j.get("name", "")]) for j in arm.iter("joint")]


def build_mjcf(spec: SceneSpec) -> str:
    """MJCF text of the scene of ``spec`` (see the module docstring); needs no MuJoCo.

    Names: the flex is :data:`~softgrasp.execution.mujoco.options.OBJECT_NAME`, bodies and joints carry
    their URDF link and joint names, the palm body the root link's name, fingertip spheres ``<tip
    link>_sphere``, servos ``<joint>_servo``; the table geom is ``table``. The keyframe ``initial`` holds
    ``q0`` (mimic joints included) and the servo targets.
    """
    if not isinstance(spec, SceneSpec):
        raise ConfigError(f"build_mjcf needs a SceneSpec, got {type(spec).__name__}")
    pts = spec.points
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = 0.5 * (lo + hi)
    extent = float(np.max(hi - lo))
    palm_xyz = spec.palm_pose[:3, 3]
    reach = max(extent, float(np.linalg.norm(palm_xyz[:2] - centre[:2])) + 0.15, 0.25)

    root = mujoco_root("softgrasp_scene", spec.timestep, impratio(len(pts)))
    visual = element(root, "visual")
    element(visual, "global", offwidth="1280", offheight="960", azimuth="135", elevation="-25")
    element(visual, "headlight", ambient="0.35 0.35 0.35", diffuse="0.5 0.5 0.5", specular="0.1 0.1 0.1")
    element(visual, "quality", shadowsize="4096")
    asset = element(root, "asset")
    element(
        asset,
        "texture",
        name="sky",
        type="skybox",
        builtin="gradient",
        rgb1="0.75 0.8 0.85",
        rgb2="0.2 0.22 0.25",
        width="256",
        height="256",
    )
    element(
        root,
        "statistic",
        center=fvec([centre[0], centre[1], 0.5 * (spec.table_z + palm_xyz[2])]),
        extent=fnum(2.0 * reach),
    )

    world = element(root, "worldbody")
    element(
        world,
        "light",
        name="key",
        pos=fvec(centre + [0.3, -0.3, 1.0]),
        dir=fvec([-0.3, 0.3, -1.0]),
        directional="true",
        castshadow="true",
        diffuse="0.6 0.6 0.6",
    )
    element(
        world,
        "light",
        name="fill",
        pos=fvec(centre + [-0.4, 0.4, 0.8]),
        dir=fvec([0.4, -0.4, -0.8]),
        directional="true",
        castshadow="false",
        diffuse="0.3 0.3 0.3",
    )
    eye = centre + np.array([0.45, -0.45, 0.35]) * max(1.0, extent / 0.13)
    look = centre - eye
    x_axis = np.cross(look, [0.0, 0.0, 1.0])
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(x_axis, look)
    y_axis /= np.linalg.norm(y_axis)
    element(world, "camera", name="overview", pos=fvec(eye), xyaxes=fvec([*x_axis, *y_axis]), fovy="45")
    add_table(world, centre, reach, spec.table_z, spec.table_mu)

    order = _add_hand(world, spec)
    add_object(world, spec)

    equality = element(root, "equality")
    actuator = element(root, "actuator")
    done: set[str] = set()  # joints shared by several fingers get one equality and one servo
    ctrl: list[float] = []
    for name in ARM_JOINTS:
        element(actuator, "position", name=actuator_name(name), joint=name, kp=fnum(ARM_KP))
        ctrl.append(0.0)
    for finger, chain in spec.hand.fingers.items():
        for joint in chain.joints:
            if joint.movable and joint.mimic is not None and joint.name not in done:
                done.add(joint.name)
                element(
                    equality,
                    "joint",
                    name=f"{joint.name}_mimic",
                    joint1=joint.name,
                    joint2=joint.mimic,
                    polycoef=fvec([joint.offset, joint.multiplier, 0.0, 0.0, 0.0]),
                    solref=fvec(EQUALITY_SOLREF),
                    solimp=fvec(EQUALITY_SOLIMP),
                )
        for k, name in enumerate(chain.joint_names):
            if name in done:
                continue
            done.add(name)
            element(
                actuator,
                "position",
                name=actuator_name(name),
                joint=name,
                kp=fnum(JOINT_KP),
                ctrlrange=fvec([chain.lower[k], chain.upper[k]]),
            )
            ctrl.append(float(spec.q0[finger][k]))
    if len(equality) == 0:
        root.remove(equality)

    n_flex_dof = 3 * spec.points.shape[0]
    qpos = [v for _, v in order] + [0.0] * n_flex_dof
    keyframe = element(root, "keyframe")
    element(
        keyframe,
        "key",
        name="initial",
        qpos=fvec(qpos),
        ctrl=fvec(ctrl),
    )

    ET.indent(root, space="  ")
    return ET.tostring(root, encoding="unicode") + "\n"
