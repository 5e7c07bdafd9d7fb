"""Reading a hand's URDF into its finger chains.

The hand is a tree of links rooted at the palm. Every link named ``<prefix>_tip`` ends a finger;
its origin is the fingertip sphere centre and its ``<collision>`` sphere gives the fingertip
radius. The finger is the serial chain of joints from the palm to that link. Prefixes ``th``,
``ff``, ``mf`` (also ``rf``, ``lf``) name the fingers ``thumb``, ``first``, ``middle`` (``ring``,
``little``); any other prefix is used as the finger name.

Joints may be ``revolute``, ``prismatic`` or ``fixed``. A joint with ``<mimic joint="J"
multiplier="a" offset="b"/>`` follows ``q = a q_J + b``; it is not an independent coordinate of the
finger and the effective limits of ``J`` are narrowed so that the mimic joint stays inside its own
limits. A finger's joint vector ``q`` holds its independent joints in root-to-tip order.

Transforms are in the parent link's frame; SI units (m, rad).
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from types import MappingProxyType

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError

__all__ = ["FINGER_NAMES", "Joint", "FingerChain", "parse_urdf", "read_urdf", "packaged_urdf"]

#: Finger name of each tip-link prefix (``ff_tip`` -> ``first``).
FINGER_NAMES: Mapping[str, str] = MappingProxyType(
    {"th": "thumb", "ff": "first", "mf": "middle", "rf": "ring", "lf": "little"}
)

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



def parse_urdf(text: str, source: str) -> dict[str, FingerChain]:
    """The finger chains, by finger name, of the URDF ``text`` (``source`` names it in messages);
    :class:`ConfigError` for a malformed or unusable description."""
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

def read_urdf(path: str | os.PathLike[str]) -> dict[str, FingerChain]:
    """:func:`parse_urdf` of the file ``path``; :class:`ConfigError` if it is missing or unreadable."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"URDF file {p} does not exist")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"URDF file {p} cannot be read: {exc}") from None
    return parse_urdf(text, str(p))


def packaged_urdf() -> tuple[dict[str, FingerChain], str]:
    """The chains of the packaged Shadow-like hand (``shadow_like.urdf``) and the file's name."""
    res = resources.files("softgrasp.hand").joinpath("shadow_like.urdf")
    return parse_urdf(res.read_text(encoding="utf-8"), str(res)), str(res)
