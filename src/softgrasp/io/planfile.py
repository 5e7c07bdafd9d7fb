"""Reading a ``plan.json`` (schema ``softgrasp.plan/2``) for execution, with every field the
executor uses checked: a file of another schema, with missing fields or non-physical values is
refused with a message naming the field."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError
from softgrasp.grasp.initial import InitialGrasp
from softgrasp.hand.reach import GRASP_FINGERS
from softgrasp.io.limits import PLAN_RANGES
from softgrasp.io.plan_document import SCHEMA
from softgrasp.io.portable import resolve_path

__all__ = ["PlanFinger", "PlanFile", "load_plan_file", "load_plan_grasp", "SCHEMA"]

#: The finger names a plan may hold (three fingers, or a gripper's two).
PLANNED = tuple(name for fingers in GRASP_FINGERS for name in fingers)


@dataclass(frozen=True)
class PlanFinger:
    """One finger of a plan: where its closing starts and ends (world, m), its set-point (the
    normal force of the held state, N) and its joints at the start (rad)."""

    name: str
    start: NDArray[np.float64]
    final: NDArray[np.float64]
    normal_force: float
    q_start: NDArray[np.float64]


@dataclass(frozen=True)
class PlanFile:
    """The parts of a plan the executor needs (SI units, world frame)."""

    path: Path
    object_name: str
    mesh_file: Path
    mass: float
    E: float
    nu: float
    mu: float
    fingertip_radius: float
    table_mu: float
    hand_source: str
    palm_pose: NDArray[np.float64]
    fingers: tuple[PlanFinger, ...]
    document: dict[str, Any]
    mesh_sha256: str = ""


def _get(doc: Any, path: str) -> Any:
    cur = doc
    for key in path.split("."):
        if not isinstance(cur, dict) or key not in cur:
            raise ConfigError(f"plan file: missing field {path!r}")
        cur = cur[key]
    return cur


def _number(
    doc: Any, path: str, *, lo: float = -math.inf, hi: float = math.inf, open_lo: bool = True
) -> float:
    v = _get(doc, path)
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ConfigError(f"plan file: field {path!r} must be a finite number, got {v!r}")
    v = float(v)
    below = v <= lo if open_lo else v < lo
    if below or v >= hi:
        lo_s = "" if lo == -math.inf else f"{'>' if open_lo else '>='} {lo:g}"
        hi_s = "" if hi == math.inf else f"< {hi:g}"
        bounds = " and ".join(filter(None, (lo_s, hi_s)))
        raise ConfigError(f"plan file: field {path!r} = {v:g} is not physical (must be {bounds})")
    return v


def _ranged(doc: Any, path: str, key: str | None = None) -> float:
    """The number at ``path``, inside the physical range :data:`PLAN_RANGES` of ``key`` (default
    ``path``)."""
    return PLAN_RANGES[key or path].check(_get(doc, path), f"'{path}'", "plan file: field ")


def _floats(v: Any) -> NDArray[np.float64]:
    """``v`` (a list, nested or not) as an array of floats; an empty array when it is not a list
    of numbers of one shape."""
    if not isinstance(v, list):
        return np.zeros(0)
    try:
        return np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return np.zeros(0)


#: Largest coordinate of a position in a plan [m]: far beyond any hand's reach, and small enough
#: that distances between positions stay finite numbers.
FAR_M = 1e9


def _vector(doc: Any, path: str, n: int = 3) -> NDArray[np.float64]:
    v = _get(doc, path)
    a = _floats(v)
    if a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"plan file: field {path!r} must be {n} finite numbers, got {v!r}")
    _near(a, path)
    return a


def _near(a: NDArray[np.float64], path: str) -> None:
    """ConfigError when a coordinate of ``a`` lies beyond :data:`FAR_M`."""
    if np.abs(a).max(initial=0.0) > FAR_M:
        raise ConfigError(
            f"plan file: field {path!r} holds a coordinate of {np.abs(a).max():g} m: no hand reaches "
            f"there (at most {FAR_M:g} m); re-plan"
        )


def _read_document(p: Path) -> dict[str, Any]:
    """The JSON document of a plan file, its schema checked."""
    if not p.is_file():
        raise ConfigError(f"plan file {p} does not exist (write one with: softgrasp plan --out DIR)")
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"plan file {p} is not readable JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"plan file {p}: expected a JSON object at the top level")
    schema = doc.get("schema")
    if schema != SCHEMA:
        raise ConfigError(f"plan file {p}: schema {schema!r} is not {SCHEMA!r}; re-plan with this softgrasp")
    return doc


def load_plan_grasp(path: str | Path) -> InitialGrasp:
    """The initial grasp of a plan file (its three contacts, their normals and the triangle's
    centroid), to plan another closing from the same contacts (``softgrasp plan --grasp``)."""
    doc = _read_document(Path(path))
    ig = doc.get("initial_grasp")
    if isinstance(ig, dict) and "contacts_m" not in ig:
        raise ConfigError(
            f"plan file {path} holds no contact points (written by an earlier softgrasp): "
            "re-plan it to reuse its grasp"
        )
    rows = {}
    for key in ("contacts_m", "normals"):
        v = _get(doc, f"initial_grasp.{key}")
        a = _floats(v)
        if a.ndim != 2 or a.shape[0] not in (2, 3) or a.shape[1] != 3 or not np.all(np.isfinite(a)):
            raise ConfigError(
                f"plan file: field 'initial_grasp.{key}' must be 3 x 3 (or 2 x 3) finite numbers, got {v!r}"
            )
        rows[key] = a
    _near(rows["contacts_m"], "initial_grasp.contacts_m")
    n = np.linalg.norm(np.clip(rows["normals"], -2.0, 2.0), axis=1)
    if np.abs(n - 1.0).max() > 1e-6:
        raise ConfigError("plan file: field 'initial_grasp.normals' must hold unit vectors")
    facets = _get(doc, "initial_grasp.facets")
    k = len(rows["contacts_m"])
    if rows["normals"].shape != (k, 3):
        raise ConfigError("plan file: fields 'initial_grasp.contacts_m' and 'normals' differ in length")
    if not (isinstance(facets, list) and len(facets) == k and all(type(f) is int and f >= 0 for f in facets)):
        raise ConfigError(
            f"plan file: field 'initial_grasp.facets' must be {k} facet numbers, got {facets!r}"
        )
    return InitialGrasp(
        points=rows["contacts_m"],
        normals=rows["normals"],
        facets=np.asarray(facets, dtype=np.int64),
        centroid=_vector(doc, "initial_grasp.triangle_centroid_m"),
        epsilon=_number(doc, "initial_grasp.epsilon", lo=0.0, open_lo=False),
        thumb_azimuth=math.radians(_number(doc, "initial_grasp.thumb_azimuth_deg")),
        spread=math.radians(_number(doc, "initial_grasp.finger_half_spread_deg")),
    )


def load_plan_file(path: str | Path) -> PlanFile:
    """Read and check ``path``; :class:`ConfigError` says what is wrong and where."""
    p = Path(path)
    doc = _read_document(p)
    mesh_name = _get(doc, "object.mesh_file")
    if not isinstance(mesh_name, str) or not mesh_name:
        raise ConfigError("plan file: field 'object.mesh_file' must name the object's mesh file")
    mesh_file = (p.parent / mesh_name).resolve()
    if not mesh_file.is_file():
        raise ConfigError(
            f"plan file: the object mesh {mesh_file} is missing (it is written beside plan.json)"
        )
    hand = _get(doc, "hand")
    if hand is None:
        raise ConfigError(
            "plan file: no 'hand' section: the plan was made without a hand model (re-plan with one)"
        )
    pose = _floats(_get(doc, "hand.palm_pose"))
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ConfigError("plan file: field 'hand.palm_pose' must be a 4 x 4 matrix of finite numbers")
    _near(pose[:3, 3], "hand.palm_pose")
    R = pose[:3, :3]
    if (
        np.abs(R).max() > 1.0 + 1e-6
        or np.abs(R @ R.T - np.eye(3)).max() > 1e-6
        or abs(np.linalg.det(R) - 1) > 1e-6
        or np.any(pose[3] != [0, 0, 0, 1])
    ):
        raise ConfigError("plan file: field 'hand.palm_pose' is not a rigid transform")
    fingers_doc = _get(doc, "fingers")
    if not isinstance(fingers_doc, list) or not fingers_doc:
        raise ConfigError("plan file: field 'fingers' must be a non-empty list")
    fingers = []
    seen: set[str] = set()
    for k, f in enumerate(fingers_doc):
        where = f"fingers[{k}]"
        name = f.get("name") if isinstance(f, dict) else None
        if not isinstance(name, str) or not name:
            raise ConfigError(f"plan file: field '{where}.name' must be a finger name")
        if name not in PLANNED:
            raise ConfigError(
                f"plan file: field '{where}.name' = {name!r} is not a finger softgrasp plans "
                f"({', '.join(PLANNED)})"
            )
        if name in seen:
            raise ConfigError(f"plan file: field '{where}.name': finger {name!r} appears twice in 'fingers'")
        seen.add(name)
        q = _get(doc, f"hand.fingers.{name}.q_start_rad")
        qa = _floats(q)
        if not isinstance(q, list) or qa.shape != (len(q),) or not np.all(np.isfinite(qa)):
            raise ConfigError(
                f"plan file: field 'hand.fingers.{name}.q_start_rad' must be a list of finite angles"
            )
        named = {where: f}
        start = _vector(named, f"{where}.start_position_m")
        final = _vector(named, f"{where}.final_position_m")
        if np.linalg.norm(final - start) <= 0:
            raise ConfigError(f"plan file: finger {name!r} has no closing travel (start = final position)")
        fingers.append(
            PlanFinger(
                name=name,
                start=start,
                final=final,
                normal_force=_ranged(named, f"{where}.setpoint_N", "setpoint_N"),
                q_start=qa,
            )
        )
    return PlanFile(
        path=p,
        object_name=str(_get(doc, "object.name")),
        mesh_file=mesh_file,
        mass=_ranged(doc, "object.mass_kg"),
        E=_ranged(doc, "object.material.E_Pa"),
        nu=_ranged(doc, "object.material.nu"),
        mu=_ranged(doc, "parameters.contact.mu"),
        fingertip_radius=_ranged(doc, "parameters.fingertip_radius_m"),
        table_mu=_ranged(doc, "parameters.table_mu"),
        hand_source=str(resolve_path(_text(doc, "hand.model"), p.parent)),
        palm_pose=pose,
        fingers=tuple(fingers),
        document=doc,
        mesh_sha256=_digest(doc),
    )


def _text(doc: Any, path: str) -> str:
    v = _get(doc, path)
    if not isinstance(v, str) or not v:
        raise ConfigError(f"plan file: field {path!r} must be a non-empty string, got {v!r}")
    return v


def _digest(doc: Any) -> str:
    """The recorded fingerprint of the placed object mesh (``object.mesh_sha256``)."""
    obj = _get(doc, "object")
    if "mesh_sha256" not in obj:
        raise ConfigError(
            "plan file: missing field 'object.mesh_sha256' (the object mesh's fingerprint; "
            "written by an earlier softgrasp): re-plan it"
        )
    v = obj["mesh_sha256"]
    if not (isinstance(v, str) and v.startswith("sha256:") and len(v) == 71):
        raise ConfigError(
            f"plan file: field 'object.mesh_sha256' must be the mesh's 'sha256:<64 hex digits>', got {v!r}"
        )
    return v
