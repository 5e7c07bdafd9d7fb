"""Whether the parts of a plan file agree, checked before anything is simulated.

A ``plan.json`` names its object mesh (``object.vtu`` beside it), its hand model and palm pose,
and per finger its closing line and starting joints. Edited by hand, copied beside another
object's mesh or mixed with another plan, those parts can each be valid and yet disagree; a hand
would then close on the wrong places and the object drop, for no fault of the set-points.
:func:`check_plan` refuses such a plan with a :class:`~softgrasp.errors.ConfigError` naming the
field:

* **fingers**: exactly the planner's three (``thumb``, ``first``, ``middle``), each once, each a
  finger of the hand model, with the hand model's joints;
* **object mesh**: the fingerprint of ``object.vtu`` (points and tets) is ``object.mesh_sha256``;
* **hand and palm pose**: each fingertip, put by the hand's kinematics at ``hand.palm_pose`` with
  its starting joints, is where the finger's closing starts (within :data:`POSE_TOL`); the joints
  are inside their limits; the fingertips start and end their closing at the object.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError
from softgrasp.hand.kinematics import HandModel
from softgrasp.hand.placement import transform
from softgrasp.io.plan_document import mesh_digest
from softgrasp.io.planfile import PlanFile
from softgrasp.model.mesh.tetmesh import TetMesh

__all__ = ["POSE_TOL", "REACH_TOL", "check_plan", "hand_model_of"]

#: Largest distance [m] between a fingertip placed by the hand's kinematics and the finger's
#: recorded start (the planner's inverse kinematics puts it within 1e-7 m).
POSE_TOL = 5e-4
#: Largest distance [m] of a fingertip's start or end from the object's bounding box, beyond its
#: own radius.
REACH_TOL = 0.01


def hand_model_of(plan: PlanFile) -> HandModel:
    """The hand a plan was made with: its URDF or MJCF file read with the plan's fingertip mapping
    and radius (``hand.fingertips``, ``hand.fingertip_radius_m``), or the packaged hand the plan
    names (a plan written elsewhere carries another install's path)."""
    from softgrasp.hand.packaged import PACKAGE_PREFIX
    from softgrasp.hand.urdf import PACKAGED
    from softgrasp.io.options import hand_model

    section = plan.document.get("hand") or {}
    mapping = section.get("fingertips") if isinstance(section, dict) else None
    radius = section.get("fingertip_radius_m") if isinstance(section, dict) else None
    src = Path(plan.hand_source)
    packaged = {file: name for name, file in PACKAGED.items()}
    recorded = str(section.get("model", "")) if isinstance(section, dict) else ""
    if recorded.startswith(PACKAGE_PREFIX) and src.name in packaged:  # a packaged hand, by name
        return hand_model(packaged[src.name], None, radius)
    if src.is_file():
        return hand_model(str(src), mapping, radius)
    if src.name in packaged:  # written by another installation
        return hand_model(packaged[src.name], None, radius)
    raise ConfigError(f"plan file: the hand model {src} is not found; put the hand file back at that path")


def _mm(d: float) -> str:
    return f"{d * 1e3:.3g} mm" if d < 1.0 else f"{d:.3g} m"


def _check_mesh(plan: PlanFile) -> TetMesh:
    from softgrasp.model.mesh.io import load_mesh

    mesh = load_mesh(plan.mesh_file)
    if mesh_digest(mesh.points, mesh.tets) != plan.mesh_sha256:
        raise ConfigError(
            f"plan file: the object mesh {plan.mesh_file.name} is not the one planned (its points and "
            "tets do not match field 'object.mesh_sha256'): put back the object.vtu written with this "
            "plan.json, or re-plan"
        )
    return mesh


def _check_fingers(plan: PlanFile, hand: HandModel) -> None:
    names = [f.name for f in plan.fingers]
    for k, name in enumerate(names):
        if name not in hand.fingers:
            raise ConfigError(
                f"plan file: field 'fingers[{k}].name': the hand model has no finger {name!r} "
                f"(it has {', '.join(sorted(hand.fingers))})"
            )
    missing = [n for n in hand.grasp_fingers if n not in names]
    if missing:
        raise ConfigError(f"plan file: field 'fingers' lacks the finger(s) {', '.join(missing)}")
    section = plan.document["hand"].get("fingers")
    if not isinstance(section, dict) or sorted(section) != sorted(names):
        got = sorted(section) if isinstance(section, dict) else section
        raise ConfigError(f"plan file: field 'hand.fingers' must hold exactly the fingers {names}, got {got}")
    for name in names:
        joints = section[name].get("joints") if isinstance(section[name], dict) else None
        want = list(hand.joint_names(name))
        if joints != want:
            raise ConfigError(
                f"plan file: field 'hand.fingers.{name}.joints' = {joints!r} is not the hand model's "
                f"{want}: the plan was made with another hand"
            )


def _check_pose(plan: PlanFile, hand: HandModel, mesh: TetMesh) -> None:
    where = {f.name: k for k, f in enumerate(plan.fingers)}
    tips: dict[str, NDArray[np.float64]] = {}
    for f in plan.fingers:
        chain, field = hand.chain(f.name), f"'hand.fingers.{f.name}.q_start_rad'"
        if f.q_start.shape != (chain.dof,):
            raise ConfigError(
                f"plan file: field {field} must hold {chain.dof} angles {list(chain.joint_names)}, "
                f"got {f.q_start.size}"
            )
        lo, hi = hand.limits(f.name)
        if np.any(f.q_start < lo - 1e-6) or np.any(f.q_start > hi + 1e-6):
            raise ConfigError(f"plan file: field {field} lies outside the finger's joint limits")
        tips[f.name] = transform(plan.palm_pose, hand.forward(f.name, f.q_start))
    off = {f.name: tips[f.name] - f.start for f in plan.fingers}
    bad = [f for f in plan.fingers if np.linalg.norm(off[f.name]) > POSE_TOL]
    if len(bad) == len(plan.fingers) and len(bad) > 1:
        first = off[bad[0].name]
        if all(np.linalg.norm(off[f.name] - first) <= POSE_TOL for f in bad):
            raise ConfigError(
                f"plan file: field 'hand.palm_pose' puts the palm {_mm(float(np.linalg.norm(first)))} from "
                "where the fingers' starting joints and closing lines place it: the palm pose was moved; "
                "re-plan"
            )
    for f in bad:
        k = where[f.name]
        d = float(np.linalg.norm(off[f.name]))
        other = [
            j
            for j, g in enumerate(plan.fingers)
            if j != k and np.linalg.norm(tips[f.name] - g.start) <= POSE_TOL
        ]
        hint = f" (it puts it where fingers[{other[0]}] starts: fingers swapped?)" if other else ""
        raise ConfigError(
            f"plan file: field 'fingers[{k}].start_position_m' is {_mm(d)} from where the hand puts the "
            f"{f.name} fingertip at 'hand.palm_pose' with 'hand.fingers.{f.name}.q_start_rad'{hint} "
            f"(tolerance {POSE_TOL * 1e3:g} mm): the plan's fingers and hand disagree; re-plan"
        )
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    reach = plan.fingertip_radius + REACH_TOL
    for k, f in enumerate(plan.fingers):
        for key, p in (("start_position_m", f.start), ("final_position_m", f.final)):
            d = float(np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0)))
            if d > reach:
                raise ConfigError(
                    f"plan file: field 'fingers[{k}].{key}' lies {_mm(d)} outside the object's bounding "
                    f"box (at most the fingertip radius + {REACH_TOL * 1e3:g} mm): the finger would close "
                    "on nothing; re-plan"
                )


def check_plan(plan: PlanFile, hand: HandModel | None = None) -> tuple[HandModel, TetMesh]:
    """Check that ``plan``'s fingers, object mesh, hand and palm pose agree (module docstring);
    return the hand model and the object mesh. :class:`ConfigError` names the field that does not."""
    hand = hand_model_of(plan) if hand is None else hand
    _check_fingers(plan, hand)
    mesh = _check_mesh(plan)
    _check_pose(plan, hand, mesh)
    return hand, mesh
