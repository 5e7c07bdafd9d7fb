"""The built-in :class:`~softgrasp.execution.protocol.Hand` backend: the hand, the object and the table
simulated in MuJoCo (physics softgrasp did not write), from a plan.

* tactile sensing: each fingertip's normal contact force is the sum of the normal components of
  MuJoCo's contact forces on its sphere (what a pressure-sensing fingertip reads);
* Cartesian fingertip commands go through softgrasp's WDLS (:func:`softgrasp.hand.ik.track`)
  to the joints' position servos, from the last commanded posture;
* the base is the scene's arm (three stiff slide servos carrying the palm).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from softgrasp.execution.mujoco.scene import MujocoScene, load_scene
from softgrasp.execution.mujoco.spec import SceneSpec
from softgrasp.execution.plan_check import check_plan, hand_model_of
from softgrasp.hand.ik import track
from softgrasp.hand.kinematics import HandModel
from softgrasp.hand.placement import invert, transform
from softgrasp.io.planfile import PlanFile
from softgrasp.model.mesh.tetmesh import TetMesh

__all__ = ["MujocoHand", "hand_model_of", "scene_spec_of"]


def scene_spec_of(plan: PlanFile, hand: HandModel, mesh: TetMesh | None = None) -> SceneSpec:
    """The MuJoCo scene of a plan: its object (``mesh``, default the plan's mesh file, as placed on
    the table; mass, E, nu), table and friction, the hand at the planned palm pose with the fingers
    at their starting joints."""
    from softgrasp.model.mesh.io import load_mesh

    mesh = load_mesh(plan.mesh_file) if mesh is None else mesh
    pts = np.asarray(mesh.points, dtype=np.float64)
    return SceneSpec(
        hand=hand,
        palm_pose=plan.palm_pose,
        q0={f.name: f.q_start for f in plan.fingers},
        points=pts,
        tets=np.asarray(mesh.tets),
        mass=plan.mass,
        young=plan.E,
        poisson=plan.nu,
        mu=plan.mu,
        table_z=float(pts[:, 2].min()),
        table_mu=plan.table_mu,
    )


class MujocoHand:
    """A simulated hand implementing :class:`~softgrasp.execution.protocol.Hand` on a
    :class:`~softgrasp.execution.mujoco.scene.MujocoScene`."""

    def __init__(self, scene: MujocoScene, fingers: tuple[str, ...] | None = None) -> None:
        self.scene = scene
        self.model = scene.spec.hand
        self._fingers = tuple(fingers) if fingers is not None else scene.fingers
        self._q = {f: np.array(scene.spec.q0[f], dtype=np.float64) for f in self._fingers}
        for f in self._fingers:
            scene.data.ctrl[scene.actuator_index(f)] = self._q[f]

    @classmethod
    def from_plan(cls, plan: PlanFile) -> MujocoHand:
        """The scene of ``plan`` with the hand at its starting posture, once
        :func:`~softgrasp.execution.plan_check.check_plan` has found its parts in agreement."""
        hand, mesh = check_plan(plan)
        return cls(load_scene(scene_spec_of(plan, hand, mesh)), tuple(f.name for f in plan.fingers))

    # -- the Hand protocol
    @property
    def fingers(self) -> tuple[str, ...]:
        return self._fingers

    @property
    def time(self) -> float:
        return float(self.scene.data.time)

    def fingertip_positions(self) -> dict[str, NDArray[np.float64]]:
        inv = invert(self.scene.palm_pose())
        return {f: transform(inv, self.scene.fingertip_position(f)) for f in self._fingers}

    def fingertip_normal_forces(self) -> dict[str, float]:
        mj, m, d = self.scene._mj, self.scene.model, self.scene.data
        tips = {self.scene.tip_geom(f): f for f in self._fingers}
        out = dict.fromkeys(self._fingers, 0.0)
        f6 = np.zeros(6)
        for i in range(int(d.ncon)):
            c = d.contact[i]
            if c.efc_address < 0:
                continue
            f = tips.get(int(c.geom[0])) or tips.get(int(c.geom[1]))
            if f is None:
                continue
            mj.mj_contactForce(m, d, i, f6)
            out[f] += float(f6[0])  # the normal component, >= 0
        return out

    def fingertip_forces(self) -> dict[str, NDArray[np.float64]]:
        return {f: self.scene.fingertip_force(f) for f in self._fingers}

    def command_fingertips(self, targets: Mapping[str, NDArray[np.float64]]) -> None:
        for f, p in targets.items():
            self._q[f] = track(self.model, f, p, self._q[f], iterations=5)
            self.scene.data.ctrl[self.scene.actuator_index(f)] = self._q[f]

    def command_base(self, offset: NDArray[np.float64]) -> None:
        self.scene.command_palm(offset)

    def step(self, dt: float) -> None:
        n = max(1, int(round(dt / float(self.scene.model.opt.timestep))))
        self.scene.step(n)

    def object_position(self) -> NDArray[np.float64]:
        return self.scene.object_com()

    # -- extras for reports
    def palm_to_world(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Palm-frame points to the world at the current base pose."""
        return transform(self.scene.palm_pose(), p)

    def snapshot(self, names: list[str] | tuple[str, ...]) -> tuple:
        """The scene now, for a picture: (object nodes (N, 3), fingertip centres (F, 3), fingertip
        forces on the object (F, 3) [N], the hand's polylines, time [s])."""
        sc = self.scene
        sc.forward()
        tips = np.array([sc.fingertip_position(n) for n in names])
        forces = np.array([sc.fingertip_force(n) for n in names])
        return sc.object_nodes(), tips, forces, self.links(), self.time

    def links(self) -> list[NDArray[np.float64]]:
        """The hand as world polylines at its current joint readings: palm, then each finger."""
        d = self.scene.data
        pose = self.scene.palm_pose()
        fingers = {}
        for f in self._fingers:
            q = np.array(d.qpos[self.scene.joint_qpos_index(f)], dtype=np.float64)
            lo, hi = self.model.limits(f)
            fingers[f] = transform(pose, self.model.link_points(f, np.clip(q, lo, hi)))
        wrist = pose[:3, 3]
        palm = np.array([wrist] + [pts[0] for pts in fingers.values()] + [wrist])
        return [palm, *fingers.values()]
