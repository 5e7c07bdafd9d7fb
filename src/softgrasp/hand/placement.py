"""Where the hand goes: the palm pose and joint angles that put each fingertip at its start point,
and the joint paths that move the fingertips along their straight closing lines (paper Sec. 2 and
4.3: the fingers close in Cartesian space, driven by WDLS on the hand model).

The palm is a free rigid body (the arm positions it): its pose is found together with the
fingers' joints by WDLS on the stacked fingertip tasks, the palm's six coordinates (a translation
and a small rotation about world axes) acting as extra joints without limits. Several starting
postures are tried (grasps from above, and Kabsch's best rigid fit of a nominal posture's
fingertips onto the targets), each iterating on its own (:mod:`softgrasp.hand.descent`,
compiled); a solution must reach
every target, keep every joint inside its limits and keep the palm and all finger joints outside
the object. The one with the most room to its joint limits wins (the first one on a tie).

All positions are world coordinates [m] unless named ``*_palm``.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import product
from types import MappingProxyType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.hand.ik import follow_line
from softgrasp.hand.kinematics import ChainStack, HandModel, chain_stack, stack_kinematics

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
#: Step halvings of the line search before a posture counts as stuck.
MAX_HALVINGS = 20


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
    from softgrasp.hand import descent  # compiled: loaded at the first placement

    out = np.empty((3, 3))
    descent.rotation(float(w[0]), float(w[1]), float(w[2]), out)
    return out


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
    """Starting (palm pose, posture) pairs: grasps from above (when a thumb opposes the others, or
    a two-finger gripper closes across its two targets), then Kabsch fits of nominal postures onto
    the targets."""
    out = []
    postures = _postures(model, fingers)
    stack = chain_stack(tuple(model.chain(f) for f in fingers))
    tips = stack_kinematics(stack, np.array([np.concatenate([q[f] for f in fingers]) for q in postures])).tips
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
            for q0, local in zip(postures[1::2], tips[1::2], strict=True):
                for tilt, yaw in product((0.3, 0.9), (0.0, -0.4, 0.4)):
                    R = _rotation(yaw * up) @ base @ _rotation(np.array([tilt, 0.0, 0.0]))
                    pose = np.eye(4)
                    pose[:3, :3] = R
                    pose[:3, 3] = T.mean(axis=0) - R @ local.mean(axis=0)
                    out.append((pose, dict(q0)))
    if len(fingers) == 2:  # a gripper: from above, its closing axis through the two targets
        y = T[1] - T[0]
        z = -up + (up @ y) / (y @ y) * y
        if np.linalg.norm(y) > 1e-9 and np.linalg.norm(z) > 1e-9:
            y /= np.linalg.norm(y)
            z /= np.linalg.norm(z)
            base = np.column_stack([np.cross(y, z), y, z])  # palm x, y (closing axis), z (approach)
            # the fingers opened alike to the targets' distance: the palm centred between them
            even = [{f: model.limits(f)[0] + a * np.subtract(*model.limits(f)[::-1]) for f in fingers}
                    for a in np.linspace(0.0, 1.0, 41)]
            opened = np.array([np.concatenate([q[f] for f in fingers]) for q in even])
            ends = stack_kinematics(stack, opened).tips
            gap = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
            k = int(np.argmin(np.abs(gap - np.linalg.norm(T[1] - T[0]))))
            for q0, local in ((even[k], ends[k]),):
                for tilt in (0.0, 0.4, -0.4):
                    R = base @ _rotation(np.array([0.0, tilt, 0.0]))
                    pose = np.eye(4)
                    pose[:3, :3] = R
                    pose[:3, 3] = T.mean(axis=0) - R @ local.mean(axis=0)
                    out.append((pose, dict(q0)))
    for q0, local in zip(postures, tips, strict=True):
        out.append((_kabsch(local, T), dict(q0)))
    return out


def _rooms(stack: ChainStack, q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Smallest distance of any joint to its nearer limit as a fraction of its range, per row of the
    stacked joint vectors ``q`` ``(S, n)``."""
    lo = np.concatenate([c.lower for c in stack.chains])
    hi = np.concatenate([c.upper for c in stack.chains])
    span = np.where(hi > lo, hi - lo, 1.0)
    return np.min(np.minimum(q - lo, hi - q) / span, axis=1)


_HULL: list[tuple[bytes, NDArray[np.float64]]] = []  # the last obstacle's (digest, hull equations)


def _hull_equations(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Facet equations ``n . p + d <= 0`` of the convex hull of ``points`` (K, 3); the last
    obstacle's are kept (a planner tries several grasps of one object: 2.7 ms a hull at 2 196
    nodes)."""
    from scipy.spatial import ConvexHull

    key = hashlib.blake2b(np.ascontiguousarray(points).tobytes(), digest_size=16).digest() + repr(
        points.shape
    ).encode()
    kept = _HULL[0] if _HULL else None  # read once: another thread may replace it
    if kept is not None and kept[0] == key:
        return kept[1]
    eq = ConvexHull(points).equations
    eq.setflags(write=False)
    _HULL[:] = [(key, eq)]
    return eq


def _outside(points: NDArray[np.float64], hull_eq: NDArray[np.float64] | None, margin: float) -> bool:
    """Whether every point lies at least ``margin`` outside the convex hull ``n . p + d <= 0``."""
    if hull_eq is None:
        return True
    dist = points @ hull_eq[:, :3].T + hull_eq[:, 3]  # signed distance to each facet plane
    return bool((dist.max(axis=1) >= margin).all())


def _solve(
    stack: ChainStack,
    targets: NDArray[np.float64],
    R: NDArray[np.float64],
    p: NDArray[np.float64],
    q: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Floating-palm WDLS towards the targets ``(C, 3)`` from each of ``S`` starting postures (palm
    rotations ``R`` ``(S, 3, 3)``, origins ``p`` ``(S, 3)``, joints ``q`` ``(S, n)``); returns the last
    ``R``, ``p``, ``q`` and largest fingertip error ``(S,)`` of each
    (:func:`softgrasp.hand.descent.solve` with this module's rules)."""
    from softgrasp.hand import descent
    from softgrasp.hand.wdls import LIMIT_EPS

    return descent.solve(
        stack,
        targets,
        R,
        p,
        q,
        reach_tol=REACH_TOL,
        max_iter=MAX_ITER,
        max_step=MAX_STEP,
        damping=DAMPING,
        stall_fraction=STALL_FRACTION,
        stall_window=STALL_WINDOW,
        max_halvings=MAX_HALVINGS,
        limit_eps=LIMIT_EPS,
    )[:4]


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
    hull_eq = None if obstacle is None else _hull_equations(np.asarray(obstacle, dtype=np.float64))
    stack = chain_stack(tuple(model.chain(f) for f in fingers))
    seeds = _seeds(model, fingers, T, np.asarray(up, dtype=np.float64))
    poses = np.array([pose for pose, _ in seeds])
    q0 = np.array([np.concatenate([q[f] for f in fingers]) for _, q in seeds])
    R, p, q, err = _solve(stack, T, poses[:, :3, :3], poses[:, :3, 3], q0)
    final = stack_kinematics(stack, q, R, p, origins=True)
    assert final.origins is not None
    tip_err = np.linalg.norm(final.tips - T, axis=2)  # (S, C)
    rooms = _rooms(stack, q)
    best: HandPlacement | None = None
    closest: dict[str, float] = {f: math.inf for f in fingers}
    blocked = False
    for s in range(len(seeds)):
        errs = dict(zip(fingers, tip_err[s].tolist(), strict=True))
        if max(errs.values()) < max(closest.values()):
            closest = errs  # the start that came nearest to reaching every target
        if err[s] > REACH_TOL:
            continue
        joints = [p[s][None, :]]
        for c, chain in enumerate(stack.chains):
            pts = final.origins[s, c, : stack.length[c]]
            # The joints, not the fingertip sphere (which touches the object by design).
            joints.append(pts[np.linalg.norm(pts - final.tips[s, c], axis=1) > chain.radius])
        if not _outside(np.vstack(joints), hull_eq, clearance):
            blocked = True
            continue
        if best is None or rooms[s] > best.limit_room:
            pose = np.eye(4)
            pose[:3, :3], pose[:3, 3] = R[s], p[s]
            qd = {
                f: q[s, a : a + c.dof].copy()
                for f, a, c in zip(fingers, stack.starts, stack.chains, strict=True)
            }
            best = HandPlacement(pose, MappingProxyType(qd), float(err[s]), float(rooms[s]))
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
