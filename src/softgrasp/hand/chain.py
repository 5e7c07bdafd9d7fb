"""A hand as a tree of joints between links, and its fingers' serial chains from the palm to the
fingertip spheres.

The readers (:mod:`softgrasp.hand.urdf` for URDF, :mod:`softgrasp.hand.mjcf` for MuJoCo's MJCF)
turn a file into :class:`Joint` records and the collision spheres of its links;
:func:`finger_chains` picks the fingertip links and builds each finger's :class:`FingerChain`.

Fingertips: a mapping ``{finger: link}`` (``thumb=th_tip,first=ff_tip,middle=mf_tip``) names them;
without one, every link named ``<prefix>_tip`` ends a finger, prefixes ``th``, ``ff``, ``mf``
(``rf``, ``lf``) naming the fingers ``thumb``, ``first``, ``middle`` (``ring``, ``little``). The
fingertip is the link's collision sphere: its centre (which may sit off the link origin) is the
fingertip centre and its radius the fingertip radius. A radius given by the caller overrides the
sphere's; a fingertip link without a sphere needs one (its centre is then the link origin).

Joints may be revolute, prismatic or fixed. A joint that mimics another follows
``q = multiplier * q_J + offset``; it is not an independent coordinate of the finger, and the
effective limits of ``J`` are narrowed so that the mimic joint stays inside its own. A finger's
joint vector ``q`` holds its independent joints in root-to-tip order. SI units (m, rad).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError

__all__ = ["FINGER_NAMES", "Joint", "Sphere", "FingerChain", "finger_chains", "parse_fingertips"]

#: Finger name of each tip-link prefix (``ff_tip`` -> ``first``), the default naming of fingertips.
FINGER_NAMES: Mapping[str, str] = MappingProxyType(
    {"th": "thumb", "ff": "first", "mf": "middle", "rf": "ring", "lf": "little"}
)

MOVABLE = ("revolute", "prismatic")
SUPPORTED = ("revolute", "prismatic", "fixed")


@dataclass(frozen=True, eq=False)
class Joint:
    """One joint: ``origin`` is the parent-to-joint transform (4x4), ``axis`` a unit vector in
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
        return self.kind in MOVABLE


@dataclass(frozen=True)
class Sphere:
    """A link's collision sphere: ``radius`` [m] and ``centre`` ``(3,)`` [m] in the link frame."""

    radius: float
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True, eq=False)
class FingerChain:
    """The serial chain of one finger, palm to fingertip.

    ``joints`` are all joints of the chain (fixed ones included) in root-to-tip order, the last
    frame being the fingertip sphere's centre, the frame of ``tip_link`` (the fingertip link, or
    ``<link>:sphere`` where its sphere sits off the link's origin); ``joint_names`` the independent joints, i.e. the
    entries of the finger's ``q``, with their effective limits ``lower``/``upper``. Joint
    ``joints[k]`` moves by ``drive_gain[k] * q[drive_index[k]] + drive_offset[k]``
    (``drive_index[k] = -1``: fixed).
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


def parse_fingertips(text: str) -> dict[str, str]:
    """The mapping ``{finger: link}`` of ``thumb=LINK,first=LINK,middle=LINK``; ConfigError names
    the malformed entry."""
    out: dict[str, str] = {}
    for part in str(text).split(","):
        finger, eq, link = (s.strip() for s in part.partition("="))
        if not eq or not finger or not link:
            raise ConfigError(
                f"--fingertips entry {part.strip()!r} is not FINGER=LINK; write e.g. "
                "thumb=th_tip,first=ff_tip,middle=mf_tip"
            )
        if finger in out:
            raise ConfigError(f"--fingertips names finger {finger!r} twice")
        out[finger] = link
    return out


def _narrow(j: Joint, name: str, k: int, lower: NDArray[np.float64], upper: NDArray[np.float64]) -> None:
    """Narrow the driving joint's range ``k`` so that mimic joint ``j`` stays inside its limits."""
    a, b = j.multiplier, j.offset
    if a == 0.0:
        if not j.lower <= b <= j.upper:
            raise ConfigError(f"joint '{j.name}': mimic offset {b} is outside its limits")
        return
    lo, hi = sorted(((j.lower - b) / a, (j.upper - b) / a))
    lower[k], upper[k] = max(lower[k], lo), min(upper[k], hi)
    if lower[k] > upper[k]:
        raise ConfigError(
            f"joint '{j.name}' of finger '{name}' mimics '{j.mimic}' but their limits are incompatible "
            "(no value of the driving joint keeps both inside their limits)"
        )


def _build_chain(name: str, tip: str, radius: float, path: list[Joint]) -> FingerChain:
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
            if j.mimic not in index:
                raise ConfigError(
                    f"joint '{j.name}' of finger '{name}' mimics joint '{j.mimic}', which is not an "
                    "independent joint of the same finger"
                )
            k = index[j.mimic]
            _narrow(j, name, k, lower, upper)
            drive_index.append(k)
            drive_gain.append(j.multiplier)
            drive_offset.append(j.offset)
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


def _check_joints(joints: Sequence[Joint], links: Sequence[str], source: str) -> dict[str, Joint]:
    """The joints by child link, checked: known links, unique names, a tree, valid mimics."""
    known = set(links)
    by_name: dict[str, Joint] = {}
    parent_joint: dict[str, Joint] = {}
    for j in joints:
        what = f"{source}: joint '{j.name}'"
        if j.kind not in SUPPORTED:
            raise ConfigError(f"{what} has type {j.kind!r}; supported types are {', '.join(SUPPORTED)}")
        for role, link in (("parent", j.parent), ("child", j.child)):
            if link not in known:
                raise ConfigError(f"{what} refers to unknown {role} link '{link}'")
        if j.name in by_name:
            raise ConfigError(f"{source}: joint '{j.name}' is defined twice")
        if j.child in parent_joint:
            raise ConfigError(f"{source}: link '{j.child}' is the child of two joints")
        if j.movable and not j.lower <= j.upper:
            raise ConfigError(f"{what} has limits lower = {j.lower} > upper = {j.upper}")
        by_name[j.name] = j
        parent_joint[j.child] = j
    for j in joints:
        if j.mimic is not None:
            target = by_name.get(j.mimic)
            if target is None:
                raise ConfigError(f"{source}: joint '{j.name}' mimics unknown joint '{j.mimic}'")
            if not target.movable or target.mimic is not None:
                raise ConfigError(
                    f"{source}: joint '{j.name}' mimics '{j.mimic}', which is not an independent moving joint"
                )
    roots = sorted(known - set(parent_joint))
    if len(roots) != 1:
        raise ConfigError(f"{source} must have exactly one root (palm) link; found {roots or 'none'}")
    return parent_joint


def _path_to(link: str, parent_joint: Mapping[str, Joint], source: str) -> list[Joint]:
    path: list[Joint] = []
    seen = {link}
    while link in parent_joint:
        j = parent_joint[link]
        path.append(j)
        link = j.parent
        if link in seen:
            raise ConfigError(f"{source}: the joints form a loop through link '{link}'")
        seen.add(link)
    return path[::-1]


def _default_tips(
    links: Sequence[str], joints: Sequence[Joint], paths: Mapping[str, list[Joint]], source: str
) -> dict[str, str]:
    """The fingertips of the default naming: links ``<prefix>_tip``; every moving chain must end in one."""
    tips = sorted(link for link in links if link.endswith("_tip"))
    has_child = {j.parent for j in joints}
    for leaf in sorted(set(links) - has_child):
        on_finger = leaf in tips or any(j.child in tips for j in paths[leaf])
        if not on_finger and any(j.movable for j in paths[leaf]):
            raise ConfigError(
                f"{source}: the chain ending at link '{leaf}' has no fingertip link; name the fingertip "
                "link '<finger>_tip' (e.g. 'ff_tip') or map the fingertips (--fingertips thumb=LINK,...)"
            )
    if not tips:
        raise ConfigError(
            f"{source} has no fingertip link named '<finger>_tip'; map the fingertips "
            "(--fingertips thumb=LINK,first=LINK,middle=LINK)"
        )
    out: dict[str, str] = {}
    for tip in tips:
        prefix = tip[: -len("_tip")]
        if not prefix:
            raise ConfigError(
                f"{source}: fingertip link '{tip}' has no finger prefix (expected e.g. 'ff_tip')"
            )
        name = FINGER_NAMES.get(prefix.lower(), prefix)
        if name in out:
            raise ConfigError(f"{source}: two fingertip links map to finger '{name}'")
        out[name] = tip
    return out


def finger_chains(
    joints: Sequence[Joint],
    links: Sequence[str],
    spheres: Mapping[str, Sphere],
    source: str,
    fingertips: Mapping[str, str] | None = None,
    radius: float | None = None,
) -> dict[str, FingerChain]:
    """The finger chains, by finger name, of a hand given as its ``joints`` between ``links`` and
    the links' collision ``spheres`` (``source`` names the file in messages).

    ``fingertips`` maps finger names to their fingertip links (default: the ``<prefix>_tip``
    naming); ``radius`` [m] overrides the fingertip spheres' radii. ConfigError for a malformed or
    unusable hand, naming the link or joint and what to change.
    """
    parent_joint = _check_joints(joints, links, source)
    paths = {link: _path_to(link, parent_joint, source) for link in links}
    if fingertips is None:
        tips = _default_tips(links, joints, paths, source)
    else:
        if not fingertips:
            raise ConfigError(
                "--fingertips maps no finger; write e.g. thumb=th_tip,first=ff_tip,middle=mf_tip"
            )
        for finger, link in fingertips.items():
            if link not in paths:
                some = ", ".join(sorted(links)[:12]) + (", ..." if len(links) > 12 else "")
                raise ConfigError(
                    f"--fingertips {finger}={link}: {source} has no link or body '{link}' (it has {some})"
                )
        tips = dict(fingertips)
    if radius is not None and not (math.isfinite(radius) and radius > 0.0):
        raise ConfigError(f"fingertip radius {radius} m is invalid: it must be finite and > 0")
    chains: dict[str, FingerChain] = {}
    for name, tip in tips.items():
        sphere = spheres.get(tip)
        if sphere is None and radius is None:
            raise ConfigError(
                f"{source}: fingertip link '{tip}' ({name}) has no collision sphere giving the fingertip "
                "radius; add a sphere to it or give the radius (--fingertip-radius)"
            )
        r = radius if radius is not None else sphere.radius  # type: ignore[union-attr]
        if not (math.isfinite(r) and r > 0.0):
            raise ConfigError(f"{source}: fingertip link '{tip}' has sphere radius {r} m; it must be > 0")
        path = list(paths[tip])
        centre = (0.0, 0.0, 0.0) if sphere is None else sphere.centre
        end = tip
        if any(c != 0.0 for c in centre):  # the sphere off the link origin: one more fixed frame
            T = np.eye(4)
            T[:3, 3] = centre
            end = f"{tip}:sphere"
            path.append(Joint(end, "fixed", tip, end, T, np.zeros(3), 0.0, 0.0))
        chains[name] = _build_chain(name, end, float(r), path)
    return chains
