"""Kinematic model of a multi-finger hand read from a URDF: fingertip forward kinematics, the
analytic positional Jacobian and weighted damped least-squares (WDLS) inverse kinematics.

The hand is a tree of links rooted at the palm. Every link named ``<prefix>_tip`` ends a finger;
its origin is the fingertip sphere centre and its ``<collision>`` sphere gives the fingertip
radius. The finger is the serial chain of joints from the palm to that link. Prefixes ``th``,
``ff``, ``mf`` (also ``rf``, ``lf``) name the fingers ``thumb``, ``first``, ``middle`` (``ring``,
``little``); any other prefix is used as the finger name.

Joints may be ``revolute``, ``prismatic`` or ``fixed``. A joint with ``<mimic joint="J"
multiplier="a" offset="b"/>`` follows ``q = a q_J + b``; it is not an independent coordinate of the
finger and the effective limits of ``J`` are narrowed so that the mimic joint stays inside its own
limits. A finger's joint vector ``q`` holds its independent joints in root-to-tip order.

All positions are in the palm (root link) frame; SI units (m, rad).
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ConfigError, InfeasibleGrasp

__all__ = [
    "FINGER_NAMES",
    "LINE_TOLERANCE",
    "Joint",
    "FingerChain",
    "HandModel",
    "ChainStack",
    "Kinematics",
    "chain_stack",
    "local_transforms",
    "chain_product",
    "chain_frames",
    "frame_kinematics",
    "stack_kinematics",
    "wdls_step",
    "solve_ik",
    "track",
    "follow_line",
]

#: Finger name of each tip-link prefix (``ff_tip`` -> ``first``).
FINGER_NAMES: Mapping[str, str] = MappingProxyType(
    {"th": "thumb", "ff": "first", "mf": "middle", "rf": "ring", "lf": "little"}
)

#: Largest distance [m] :func:`follow_line` lets the fingertip stray from its commanded line point.
LINE_TOLERANCE = 5e-4

#: Largest Cartesian correction [m] one IK iteration aims at (longer errors are shortened).
MAX_CARTESIAN_STEP = 0.01

#: A joint closer than this [rad or m] to a limit counts as being at the limit.
LIMIT_EPS = 1e-12

#: Step halvings of the IK line search before an iteration counts as "no progress".
MAX_HALVINGS = 30

#: An IK attempt stops when its error fell by less than this fraction over the last
#: :data:`STALL_WINDOW` iterations (slow creep towards the closest point of an unreachable target).
STALL_FRACTION = 1e-3
STALL_WINDOW = 10

#: Extra random starting configurations tried by :func:`solve_ik` after ``q0`` and mid-range.
IK_RESTARTS = 6

#: ``-[a]x = a @ _LEVI_CIVITA`` (reshaped to 3 x 3): the Levi-Civita symbol as ``eps[k, 3 i + j]``.
_LEVI_CIVITA = np.zeros((3, 9))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI_CIVITA[_k, 3 * _i + _j], _LEVI_CIVITA[_k, 3 * _j + _i] = 1.0, -1.0
_LEVI_CIVITA.setflags(write=False)

_MOVABLE = ("revolute", "prismatic")
_SUPPORTED = ("revolute", "prismatic", "fixed")


@dataclass(frozen=True, eq=False)
class Joint:
    """One URDF joint: ``origin`` is the parent-to-joint transform (4x4), ``axis`` a unit vector in
    the joint frame, ``lower``/``upper`` its limits [rad or m] (``0`` for fixed joints) and
    ``mimic`` the name of the joint it follows (``q = multiplier * q_mimic + offset``) or ``None``."""

    name: str
    kind: str
    parent: str
    child: str
    origin: NDArray[np.float64]
    axis: NDArray[np.float64]
    lower: float
    upper: float
    mimic: str | None = None
    multiplier: float = 1.0
    offset: float = 0.0

    @property
    def movable(self) -> bool:
        """True for revolute and prismatic joints."""
        return self.kind in _MOVABLE


@dataclass(frozen=True, eq=False)
class FingerChain:
    """The serial chain of one finger, palm to fingertip.

    ``joints`` are all joints of the chain (fixed ones included) in root-to-tip order;
    ``joint_names`` the independent joints, i.e. the entries of the finger's ``q``, with their
    effective limits ``lower``/``upper``. Joint ``joints[k]`` moves by
    ``drive_gain[k] * q[drive_index[k]] + drive_offset[k]`` (``drive_index[k] = -1``: fixed).
    """

    name: str
    tip_link: str
    radius: float
    joints: tuple[Joint, ...]
    joint_names: tuple[str, ...]
    lower: NDArray[np.float64]
    upper: NDArray[np.float64]
    drive_index: tuple[int, ...]
    drive_gain: tuple[float, ...]
    drive_offset: tuple[float, ...]

    @property
    def dof(self) -> int:
        """Number of independent joints."""
        return len(self.joint_names)


# ---------------------------------------------------------------------- geometry helpers


def _rpy_matrix(roll: float, pitch: float, yaw: float) -> NDArray[np.float64]:
    """URDF rotation ``Rz(yaw) Ry(pitch) Rx(roll)`` (fixed axes x, y, z)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _axis_rotation(axis: NDArray[np.float64], angle: float) -> NDArray[np.float64]:
    """Rotation by ``angle`` [rad] about the unit vector ``axis`` (Rodrigues)."""
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    t = 1.0 - c
    return np.array(
        [
            [c + x * x * t, x * y * t - z * s, x * z * t + y * s],
            [y * x * t + z * s, c + y * y * t, y * z * t - x * s],
            [z * x * t - y * s, z * y * t + x * s, c + z * z * t],
        ]
    )


# ---------------------------------------------------------------------- URDF reading


def _floats(text: str | None, count: int, what: str, default: tuple[float, ...]) -> tuple[float, ...]:
    if text is None:
        return default
    try:
        values = tuple(float(v) for v in text.split())
    except ValueError:
        raise ConfigError(f"{what} = {text!r} is not a list of numbers") from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{what} = {text!r} must be {count} finite numbers")
    return values


def _float_attr(elem: ET.Element, key: str, what: str, default: float | None = None) -> float:
    text = elem.get(key)
    if text is None:
        if default is None:
            raise ConfigError(f"{what} has no '{key}' attribute")
        return default
    return _floats(text, 1, f"{what} {key}", (default or 0.0,))[0]


def _parse_joint(elem: ET.Element, links: set[str]) -> Joint:
    name = elem.get("name")
    if not name:
        raise ConfigError("a <joint> has no name")
    what = f"joint '{name}'"
    kind = elem.get("type")
    if kind not in _SUPPORTED:
        raise ConfigError(f"{what} has type {kind!r}; supported types are {', '.join(_SUPPORTED)}")
    ends = {}
    for tag in ("parent", "child"):
        e = elem.find(tag)
        link = e.get("link") if e is not None else None
        if not link:
            raise ConfigError(f"{what} has no <{tag} link=...>")
        if link not in links:
            raise ConfigError(f"{what} refers to unknown {tag} link '{link}'")
        ends[tag] = link
    T = np.eye(4)
    o = elem.find("origin")
    if o is not None:
        xyz = _floats(o.get("xyz"), 3, f"{what} origin xyz", (0.0, 0.0, 0.0))
        rpy = _floats(o.get("rpy"), 3, f"{what} origin rpy", (0.0, 0.0, 0.0))
        T[:3, :3] = _rpy_matrix(*rpy)
        T[:3, 3] = xyz
    a = elem.find("axis")
    axis = np.array(_floats(a.get("xyz") if a is not None else None, 3, f"{what} axis", (1.0, 0.0, 0.0)))
    lower = upper = 0.0
    mimic, multiplier, offset = None, 1.0, 0.0
    if kind in _MOVABLE:
        norm = float(np.linalg.norm(axis))
        if norm == 0.0:
            raise ConfigError(f"{what} has a zero axis")
        axis = axis / norm
        lim = elem.find("limit")
        if lim is None or lim.get("lower") is None or lim.get("upper") is None:
            raise ConfigError(f"{what} has no <limit lower=... upper=...>; every moving joint needs limits")
        lower = _float_attr(lim, "lower", f"{what} limit")
        upper = _float_attr(lim, "upper", f"{what} limit")
        if lower > upper:
            raise ConfigError(f"{what} has limits lower = {lower} > upper = {upper}")
        m = elem.find("mimic")
        if m is not None:
            mimic = m.get("joint")
            if not mimic:
                raise ConfigError(f"{what} has a <mimic> without a joint attribute")
            multiplier = _float_attr(m, "multiplier", f"{what} mimic", 1.0)
            offset = _float_attr(m, "offset", f"{what} mimic", 0.0)
    return Joint(name, kind, ends["parent"], ends["child"], T, axis, lower, upper, mimic, multiplier, offset)


def _tip_radius(link: ET.Element, name: str) -> float:
    for col in link.findall("collision"):
        sphere = col.find("geometry/sphere")
        if sphere is not None:
            r = _float_attr(sphere, "radius", f"fingertip link '{name}' sphere")
            if not r > 0.0:
                raise ConfigError(f"fingertip link '{name}' has sphere radius {r} m; it must be > 0")
            origin = col.find("origin")
            if origin is not None:
                xyz = _floats(origin.get("xyz"), 3, f"link '{name}' collision xyz", (0.0, 0.0, 0.0))
                if any(v != 0.0 for v in xyz):
                    raise ConfigError(
                        f"fingertip link '{name}': the sphere must be centred on the link origin"
                    )
            return r
    raise ConfigError(f"fingertip link '{name}' has no <collision> sphere giving the fingertip radius")


def _finger_name(tip: str) -> str:
    prefix = tip[: -len("_tip")]
    if not prefix:
        raise ConfigError(f"fingertip link '{tip}' has no finger prefix (expected e.g. 'ff_tip')")
    return FINGER_NAMES.get(prefix.lower(), prefix)


def _build_chain(
    name: str, tip: str, radius: float, path: list[Joint], by_name: dict[str, Joint]
) -> FingerChain:
    independent = [j for j in path if j.movable and j.mimic is None]
    if not independent:
        raise ConfigError(f"finger '{name}' (link '{tip}') has no independent moving joint")
    index = {j.name: k for k, j in enumerate(independent)}
    lower = np.array([j.lower for j in independent])
    upper = np.array([j.upper for j in independent])
    drive_index, drive_gain, drive_offset = [], [], []
    for j in path:
        if not j.movable:
            drive_index.append(-1)
            drive_gain.append(0.0)
            drive_offset.append(0.0)
        elif j.mimic is None:
            drive_index.append(index[j.name])
            drive_gain.append(1.0)
            drive_offset.append(0.0)
        else:
            target = by_name[j.mimic]
            if target.name not in index:
                raise ConfigError(
                    f"joint '{j.name}' of finger '{name}' mimics joint '{j.mimic}', which is not an "
                    "independent joint of the same finger"
                )
            k = index[target.name]
            a, b = j.multiplier, j.offset
            # the mimic joint must stay inside its own limits: narrow the driving joint's range
            if a == 0.0:
                if not j.lower <= b <= j.upper:
                    raise ConfigError(f"joint '{j.name}': mimic offset {b} is outside its limits")
            else:
                lo, hi = sorted(((j.lower - b) / a, (j.upper - b) / a))
                lower[k], upper[k] = max(lower[k], lo), min(upper[k], hi)
                if lower[k] > upper[k]:
                    raise ConfigError(
                        f"joint '{j.name}' mimics '{j.mimic}' but their limits are incompatible "
                        "(no value of the driving joint keeps both inside their limits)"
                    )
            drive_index.append(k)
            drive_gain.append(a)
            drive_offset.append(b)
    lower.setflags(write=False)
    upper.setflags(write=False)
    return FingerChain(
        name=name,
        tip_link=tip,
        radius=radius,
        joints=tuple(path),
        joint_names=tuple(j.name for j in independent),
        lower=lower,
        upper=upper,
        drive_index=tuple(drive_index),
        drive_gain=tuple(drive_gain),
        drive_offset=tuple(drive_offset),
    )


def _parse_urdf(text: str, source: str) -> dict[str, FingerChain]:
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ConfigError(f"URDF {source} is not well-formed XML: {exc}") from None
    if root.tag != "robot":
        raise ConfigError(f"URDF {source}: the root element is <{root.tag}>, expected <robot>")
    link_elems: dict[str, ET.Element] = {}
    for le in root.findall("link"):
        lname = le.get("name")
        if not lname:
            raise ConfigError(f"URDF {source}: a <link> has no name")
        if lname in link_elems:
            raise ConfigError(f"URDF {source}: link '{lname}' is defined twice")
        link_elems[lname] = le
    if not link_elems:
        raise ConfigError(f"URDF {source} defines no <link>")
    links = set(link_elems)
    by_name: dict[str, Joint] = {}
    parent_joint: dict[str, Joint] = {}
    for je in root.findall("joint"):
        joint = _parse_joint(je, links)
        if joint.name in by_name:
            raise ConfigError(f"URDF {source}: joint '{joint.name}' is defined twice")
        if joint.child in parent_joint:
            raise ConfigError(f"URDF {source}: link '{joint.child}' is the child of two joints")
        by_name[joint.name] = joint
        parent_joint[joint.child] = joint
    for joint in by_name.values():
        if joint.mimic is not None:
            target = by_name.get(joint.mimic)
            if target is None:
                raise ConfigError(f"URDF {source}: joint '{joint.name}' mimics unknown joint '{joint.mimic}'")
            if not target.movable or target.mimic is not None:
                raise ConfigError(
                    f"URDF {source}: joint '{joint.name}' mimics '{joint.mimic}', which is not an "
                    "independent moving joint"
                )
    roots = sorted(links - set(parent_joint))
    if len(roots) != 1:
        raise ConfigError(f"URDF {source} must have exactly one root (palm) link; found {roots or 'none'}")

    def path_to(link: str) -> list[Joint]:
        path: list[Joint] = []
        seen = {link}
        while link in parent_joint:
            j = parent_joint[link]
            path.append(j)
            link = j.parent
            if link in seen:
                raise ConfigError(f"URDF {source}: the joints form a loop through link '{link}'")
            seen.add(link)
        return path[::-1]

    has_child = {j.parent for j in by_name.values()}
    paths = {link: path_to(link) for link in links}
    tips = sorted(link for link in links if link.endswith("_tip"))
    for leaf in sorted(links - has_child - set(roots)):
        on_finger = any(j.child in tips for j in paths[leaf]) or leaf in tips
        if not on_finger and any(j.movable for j in paths[leaf]):
            raise ConfigError(
                f"URDF {source}: the chain ending at link '{leaf}' has no fingertip link; name the "
                "fingertip link '<finger>_tip' (e.g. 'ff_tip')"
            )
    if not tips:
        raise ConfigError(f"URDF {source} has no fingertip link named '<finger>_tip' (e.g. 'ff_tip')")
    chains: dict[str, FingerChain] = {}
    for tip in tips:
        name = _finger_name(tip)
        if name in chains:
            raise ConfigError(f"URDF {source}: two fingertip links map to finger '{name}'")
        radius = _tip_radius(link_elems[tip], tip)
        chains[name] = _build_chain(name, tip, radius, paths[tip], by_name)
    return chains


# ---------------------------------------------------------------------- kinematics


@dataclass(frozen=True, eq=False)
class ChainStack:
    """Finger chains prepared for forward kinematics evaluated all at once, vectorised over a batch of
    configurations and over the chains (:func:`chain_stack` builds and caches it).

    The chains' joint vectors are concatenated, in order, into one vector of length ``n``
    (``starts[c]`` is where chain ``c``'s begins). Chain ``c`` has ``length[c]`` joints, padded with
    fixed identity joints to ``L = max(length)``. Per joint, arrays ``(L, C, ...)`` (joint index
    first): joint ``(l, c)`` takes the value ``gain * q[column] + offset`` (``plain``: every gain is 1
    or 0 and every offset 0, so the value is ``q[column]``). Its transform, origin times motion, is
    linear in the coefficients ``(cos value, sin value, 1, value)``: ``basis`` ``(L, C, K, 16)``
    holds the flattened 4 x 4 matrix of each coefficient (Rodrigues' formula split by coefficient
    for a revolute joint, the shift for a prismatic one, the origin alone for a fixed or padding
    joint, whose value is then irrelevant; ``K = 3`` without prismatic joints). ``axis``
    ``(L, C, 3, 1)`` is its unit axis in its own frame (0 for a fixed joint); ``prismatic``
    ``(L, C)`` its kind. ``select`` ``(C, L, n)`` is ``d value / d q`` (the Jacobian's scatter: a
    mimic joint adds to its driver; zero for a fixed joint).
    """

    chains: tuple[FingerChain, ...]
    n: int
    starts: tuple[int, ...]
    length: tuple[int, ...]
    basis: NDArray[np.float64]
    axis: NDArray[np.float64]
    prismatic: NDArray[np.bool_]
    column: NDArray[np.intp]
    gain: NDArray[np.float64]
    offset: NDArray[np.float64]
    select: NDArray[np.float64]
    has_prismatic: bool
    plain: bool


@lru_cache(maxsize=64)
def chain_stack(chains: tuple[FingerChain, ...]) -> ChainStack:
    """The :class:`ChainStack` of ``chains`` (cached per tuple of chain objects)."""
    C = len(chains)
    L = max(len(c.joints) for c in chains)
    dofs = [c.dof for c in chains]
    starts = tuple(int(s) for s in np.concatenate([[0], np.cumsum(dofs)[:-1]]))
    n = int(sum(dofs))
    origin = np.tile(np.eye(4), (L, C, 1, 1))
    axis = np.zeros((L, C, 3))
    revolute = np.zeros((L, C), dtype=bool)
    prismatic = np.zeros((L, C), dtype=bool)
    column = np.zeros((L, C), dtype=np.intp)
    gain = np.zeros((L, C))
    offset = np.zeros((L, C))
    select = np.zeros((C, L, n))
    for c, chain in enumerate(chains):
        for l, (joint, k, g, b) in enumerate(
            zip(chain.joints, chain.drive_index, chain.drive_gain, chain.drive_offset, strict=True)
        ):
            origin[l, c] = joint.origin
            if k < 0:
                continue
            axis[l, c] = joint.axis
            revolute[l, c] = joint.kind == "revolute"
            prismatic[l, c] = joint.kind == "prismatic"
            column[l, c] = starts[c] + k
            gain[l, c], offset[l, c] = g, b
            select[c, l, starts[c] + k] = g
    # A revolute joint's motion is [[c (I - A) + s K + A, 0], [0, 1]] (A = a a^T, K = [a]x), a
    # prismatic one's [[I, t a], [0, 1]] (t its shift), a fixed one's I: each picks its coefficients.
    rev = revolute[..., None, None]
    A = np.where(rev, axis[..., :, None] * axis[..., None, :], 0.0)
    motion = np.zeros((L, C, 4, 4, 4))
    motion[:, :, 0, :3, :3] = np.where(rev, np.eye(3) - A, 0.0)
    motion[:, :, 1, :3, :3] = np.where(rev, -(axis @ _LEVI_CIVITA).reshape(L, C, 3, 3), 0.0)
    motion[:, :, 2] = np.where(rev, 0.0, np.eye(4))
    motion[:, :, 2, :3, :3] += A
    motion[:, :, 2, 3, 3] = 1.0
    motion[:, :, 3, :3, 3] = np.where(prismatic[..., None], axis, 0.0)
    K = 4 if prismatic.any() else 3
    arrays = {
        "basis": (origin[:, :, None] @ motion[:, :, :K]).reshape(L, C, K, 16),
        "axis": axis[..., None],
        "prismatic": prismatic,
        "column": column,
        "gain": gain,
        "offset": offset,
        "select": select,
    }
    for a in arrays.values():
        a.setflags(write=False)
    length = tuple(len(c.joints) for c in chains)
    plain = bool(np.all((gain == 1.0) | (gain == 0.0)) and not offset.any())
    return ChainStack(chains, n, starts, length, **arrays, has_prismatic=K == 4, plain=plain)


class Kinematics(NamedTuple):
    """Forward kinematics of a :class:`ChainStack` for a batch of ``B`` configurations.

    tips: fingertip sphere centres, ``(B, C, 3)`` [m].
    jacobian: ``d tips / d q``, ``(B, C, 3, n)`` (``None`` if not asked for).
    origins: every joint's origin in root-to-tip order, ``(B, C, L, 3)`` [m], padding joints
        repeating the fingertip (``None`` if not asked for).
    """

    tips: NDArray[np.float64]
    jacobian: NDArray[np.float64] | None
    origins: NDArray[np.float64] | None


def _values(stack: ChainStack, q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Every joint's value ``(L, B, C)`` for the stacked joint vectors ``q`` ``(B, n)`` (a fixed
    joint's value is arbitrary when the stack is ``plain``)."""
    value = np.take(q, stack.column, axis=1).transpose(1, 0, 2)
    return value if stack.plain else value * stack.gain[:, None] + stack.offset[:, None]


def local_transforms(
    stack: ChainStack,
    q: NDArray[np.float64],
    rot: NDArray[np.float64] | None = None,
    pos: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Each joint's transform (its origin times its motion) for each row of ``q`` ``(B, n)``:
    ``(L, B, C, 4, 4)``, preceded by the palm's pose (``rot`` ``(B, 3, 3)``, ``pos`` ``(B, 3)``, both
    or neither) if given: ``(1 + L, B, C, 4, 4)``. Their product, root to tip, is the chain."""
    B = q.shape[0]
    L, C, K = stack.basis.shape[:3]
    value = _values(stack, q)
    coef = np.ones((L, B, C, 1, K))
    np.cos(value, out=coef[..., 0, 0])
    np.sin(value, out=coef[..., 0, 1])
    if stack.has_prismatic:
        coef[..., 0, 3] = value
    root = rot is not None
    E = np.empty((L + root, B, C, 1, 16))
    np.matmul(coef, stack.basis[:, None], out=E[root:])
    E = E.reshape(L + root, B, C, 4, 4)
    if root:
        assert rot is not None and pos is not None
        E[0, :, :, :3, :3] = rot[:, None]
        E[0, :, :, :3, 3] = pos[:, None]
        E[0, :, :, 3] = (0.0, 0.0, 0.0, 1.0)
    return E


def chain_product(E: NDArray[np.float64]) -> NDArray[np.float64]:
    """The product ``E[0] @ E[1] @ ... `` of transforms ``(K, ..., 4, 4)`` (pairwise, log2 K rounds)."""
    while len(E) > 1:
        half = len(E) // 2
        P = E[0 : 2 * half : 2] @ E[1 : 2 * half : 2]
        E = np.concatenate([P, E[-1:]]) if len(E) % 2 else P
    return E[0]


def chain_frames(E: NDArray[np.float64]) -> NDArray[np.float64]:
    """The prefix products ``E[0] @ ... @ E[k]`` of transforms ``(K, ..., 4, 4)`` (a new array;
    Hillis-Steele scan, log2 K rounds)."""
    P = E.copy()
    d = 1
    while d < len(P):
        P[d:] = P[:-d] @ P[d:]
        d *= 2
    return P


def frame_kinematics(
    stack: ChainStack,
    frames: NDArray[np.float64],
    q: NDArray[np.float64],
    *,
    jacobian: bool = False,
    origins: bool = False,
) -> Kinematics:
    """:class:`Kinematics` from the frames ``(L, B, C, 4, 4)`` after each joint (the prefix products
    of :func:`local_transforms` without the palm's) for the joint vectors ``q`` ``(B, n)``.

    A revolute joint's Jacobian column is ``a x (p_tip - p_joint)``, a prismatic one's ``a`` (``a``
    the joint axis in the output frame); a mimic joint adds its column times its multiplier to
    its driver's.
    """
    L, B, C = frames.shape[:3]
    tips = frames[-1, :, :, :3, 3]
    if not (jacobian or origins):
        return Kinematics(tips, None, None)
    o = frames[..., :3, 3]  # a revolute or fixed joint does not move its own origin
    a = None
    if stack.has_prismatic or jacobian:
        a = (frames[..., :3, :3] @ stack.axis[:, None])[..., 0]  # joint axes, (L, B, C, 3)
        if stack.has_prismatic:
            o = o - np.where(stack.prismatic[:, None], _values(stack, q), 0.0)[..., None] * a
    J = None
    if jacobian:
        assert a is not None
        neg_cross = (a @ _LEVI_CIVITA).reshape(L, B, C, 3, 3)  # -[a]x
        col = (neg_cross @ (o - tips)[..., None])[..., 0]  # a x (tip - o), (L, B, C, 3)
        if stack.has_prismatic:
            col = np.where(stack.prismatic[:, None, :, None], a, col)
        J = col.transpose(1, 2, 3, 0) @ stack.select  # fixed joints have zero rows in select
    return Kinematics(tips, J, o.transpose(1, 2, 0, 3) if origins else None)


def stack_kinematics(
    stack: ChainStack,
    q: NDArray[np.float64],
    rot: NDArray[np.float64] | None = None,
    pos: NDArray[np.float64] | None = None,
    *,
    jacobian: bool = False,
    origins: bool = False,
) -> Kinematics:
    """Fingertips (and optionally the Jacobian and joint origins) of every chain of ``stack`` for each
    row of ``q`` ``(B, n)`` (validated by the caller), in the frame where the palm has rotation
    ``rot`` ``(B, 3, 3)`` and origin ``pos`` ``(B, 3)`` (both or neither; default: the palm frame).
    See :func:`local_transforms` and :func:`frame_kinematics`."""
    E = local_transforms(stack, q, rot, pos)
    if not (jacobian or origins):
        return Kinematics(chain_product(E)[..., :3, 3], None, None)
    frames = chain_frames(E)
    return frame_kinematics(stack, frames[rot is not None :], q, jacobian=jacobian, origins=origins)


def _kinematics(
    chain: FingerChain,
    q: NDArray[np.float64],
    with_jacobian: bool,
    origins: list[NDArray[np.float64]] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Fingertip centre and (optionally) its positional Jacobian for an already validated ``q``;
    ``origins``, if given, receives each joint's origin in root-to-tip order."""
    k = stack_kinematics(chain_stack((chain,)), q[None], jacobian=with_jacobian, origins=origins is not None)
    if origins is not None:
        assert k.origins is not None
        origins.extend(k.origins[0, 0, : len(chain.joints)])
    return k.tips[0, 0], None if k.jacobian is None else k.jacobian[0, 0]


@dataclass(frozen=True, eq=False)
class HandModel:
    """Kinematic model of a hand: ``fingers`` maps finger names to their :class:`FingerChain`."""

    fingers: Mapping[str, FingerChain]
    source: str = "<memory>"

    @classmethod
    def from_urdf(cls, path: str | os.PathLike[str]) -> HandModel:
        """Read a URDF file; :class:`ConfigError` for a missing, malformed or unusable description."""
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"URDF file {p} does not exist")
        try:
            text = p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"URDF file {p} cannot be read: {exc}") from None
        return cls(MappingProxyType(_parse_urdf(text, str(p))), str(p))

    @classmethod
    def default(cls) -> HandModel:
        """The packaged Shadow-like hand (``shadow_like.urdf``): fingers thumb, first, middle."""
        res = resources.files("softgrasp.hand").joinpath("shadow_like.urdf")
        return cls(MappingProxyType(_parse_urdf(res.read_text(encoding="utf-8"), str(res))), str(res))

    def chain(self, finger: str) -> FingerChain:
        """The chain of ``finger``; :class:`ConfigError` naming the known fingers otherwise."""
        try:
            return self.fingers[finger]
        except (KeyError, TypeError):
            raise ConfigError(f"unknown finger {finger!r}; this hand has {', '.join(self.fingers)}") from None

    def joint_names(self, finger: str) -> tuple[str, ...]:
        """Names of the finger's independent joints, the order of its ``q``."""
        return self.chain(finger).joint_names

    def limits(self, finger: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Effective lower and upper limits of the finger's independent joints [rad or m] (copies)."""
        c = self.chain(finger)
        return c.lower.copy(), c.upper.copy()

    def fingertip_radius(self, finger: str) -> float:
        """Radius [m] of the finger's fingertip sphere."""
        return self.chain(finger).radius

    def _q(self, finger: str, q: ArrayLike) -> tuple[FingerChain, NDArray[np.float64]]:
        chain = self.chain(finger)
        v = np.asarray(q, dtype=np.float64)
        if v.shape != (chain.dof,) or not np.all(np.isfinite(v)):
            raise ConfigError(
                f"the {finger} joint vector must be {chain.dof} finite values {chain.joint_names}; "
                f"got shape {v.shape}"
            )
        return chain, v

    def forward(self, finger: str, q: ArrayLike) -> NDArray[np.float64]:
        """Fingertip sphere centre ``(3,)`` [m] in the palm frame; mimic joints follow ``q``."""
        chain, v = self._q(finger, q)
        return _kinematics(chain, v, False)[0]

    def link_points(self, finger: str, q: ArrayLike) -> NDArray[np.float64]:
        """Origins of the finger's joints in root-to-tip order, then the fingertip centre, ``(k + 1,
        3)`` [m] in the palm frame: the polyline of its links (for clearance checks and drawings)."""
        chain, v = self._q(finger, q)
        out: list[NDArray[np.float64]] = []
        tip = _kinematics(chain, v, False, out)[0]
        return np.array([*out, tip])

    def jacobian(self, finger: str, q: ArrayLike) -> NDArray[np.float64]:
        """Analytic positional Jacobian ``d tip / d q``, shape ``(3, dof)``.

        Revolute joint column ``a x (p_tip - p_joint)``, prismatic ``a`` (``a`` the joint axis in
        the palm frame); a mimic joint adds its column times its multiplier to its driver's.
        """
        chain, v = self._q(finger, q)
        J = _kinematics(chain, v, True)[1]
        assert J is not None
        return J


# ---------------------------------------------------------------------- WDLS


def _weights(W: ArrayLike | None, n: int) -> NDArray[np.float64]:
    if W is None:
        return np.ones(n)
    w = np.asarray(W, dtype=np.float64)
    if w.shape == (n, n):
        if np.any(w - np.diag(np.diag(w))):
            raise ConfigError("the weight matrix W must be diagonal")
        w = np.diag(w).copy()
    if w.shape != (n,):
        raise ConfigError(f"the weights W must have shape ({n},) or ({n}, {n}); got {w.shape}")
    if not (np.all(np.isfinite(w)) and np.all(w > 0.0)):
        raise ConfigError("the weights W must be finite and > 0")
    return w


def wdls_step(
    J: ArrayLike, dx: ArrayLike, W: ArrayLike | None = None, damping: float = 1e-3
) -> NDArray[np.float64]:
    """Weighted damped least-squares step ``dq = W^-1 J^T (J W^-1 J^T + lambda^2 I)^-1 dx``.

    Minimises ``|J dq - dx|^2 + lambda^2 dq^T W dq`` (Nakamura and Hanafusa; Chiaverini's WDLS).
    ``J`` is ``(m, n)``, ``dx`` ``(m,)``, ``W`` a positive diagonal joint weight given as its
    diagonal ``(n,)`` or as an ``(n, n)`` diagonal matrix (default identity; a heavier joint moves
    less) and ``damping`` is ``lambda >= 0`` [units of J]. With ``damping = 0`` this is the weighted
    pseudo-inverse ``W^-1 J^T (J W^-1 J^T)^-1 dx``; for a rank-deficient ``J`` the Moore-Penrose
    inverse of ``J W^-1 J^T`` is then used.
    """
    Jm = np.asarray(J, dtype=np.float64)
    if Jm.ndim != 2 or Jm.shape[0] == 0 or Jm.shape[1] == 0 or not np.all(np.isfinite(Jm)):
        raise ConfigError(f"J must be a finite, non-empty (m, n) matrix; got shape {Jm.shape}")
    m, n = Jm.shape
    d = np.asarray(dx, dtype=np.float64)
    if d.shape != (m,) or not np.all(np.isfinite(d)):
        raise ConfigError(f"dx must be {m} finite values; got shape {d.shape}")
    lam = float(damping)
    if not (math.isfinite(lam) and lam >= 0.0):
        raise ConfigError(f"damping = {damping} is invalid: it must be finite and >= 0")
    winv = 1.0 / _weights(W, n)
    JW = Jm * winv  # J W^-1
    A = JW @ Jm.T
    if lam > 0.0:
        A[np.diag_indices(m)] += lam * lam
        y = np.linalg.solve(A, d)
    else:
        y = np.linalg.pinv(A) @ d
    return JW.T @ y


# ---------------------------------------------------------------------- inverse kinematics


def _limited_step(
    J: NDArray[np.float64],
    dx: NDArray[np.float64],
    q: NDArray[np.float64],
    lower: NDArray[np.float64],
    upper: NDArray[np.float64],
    w: NDArray[np.float64],
    damping: float,
) -> NDArray[np.float64]:
    """WDLS step in which joints at a limit that the step would push further out are frozen.

    The step is computed with all joints; every joint sitting at a limit whose step points out of
    its range is removed (its column dropped, i.e. infinite weight) and the step recomputed with the
    remaining joints, until no removed-worthy joint is left.
    """
    return _limited_steps(J[None], dx[None], q[None], lower, upper, 1.0 / w, damping)[0]


def _limited_steps(
    J: NDArray[np.float64],
    dx: NDArray[np.float64],
    q: NDArray[np.float64],
    lower: NDArray[np.float64],
    upper: NDArray[np.float64],
    winv: NDArray[np.float64],
    damping: float,
) -> NDArray[np.float64]:
    """:func:`_limited_step` for a batch: ``J`` ``(B, m, n)``, ``dx`` ``(B, m)``, ``q`` ``(B, n)``;
    ``lower``, ``upper`` and the inverse joint weights ``winv`` ``(n,)``. Returns ``dq`` ``(B, n)``.

    A frozen joint gets the inverse weight 0 (the same as dropping its column: its step is exactly
    0 and it adds nothing to ``J W^-1 J^T``).
    """
    at_lower = q <= lower + LIMIT_EPS
    at_upper = q >= upper - LIMIT_EPS
    free = ~(at_lower & at_upper)  # a joint with lower == upper never moves
    outward = at_upper.astype(np.float64) - at_lower  # the sign of a step out of the range, or 0
    JT = J.transpose(0, 2, 1)
    damp = damping * damping * np.eye(J.shape[1])
    while True:  # every row again (a row's result does not depend on the others)
        JW = J * (winv * free)[:, None, :]  # J W^-1 with the frozen columns zeroed
        A = JW @ JT
        if damping > 0.0:
            y = np.linalg.solve(A + damp, dx[..., None])
        else:
            y = np.linalg.pinv(A) @ dx[..., None]
        dq = (JW.transpose(0, 2, 1) @ y)[..., 0]
        blocked = free & (dq * outward > 0.0)
        if not blocked.any():
            return dq
        free &= ~blocked


def _descend(
    chain: FingerChain,
    target: NDArray[np.float64],
    q: NDArray[np.float64],
    w: NDArray[np.float64],
    damping: float,
    tol: float,
    max_iter: int,
) -> tuple[NDArray[np.float64], float]:
    """Clamped WDLS iterations from ``q`` (inside the limits); returns the last ``q`` and its error."""
    lower, upper = chain.lower, chain.upper
    tip, J = _kinematics(chain, q, True)
    e = target - tip
    err = float(np.linalg.norm(e))
    history = [err]
    for _ in range(max_iter):
        if err <= tol:
            break
        if len(history) > STALL_WINDOW and history[-1 - STALL_WINDOW] - err < STALL_FRACTION * err:
            break  # stalled
        dx = e if err <= MAX_CARTESIAN_STEP else e * (MAX_CARTESIAN_STEP / err)
        assert J is not None
        dq = _limited_step(J, dx, q, lower, upper, w, damping)
        if not np.any(dq):
            break
        alpha = 1.0
        for _ in range(MAX_HALVINGS):
            q_try = np.clip(q + alpha * dq, lower, upper)
            tip_try = _kinematics(chain, q_try, False)[0]
            err_try = float(np.linalg.norm(target - tip_try))
            if err_try < err:
                break
            alpha *= 0.5
        else:
            break  # no progress: a local minimum of the distance within the limits
        q = q_try
        tip, J = _kinematics(chain, q, True)
        e = target - tip
        err = float(np.linalg.norm(e))
        history.append(err)
    return q, err


def _point(v: ArrayLike, what: str) -> NDArray[np.float64]:
    p = np.asarray(v, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ConfigError(f"{what} must be 3 finite coordinates [m]; got shape {p.shape}")
    return p


def _mm(p: NDArray[np.float64]) -> str:
    """``(x, y, z)`` in mm with one decimal, for messages."""
    return "(" + ", ".join(f"{1e3 * v:.1f}" for v in p) + ")"


def _ik_options(
    model: HandModel, finger: str, q0: ArrayLike, damping: float, weights: ArrayLike | None
) -> tuple[FingerChain, NDArray[np.float64], NDArray[np.float64], float]:
    chain, q = model._q(finger, q0)
    lam = float(damping)
    if not (math.isfinite(lam) and lam >= 0.0):
        raise ConfigError(f"damping = {damping} is invalid: it must be finite and >= 0")
    return chain, np.clip(q, chain.lower, chain.upper), _weights(weights, chain.dof), lam


def solve_ik(
    model: HandModel,
    finger: str,
    target: ArrayLike,
    q0: ArrayLike,
    *,
    damping: float = 1e-3,
    weights: ArrayLike | None = None,
    tol: float = 1e-5,
    max_iter: int = 200,
) -> NDArray[np.float64]:
    """Independent joint vector placing the ``finger``'s fingertip centre at ``target`` [m].

    Iterates WDLS steps (:func:`wdls_step`, joint weights ``weights``, default 1) on the
    fingertip error, each aimed at most :data:`MAX_CARTESIAN_STEP` along the error and shortened
    by halving until the error decreases. Joint limits: ``q0`` is first clipped into the limits;
    at every iteration a joint sitting at a limit whose step would push it further out is removed
    from the step (infinite weight) and the step recomputed with the other joints; the trial
    ``q`` is clipped into the limits, so the result never leaves them. Iterations stop at an error
    ``<= tol`` [m], after ``max_iter`` iterations, when no shortened step decreases the error, or
    when the error fell by less than :data:`STALL_FRACTION` over :data:`STALL_WINDOW` iterations.
    If ``q0`` fails, the mid-range configuration and :data:`IK_RESTARTS` fixed pseudo-random ones
    are tried. :class:`InfeasibleGrasp` names the finger and the closest distance reached.
    """
    chain, q, w, lam = _ik_options(model, finger, q0, damping, weights)
    p = _point(target, "target")
    if not (math.isfinite(tol) and tol > 0.0):
        raise ConfigError(f"tol = {tol} m is invalid: it must be finite and > 0")
    if int(max_iter) != max_iter or max_iter < 1:
        raise ConfigError(f"max_iter = {max_iter} must be an integer >= 1")
    rng = np.random.default_rng(0)
    seeds = [q, 0.5 * (chain.lower + chain.upper)]
    seeds += list(rng.uniform(chain.lower, chain.upper, size=(IK_RESTARTS, chain.dof)))
    best = math.inf
    for seed in seeds:
        q_end, err = _descend(chain, p, seed, w, lam, tol, int(max_iter))
        if err <= tol:
            return q_end
        best = min(best, err)
    raise InfeasibleGrasp(
        f"the {finger} fingertip cannot reach target {_mm(p)} mm: closest {1e3 * best:.3f} mm away"
    )


def track(
    model: HandModel,
    finger: str,
    target: ArrayLike,
    q: ArrayLike,
    *,
    iterations: int = 10,
    damping: float = 1e-3,
) -> NDArray[np.float64]:
    """Joint vector moving the fingertip from its posture ``q`` towards ``target`` (palm frame):
    up to ``iterations`` limit-clamped WDLS iterations, no restarts, so successive calls give a
    continuous motion (a Cartesian controller's inner loop). Never leaves the joint limits."""
    chain, q0, w, lam = _ik_options(model, finger, q, damping, None)
    return _descend(chain, _point(target, "target"), q0, w, lam, 1e-7, int(iterations))[0]


def follow_line(
    model: HandModel,
    finger: str,
    q0: ArrayLike,
    start: ArrayLike,
    end: ArrayLike,
    steps: int,
    *,
    damping: float = 1e-3,
    weights: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Joint trajectory ``(steps + 1, dof)`` moving the fingertip straight from ``start`` to ``end``.

    Row 0 is ``q0`` (clipped into the limits) if its fingertip is within 1e-6 m of ``start``,
    otherwise :func:`solve_ik` from ``q0`` to ``start``. Row ``k`` tracks the line point
    ``start + k / steps (end - start)`` by limit-clamped WDLS iterations (as :func:`solve_ik`,
    without restarts, so the trajectory is continuous) from row ``k - 1``. If the fingertip ends
    a row more than :data:`LINE_TOLERANCE` (0.5 mm) from its commanded point (so possibly off
    the line), :class:`InfeasibleGrasp` names the finger and the step.
    """
    chain, q, w, lam = _ik_options(model, finger, q0, damping, weights)
    a = _point(start, "start")
    b = _point(end, "end")
    if isinstance(steps, bool) or int(steps) != steps or steps < 1:
        raise ConfigError(f"steps = {steps} must be an integer >= 1")
    steps = int(steps)
    if np.linalg.norm(_kinematics(chain, q, False)[0] - a) > 1e-6:
        q = solve_ik(model, finger, a, q, damping=lam, weights=w, tol=1e-7)
    out = np.empty((steps + 1, chain.dof))
    out[0] = q
    for k in range(1, steps + 1):
        point = a + (k / steps) * (b - a)
        q, err = _descend(chain, point, q, w, lam, 1e-7, 50)
        if err > LINE_TOLERANCE:
            raise InfeasibleGrasp(
                f"the {finger} fingertip cannot follow the line from "
                f"{_mm(a)} to {_mm(b)} mm: "
                f"{1e3 * err:.2f} mm off at step {k}/{steps}"
            )
        out[k] = q
    return out
