"""A planned grasp as plain data: the ``softgrasp.plan/2`` JSON document, the per-increment
history rows and the people-facing table (no file I/O here)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from softgrasp import __version__
from softgrasp.grasp.planner import GraspPlan
from softgrasp.hand.packaged import portable_name
from softgrasp.physics.body import Body

__all__ = [
    "SCHEMA",
    "TRANSFORM_NOTE",
    "mesh_digest",
    "mesh_frame",
    "plan_document",
    "history_rows",
    "HISTORY_HEADER",
    "plan_table",
    "hand_polylines",
]

SCHEMA = "softgrasp.plan/2"
#: Equilibrium is "satisfied" when the held state's residuals are below this fraction of the weight.
EQUILIBRIUM_TOL = 0.02
HISTORY_HEADER = (
    "increment",
    "finger",
    "penetration_m",
    "force_norm_N",
    "normal_force_N",
    "tangential_force_N",
)


def _v(a: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(a).ravel()]


def mesh_digest(points: NDArray[np.float64], tets: NDArray[np.int64]) -> str:
    """SHA-256 of a mesh's node coordinates (float64) and tetrahedra (int64), little-endian, as
    ``"sha256:<hex>"``: the fingerprint ``plan.json`` records of the placed object, which
    ``execute`` compares with ``object.vtu``."""
    import hashlib

    h = hashlib.sha256()
    for a, dtype in ((points, "<f8"), (tets, "<i8")):
        arr = np.ascontiguousarray(np.asarray(a), dtype=dtype)
        h.update(str(arr.shape).encode())
        h.update(arr.tobytes())
    return "sha256:" + h.hexdigest()


#: What ``object.transform_mesh_to_plan`` maps, for people reading ``plan.json``.
TRANSFORM_NOTE = (
    "p_plan = T p_mesh (homogeneous, T the 4 x 4 transform_mesh_to_plan): p_mesh a point in the "
    "coordinates of the object's mesh file, in mesh_units (a built-in object or shape: as softgrasp "
    "generates it, in metres); p_plan the same point in the plan frame (metres, z up; the frame of "
    "every position in plan.json and of object.vtu): the mesh scaled by its unit, turned and moved "
    "to rest on the table"
)


def _closest_on_triangle(p: NDArray[np.float64], tri: NDArray[np.float64]) -> NDArray[np.float64]:
    """The point of the triangle ``tri`` (3, 3) nearest ``p`` (3,)."""
    a, b, c = tri
    best, dist = a, math.inf
    n = np.cross(b - a, c - a)
    nn = float(n @ n)
    if nn > 0:
        q = p - (n @ (p - a)) / nn * n
        w = np.array([np.cross(v - u, q - u) @ n for u, v in ((b, c), (c, a), (a, b))]) / nn
        if (w >= 0).all():
            return q
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        t = min(max(float((p - u) @ e) / max(float(e @ e), 1e-300), 0.0), 1.0)
        r = u + t * e
        d = float(np.linalg.norm(p - r))
        if d < dist:
            best, dist = r, d
    return best


def mesh_frame(
    plan: GraspPlan, body: Body, source_transform: NDArray[np.float64] | None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The transform (4, 4) from the object's source coordinates (a mesh file's, in its units) to
    the plan frame, ``p_plan = T p_mesh``: ``source_transform`` (to the body's mesh at rest, None
    for the identity) then the turn the settle gave it (onto a stable facet: the rigid fit of the
    body's mesh onto the placed object, exact for a rigid turn); and the initial contacts in the
    source's coordinates (3, 3): the points of the placed object's surface under them (on the
    touched facets), taken back by T."""
    from softgrasp.model.mesh.placement import rigid_fit

    T0 = np.eye(4) if source_transform is None else np.asarray(source_transform, dtype=np.float64)
    rest = np.asarray(body.mesh.points, dtype=np.float64)
    T = rigid_fit(rest, np.asarray(plan.placed, dtype=np.float64)) @ T0
    facets = np.asarray(body.mesh.facets)
    ig = plan.initial
    on_surface = np.array(
        [_closest_on_triangle(q, plan.placed[facets[f]]) for q, f in zip(ig.points, ig.facets, strict=True)]
    )
    back = np.linalg.inv(T)
    return T, on_surface @ back[:3, :3].T + back[:3, 3]


def plan_document(
    plan: GraspPlan,
    body: Body,
    object_name: str,
    *,
    source_transform: NDArray[np.float64] | None = None,
    units: str = "m",
) -> dict[str, Any]:
    """The ``plan.json`` document (keys carry their units). ``source_transform`` (4, 4) takes the
    object's source coordinates (a mesh file's, in ``units``) to its body's mesh at rest
    (:attr:`softgrasp.api.objects.SoftObject.transform`; None: the identity)."""
    m = body.material
    T, contacts_mesh = mesh_frame(plan, body, source_transform)
    normals_mesh = plan.initial.normals @ np.linalg.inv(T[:3, :3]).T
    normals_mesh /= np.linalg.norm(normals_mesh, axis=1, keepdims=True)
    ig = plan.initial
    weight = float(body.total_mass * np.linalg.norm(body.gravity))
    arm = float(np.linalg.norm(plan.contact_points - plan.com, axis=1).max())
    satisfied = (
        plan.friction_margin > 0.0
        and plan.force_residual <= EQUILIBRIUM_TOL * weight
        and plan.torque_residual <= EQUILIBRIUM_TOL * weight * arm
    )
    return {
        "schema": SCHEMA,
        "softgrasp_version": __version__,
        "object": {
            "name": object_name,
            "mass_kg": body.total_mass,
            "nodes": int(body.n_nodes),
            "tets": int(len(body.mesh.tets)),
            "mesh_sha256": mesh_digest(plan.placed, body.mesh.tets),
            "mesh_units": units,
            "transform_mesh_to_plan": [_v(row) for row in T],
            "transform_note": TRANSFORM_NOTE,
            "material": {
                "name": m.name,
                "E_Pa": m.E,
                "nu": m.nu,
                "density_kg_m3": m.density,
                "law": m.law.describe(),
            },
            "volume_term": body.volume,
        },
        "parameters": plan.config.describe(),
        "setpoints_N": {f.name: float(plan.setpoints[j]) for j, f in enumerate(plan.fingers)},
        "margin": None if plan.margin is None else plan.margin.relative_to(plan.config.safety_factor),
        "initial_grasp": {
            "criterion": "Ferrari-Canny epsilon on 8-edge friction cones, grasp plane through the "
            "centre of mass",
            "epsilon": ig.epsilon,
            "thumb_azimuth_deg": float(np.degrees(ig.thumb_azimuth)),
            "finger_half_spread_deg": float(np.degrees(ig.spread)),
            "triangle_centroid_m": _v(ig.centroid),
            "contacts_m": [_v(q) for q in ig.points],
            "normals": [_v(n) for n in ig.normals],
            "contacts_in_mesh_frame": [_v(q) for q in contacts_mesh],
            "normals_in_mesh_frame": [_v(n) for n in normals_mesh],
            "facets": [int(f) for f in ig.facets],
        },
        "fingers": [
            {
                "name": f.name,
                "initial_contact_m": _v(f.initial_contact),
                "contact_in_mesh_frame": _v(contacts_mesh[j]),
                "start_position_m": _v(plan.start_centres[j]),
                "final_position_m": _v(f.final_position),
                "penetration_m": f.penetration,
                "force_N": _v(f.force),
                "force_norm_N": f.force_norm,
                "setpoint_N": float(plan.setpoints[j]),
                "normal_force_N": f.normal_force,
                "tangential_force_N": f.tangential_force,
                "rigid_minimum_normal_force_N": float(plan.rigid_normal_forces[j]),
                "first_contact_travel_m": float(plan.first_contact_travel[j]),
            }
            for j, f in enumerate(plan.fingers)
        ],
        "equilibrium": {
            "satisfied": bool(satisfied),
            "force_residual_N": plan.force_residual,
            "torque_residual_Nm": plan.torque_residual,
            "friction_margin": plan.friction_margin,
            "rigid_utilisation": plan.rigid_utilisation,
            "weight_N": weight,
            "tolerance": f"residuals <= {EQUILIBRIUM_TOL:.0%} of the weight (torque: x largest lever arm)",
        },
        "hold": {
            "com_drift_m": plan.com_drift,
            "slip_m": [float(v) for v in plan.slip],
            "duration_s": plan.hold_time,
            "checks": [{"travel_m": t, "result": r} for t, r in plan.hold_checks],
        },
        "damage": None if plan.damage is None else {
            **plan.damage.describe(),
            "max_pressure_Pa": plan.config.max_pressure,
            "max_strain": plan.config.max_strain,
        },
        "hand": _hand_section(plan),
        "increments": plan.increments,
        "wall_time_s": plan.wall_time,
    }


def _hand_section(plan: GraspPlan) -> dict[str, Any] | None:
    """The hand's posture: palm pose, and per finger its joints at the start of the closing and at
    the held state (the last row of its closing path)."""
    pl, hand = plan.placement, plan.config.hand
    if pl is None or hand is None or plan.joint_paths is None:
        return None
    return {
        "model": portable_name(hand.source),
        "fingertips": None if hand.fingertips is None else dict(hand.fingertips),
        "fingertip_radius_m": hand.radius,
        "palm_pose": [_v(row) for row in pl.palm_pose],
        "fingers": {
            f.name: {
                "joints": list(hand.joint_names(f.name)),
                "q_start_rad": _v(plan.joint_paths[f.name][0]),
                "q_final_rad": _v(plan.joint_paths[f.name][-1]),
            }
            for f in plan.fingers
        },
    }


def history_rows(plan: GraspPlan) -> list[tuple[object, ...]]:
    """One row per increment and finger, in :data:`HISTORY_HEADER` order."""
    rows: list[tuple[object, ...]] = []
    for k in range(plan.increments):
        for j, name in enumerate(f.name for f in plan.fingers):
            rows.append(
                (
                    k + 1,
                    name,
                    float(plan.penetration[k, j]),
                    float(plan.force_norm[k, j]),
                    float(plan.normal_force[k, j]),
                    float(plan.tangential_force[k, j]),
                )
            )
    return rows


def plan_table(plan: GraspPlan) -> str:
    """The paper's Table 2 for this plan: finger, set-point [N] (the normal force the force
    controller closes to), and the held state's penetration [mm] and forces [N]."""
    lines = [
        f"{'finger':<8} {'set-point N':>12} {'penetration mm':>15} {'force N':>9} {'normal N':>9} "
        f"{'friction N':>11}"
    ]
    for j, f in enumerate(plan.fingers):
        lines.append(
            f"{f.name:<8} {plan.setpoints[j]:>12.3f} {f.penetration * 1e3:>15.2f} {f.force_norm:>9.3f} "
            f"{f.normal_force:>9.3f} {f.tangential_force:>11.3f}"
        )
    return "\n".join(lines)


def hand_polylines(plan: GraspPlan, travel: float | None = None) -> list[NDArray[np.float64]]:
    """The hand as world polylines [m]: the palm from the wrist through the knuckles and back, and
    each finger from its base joint to its fingertip (empty without a hand model).

    In the held state by default; at ``travel`` [m] of the closing instead, with each finger's joints
    interpolated between the rows of its closing path (extrapolated linearly from its last two rows
    past the held travel, where the closing went on only to bracket the least squeeze that holds).
    """
    from softgrasp.hand.placement import transform

    hand, pl = plan.config.hand, plan.placement
    if hand is None or pl is None or plan.joint_paths is None:
        return []
    index = {f.name: j for j, f in enumerate(plan.fingers)}
    fingers = []
    for f, q in plan.joint_paths.items():
        j = index[f]
        span = float(np.linalg.norm(plan.centres[j] - plan.start_centres[j]))
        if travel is not None and len(q) > 1 and span > 0.0:
            s = travel / span * (len(q) - 1)
            i = min(max(int(np.floor(s)), 0), len(q) - 2)
            joints = q[i] + (s - i) * (q[i + 1] - q[i])
        else:
            joints = q[-1]
        fingers.append(transform(pl.palm_pose, hand.link_points(f, joints)))
    wrist = pl.palm_pose[:3, 3]
    return [np.array([wrist, *(f[0] for f in fingers), wrist]), *fingers]
