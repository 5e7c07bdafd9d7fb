"""Where the hand goes: the palm pose and joint angles that put each fingertip at its start point,
and the joint paths that move the fingertips along their straight closing lines (paper Sec. 2 and
4.3: the fingers close in Cartesian space, driven by WDLS on the hand model).

The palm is a free rigid body (the arm positions it): its pose is found together with the
fingers' joints by WDLS on the stacked fingertip tasks, the palm's six coordinates (a translation
and a small rotation about world axes) acting as extra joints without limits. Several starting
postures are tried (Kabsch's best rigid fit of a nominal posture's fingertips onto the targets);
a solution must reach every target, keep every joint inside its limits and keep the palm and all
finger joints outside the object. The one with the most room to its joint limits wins.

All positions are world coordinates [m] unless named ``*_palm``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import product
from types import MappingProxyType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.hand.model import HandModel, _axis_rotation, _limited_step, follow_line

__all__ = ["HandPlacement", "place_hand", "closing_paths", "transform", "invert"]

#: Largest fingertip distance [m] from its target accepted as reaching it.
REACH_TOL = 1e-5
#: WDLS iterations per starting posture.
MAX_ITER = 300
#: Largest Cartesian correction per iteration [m].
MAX_STEP = 0.01
#: Damping of the WDLS steps [m].
DAMPING = 1e-3
#: A posture whose largest fingertip error fell by less than this fraction over ``STALL_WINDOW``
#: iterations has stalled.
STALL_FRACTION = 0.01
STALL_WINDOW = 20


@dataclass(frozen=True)
class HandPlacement:
    """A reachable hand posture.

    Attributes
    ----------
    palm_pose: palm frame to world, (4, 4).
    q: independent joint vector of each finger (its :meth:`HandModel.joint_names` order) [rad].
    error: largest fingertip distance to its target [m].
    limit_room: smallest distance of any joint to its nearer limit, as a fraction of its range.
    """

    palm_pose: NDArray[np.float64]
    q: Mapping[str, NDArray[np.float64]]
    error: float
    limit_room: float

    def to_palm(self, p: ArrayLike) -> NDArray[np.float64]:
        """World point(s) ``p`` (..., 3) in the palm frame."""
        return transform(invert(self.palm_pose), p)

    def fingertip(self, model: HandModel, finger: str) -> NDArray[np.float64]:
        """World position of ``finger``'s fingertip centre in this posture [m]."""
        return transform(self.palm_pose, model.forward(finger, self.q[finger]))


def transform(T: NDArray[np.float64], p: ArrayLike) -> NDArray[np.float64]:
    """Apply the homogeneous transform ``T`` (4, 4) to points ``p`` (..., 3)."""
    a = np.asarray(p, dtype=np.float64)
    return a @ T[:3, :3].T + T[:3, 3]


def invert(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse of a rigid homogeneous transform."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _rotation(w: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation by the vector ``w`` (axis times angle)."""
    a = float(np.linalg.norm(w))
    return np.eye(3) if a < 1e-15 else _axis_rotation(w / a, a)


def _kabsch(src: NDArray[np.float64], dst: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rigid transform (4, 4) that best maps points ``src`` onto ``dst`` (least squares)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    H = (src - cs).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cd - R @ cs
    return T


def _postures(model: HandModel, fingers: Sequence[str]) -> list[dict[str, NDArray[np.float64]]]:
    """Nominal starting postures: each finger's joints at a few fractions of their ranges."""
    out = []
    for a, b in product((0.3, 0.5, 0.7), (0.35, 0.6)):
        q = {}
        for k, f in enumerate(fingers):
            lo, hi = model.limits(f)
            frac = np.full(len(lo), a if k == 0 else b)
            q[f] = lo + frac * (hi - lo)
        out.append(q)
    return out


def _seeds(
    model: HandModel, fingers: Sequence[str], T: NDArray[np.float64], up: NDArray[np.float64]
) -> list[tuple[NDArray[np.float64], dict[str, NDArray[np.float64]]]]:
    """Starting (palm pose, posture) pairs: grasps from above (when a thumb opposes the others),
    then Kabsch fits of nominal postures onto the targets."""
    out = []
    postures = _postures(model, fingers)
    up = up / np.linalg.norm(up)
    if "thumb" in fingers and len(fingers) > 1:
        k = fingers.index("thumb")
        others = np.delete(T, k, axis=0).mean(axis=0)
        y = others - T[k]
        y -= (y @ up) * up
        if np.linalg.norm(y) > 1e-9:
            y /= np.linalg.norm(y)
            z = -up
            base = np.column_stack([np.cross(y, z), y, z])  # palm axes in world: x, y (fingers), z (normal)
            for q0 in postures[1::2]:
                local = np.array([model.forward(f, q0[f]) for f in fingers])
                for tilt, yaw in product((0.3, 0.9), (0.0, -0.4, 0.4)):
                    R = _rotation(yaw * up) @ base @ _rotation(np.array([tilt, 0.0, 0.0]))
                    pose = np.eye(4)
                    pose[:3, :3] = R
                    pose[:3, 3] = T.mean(axis=0) - R @ local.mean(axis=0)
                    out.append((pose, dict(q0)))
    for q0 in postures:
        local = np.array([model.forward(f, q0[f]) for f in fingers])
        out.append((_kabsch(local, T), dict(q0)))
    return out


def _room(model: HandModel, q: Mapping[str, NDArray[np.float64]]) -> float:
    room = math.inf
    for f, v in q.items():
        lo, hi = model.limits(f)
        span = np.where(hi > lo, hi - lo, 1.0)
        room = min(room, float(np.min(np.minimum(v - lo, hi - v) / span)))
    return room


def _outside(points: NDArray[np.float64], hull_eq: NDArray[np.float64] | None, margin: float) -> bool:
    """Whether every point lies at least ``margin`` outside the convex hull ``n . p + d <= 0``."""
    if hull_eq is None:
        return True
    dist = points @ hull_eq[:, :3].T + hull_eq[:, 3]  # signed distance to each facet plane
    return bool((dist.max(axis=1) >= margin).all())


def _solve(
    model: HandModel,
    fingers: Sequence[str],
    targets: NDArray[np.float64],
    pose: NDArray[np.float64],
    q: dict[str, NDArray[np.float64]],
) -> tuple[NDArray[np.float64], dict[str, NDArray[np.float64]], float]:
    """Floating-palm WDLS from (pose, q) towards the targets; returns the last pose, q and the
    largest fingertip error."""
    dofs = [model.chain(f).dof for f in fingers]
    n = 6 + sum(dofs)
    lower = np.concatenate([np.full(6, -np.inf)] + [model.limits(f)[0] for f in fingers])
    upper = np.concatenate([np.full(6, np.inf)] + [model.limits(f)[1] for f in fingers])
    w = np.ones(n)
    R, p = pose[:3, :3].copy(), pose[:3, 3].copy()
    qv = np.concatenate([q[f] for f in fingers])

    def tips_and_jac(R, p, qv, jac: bool):
        tips, J = [], np.zeros((3 * len(fingers), n))
        off = 6
        for k, (f, d) in enumerate(zip(fingers, dofs, strict=True)):
            qf = qv[off - 6 : off - 6 + d]
            local = model.forward(f, qf)
            tips.append(p + R @ local)
            if jac:
                rows = slice(3 * k, 3 * k + 3)
                J[rows, 0:3] = np.eye(3)
                r = R @ local
                J[rows, 3:6] = -np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
                J[rows, off : off + d] = R @ model.jacobian(f, qf)
            off += d
        return np.concatenate(tips), J

    tips, J = tips_and_jac(R, p, qv, True)
    e = targets.ravel() - tips
    err = float(np.linalg.norm(e.reshape(-1, 3), axis=1).max())
    history = [err]
    for _ in range(MAX_ITER):
        if err <= REACH_TOL:
            break
        if len(history) > STALL_WINDOW and history[-1 - STALL_WINDOW] - err < STALL_FRACTION * err:
            break  # stalled short of the targets: a limit or the workspace's edge
        history.append(err)
        norm = float(np.linalg.norm(e))
        dx = e if norm <= MAX_STEP else e * (MAX_STEP / norm)
        x = np.concatenate([np.zeros(6), qv])
        dq = _limited_step(J, dx, x, lower, upper, w, DAMPING)
        if not np.any(dq):
            break
        alpha = 1.0
        for _ in range(20):
            R_try = _rotation(alpha * dq[3:6]) @ R
            p_try = p + alpha * dq[0:3]
            q_try = np.clip(qv + alpha * dq[6:], lower[6:], upper[6:])
            t_try, _ = tips_and_jac(R_try, p_try, q_try, False)
            e_try = targets.ravel() - t_try
            err_try = float(np.linalg.norm(e_try.reshape(-1, 3), axis=1).max())
            if np.linalg.norm(e_try) < norm:
                break
            alpha *= 0.5
        else:
            break
        R, p, qv = R_try, p_try, q_try
        tips, J = tips_and_jac(R, p, qv, True)
        e = targets.ravel() - tips
        err = err_try
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, p
    qd, off = {}, 0
    for f, d in zip(fingers, dofs, strict=True):
        qd[f] = qv[off : off + d].copy()
        off += d
    return out, qd, err


def place_hand(
    model: HandModel,
    targets: Mapping[str, ArrayLike],
    *,
    obstacle: ArrayLike | None = None,
    clearance: float = 0.0,
    up: ArrayLike = (0.0, 0.0, 1.0),
) -> HandPlacement:
    """Palm pose and joint angles putting each finger's fingertip centre at ``targets[finger]``.

    Parameters
    ----------
    model: the hand.  targets: world point [m] per finger (every finger named must exist).
    obstacle: points (K, 3) of the object [m]; the palm origin and every finger joint must lie at
        least ``clearance`` [m] outside their convex hull (only fingertips may touch the object).
    up: the world's vertical (the table's normal): with a ``thumb`` among the fingers, the palm is
        first tried above the targets, facing down, fingers pointing from the thumb's target to
        the others' (a grasp from above, clear of the table).

    Raises
    ------
    InfeasibleGrasp: no posture reaches every target within the joint limits and clear of the
        object; the message names the finger that stays farthest from its target.
    """
    fingers = tuple(targets)
    if not fingers:
        raise ConfigError("place_hand needs at least one fingertip target")
    for f in fingers:
        model.chain(f)
    T = np.array([np.asarray(targets[f], dtype=np.float64) for f in fingers])
    if T.shape != (len(fingers), 3) or not np.all(np.isfinite(T)):
        raise ConfigError("fingertip targets must be finite points (3,) [m]")
    hull_eq = None
    if obstacle is not None:
        from scipy.spatial import ConvexHull

        hull_eq = ConvexHull(np.asarray(obstacle, dtype=np.float64)).equations
    best: HandPlacement | None = None
    closest: dict[str, float] = {f: math.inf for f in fingers}
    blocked = False
    for pose0, q0 in _seeds(model, fingers, T, np.asarray(up, dtype=np.float64)):
        pose, q, err = _solve(model, fingers, T, pose0, q0)
        errs = {
            f: float(np.linalg.norm(transform(pose, model.forward(f, q[f])) - T[k]))
            for k, f in enumerate(fingers)
        }
        if max(errs.values()) < max(closest.values()):
            closest = errs  # the start that came nearest to reaching every target
        if err > REACH_TOL:
            continue
        joints = [pose[:3, 3][None, :]]
        for f in fingers:
            pts = model.link_points(f, q[f])
            # The joints, not the fingertip sphere (which touches the object by design).
            near_tip = np.linalg.norm(pts - pts[-1], axis=1) <= model.fingertip_radius(f)
            joints.append(transform(pose, pts[~near_tip]))
        if not _outside(np.vstack(joints), hull_eq, clearance):
            blocked = True
            continue
        room = _room(model, q)
        if best is None or room > best.limit_room:
            best = HandPlacement(pose, MappingProxyType(q), err, room)
    if best is None:
        worst = max(closest, key=lambda f: closest[f])
        if closest[worst] <= REACH_TOL and blocked:
            raise InfeasibleGrasp(
                "the hand reaches the initial grasp only with its palm or finger joints inside the "
                "object; choose a smaller object or another hand"
            )
        raise InfeasibleGrasp(
            f"the {worst} fingertip cannot reach its initial contact: {1e3 * closest[worst]:.1f} mm "
            "away in the hand's best posture within its joint limits"
        )
    return best


def closing_paths(
    model: HandModel,
    placement: HandPlacement,
    lines: Mapping[str, tuple[ArrayLike, ArrayLike]],
    steps: int,
) -> dict[str, NDArray[np.float64]]:
    """Joint paths ``(steps + 1, dof)`` moving each fingertip straight from ``lines[f][0]`` to
    ``lines[f][1]`` (world points [m]) with the palm fixed at ``placement`` (WDLS, the paper's
    Cartesian control); :class:`InfeasibleGrasp` names the finger that cannot follow its line."""
    out = {}
    for f, (a, b) in lines.items():
        out[f] = follow_line(model, f, placement.q[f], placement.to_palm(a), placement.to_palm(b), steps)
    return out
