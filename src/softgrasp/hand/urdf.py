"""Reading a hand's URDF into its finger chains, through yourdfpy (a maintained URDF library).

yourdfpy parses the file (links, joints with their origins, axes, limits and mimics, collision
geometry); this module turns its joints into :class:`~softgrasp.hand.chain.Joint` records and its
links' collision spheres into fingertip spheres, and :func:`~softgrasp.hand.chain.finger_chains`
builds the fingers (the fingertip mapping, radii and mimic rules are described there). Meshes are
not loaded: only the kinematics and the fingertip spheres matter to the planner.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Mapping
from importlib import resources
from pathlib import Path

import numpy as np

from softgrasp import usercache
from softgrasp.errors import ConfigError
from softgrasp.hand.chain import FINGER_NAMES, MOVABLE, FingerChain, Joint, Sphere, finger_chains

__all__ = ["FINGER_NAMES", "parse_urdf", "read_urdf", "packaged_urdf", "PACKAGED"]

#: The hands packaged with softgrasp: name -> URDF file in :mod:`softgrasp.hand`.
PACKAGED: Mapping[str, str] = {"shadow_like": "shadow_like.urdf", "parallel_jaw": "parallel_jaw.urdf"}


def _number(value: object, what: str) -> float:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ConfigError(f"{what} = {value!r} is not a number") from None
    if not math.isfinite(v):
        raise ConfigError(f"{what} = {value!r} must be finite")
    return v


def _joint(j, source: str) -> Joint:  # type: ignore[no-untyped-def]
    """A yourdfpy joint as a :class:`Joint` (limits and mimic checked)."""
    what = f"{source}: joint '{j.name}'"
    origin = np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=np.float64)
    axis = np.asarray(j.axis if j.axis is not None else (1.0, 0.0, 0.0), dtype=np.float64)
    if origin.shape != (4, 4) or not np.all(np.isfinite(origin)):
        raise ConfigError(f"{what} has an invalid <origin>")
    if axis.shape != (3,) or not np.all(np.isfinite(axis)):
        raise ConfigError(f"{what} axis must be 3 finite numbers")
    lower = upper = 0.0
    mimic, multiplier, offset = None, 1.0, 0.0
    if j.type in MOVABLE:
        norm = float(np.linalg.norm(axis))
        if norm == 0.0:
            raise ConfigError(f"{what} has a zero axis")
        axis = axis / norm
        lim = j.limit
        if lim is None or lim.lower is None or lim.upper is None:
            raise ConfigError(f"{what} has no <limit lower=... upper=...>; every moving joint needs limits")
        lower = _number(lim.lower, f"{what} limit lower")
        upper = _number(lim.upper, f"{what} limit upper")
        if j.mimic is not None:
            if not j.mimic.joint:
                raise ConfigError(f"{what} has a <mimic> without a joint attribute")
            mimic = str(j.mimic.joint)
            multiplier = _number(1.0 if j.mimic.multiplier is None else j.mimic.multiplier, f"{what} mimic")
            offset = _number(0.0 if j.mimic.offset is None else j.mimic.offset, f"{what} mimic")
    return Joint(str(j.name), str(j.type), str(j.parent), str(j.child), origin, axis, lower, upper,
                 mimic, multiplier, offset)


def _sphere(link, source: str) -> Sphere | None:  # type: ignore[no-untyped-def]
    """The link's first collision sphere (its centre in the link frame), or None."""
    for col in link.collisions:
        geom = col.geometry
        if geom is not None and geom.sphere is not None:
            r = _number(geom.sphere.radius, f"{source}: link '{link.name}' sphere radius")
            centre = (0.0, 0.0, 0.0) if col.origin is None else tuple(float(v) for v in col.origin[:3, 3])
            return Sphere(r, centre)  # type: ignore[arg-type]
    return None


def parse_urdf(
    text: str | bytes,
    source: str,
    fingertips: Mapping[str, str] | None = None,
    radius: float | None = None,
) -> dict[str, FingerChain]:
    """The finger chains, by finger name, of the URDF ``text`` (``source`` names it in messages);
    ``fingertips`` maps finger names to links, ``radius`` [m] overrides the fingertip spheres'.
    :class:`ConfigError` for a malformed or unusable description."""
    data = text.encode("utf-8") if isinstance(text, str) else text
    joints, links, spheres = _robot(data, source)
    return finger_chains(joints, links, spheres, f"URDF {source}", fingertips, radius)


#: The modules whose sources decide what :func:`_robot` returns (they key its cache entries).
_READING_MODULES = ("softgrasp.hand.urdf", "softgrasp.hand.chain")


def _robot(data: bytes, source: str) -> tuple[list[Joint], list[str], dict[str, Sphere]]:
    """The joints, link names and collision spheres of the URDF ``data``: read by yourdfpy once,
    then from softgrasp's cache folder (:mod:`softgrasp.usercache`; yourdfpy and the mesh library
    it loads take about half a second to import), keyed by the file's bytes, the library's version
    and this module's source."""
    from importlib.metadata import version

    key = usercache.entry_key(
        "urdf", data, version("yourdfpy"), usercache.source_digest(*_READING_MODULES)
    )
    kept = _kept(key)
    if kept is not None:
        return kept
    with usercache.making("hands", key):
        kept = _kept(key)  # read meanwhile by another process
        if kept is not None:
            return kept
        joints, links, spheres = _read(data, source)
        usercache.store("hands", key, _pack(joints, links, spheres))
    return joints, links, spheres


def _kept(key: str) -> tuple[list[Joint], list[str], dict[str, Sphere]] | None:
    """The hand kept under ``key``, or None (none, or a damaged entry: the file is read again)."""
    kept = usercache.load("hands", key)
    if kept is None:
        return None
    try:
        return _unpack(kept)
    except (KeyError, ValueError, IndexError):
        return None


def _pack(joints: list[Joint], links: list[str], spheres: dict[str, Sphere]) -> dict[str, np.ndarray]:
    text = {f: np.array([str(getattr(j, f) or "") for j in joints], dtype=str)
            for f in ("name", "kind", "parent", "child", "mimic")}
    num = {f: np.array([getattr(j, f) for j in joints], dtype=np.float64)
           for f in ("lower", "upper", "multiplier", "offset")}
    return {
        **{f"joint_{f}": v for f, v in (text | num).items()},
        "joint_origin": np.array([j.origin for j in joints], dtype=np.float64).reshape(-1, 4, 4),
        "joint_axis": np.array([j.axis for j in joints], dtype=np.float64).reshape(-1, 3),
        "joint_has_mimic": np.array([j.mimic is not None for j in joints], dtype=bool),
        "links": np.array(links, dtype=str),
        "sphere_link": np.array(list(spheres), dtype=str),
        "sphere_radius": np.array([s.radius for s in spheres.values()], dtype=np.float64),
        "sphere_centre": np.array([s.centre for s in spheres.values()], dtype=np.float64).reshape(-1, 3),
    }


def _unpack(a: dict[str, np.ndarray]) -> tuple[list[Joint], list[str], dict[str, Sphere]]:
    joints = [
        Joint(str(a["joint_name"][i]), str(a["joint_kind"][i]), str(a["joint_parent"][i]),
              str(a["joint_child"][i]), a["joint_origin"][i].copy(), a["joint_axis"][i].copy(),
              float(a["joint_lower"][i]), float(a["joint_upper"][i]),
              str(a["joint_mimic"][i]) if a["joint_has_mimic"][i] else None,
              float(a["joint_multiplier"][i]), float(a["joint_offset"][i]))
        for i in range(len(a["joint_name"]))
    ]
    spheres = {
        str(link): Sphere(float(r), tuple(float(v) for v in c))  # type: ignore[arg-type]
        for link, r, c in zip(a["sphere_link"], a["sphere_radius"], a["sphere_centre"], strict=True)
    }
    return joints, [str(n) for n in a["links"]], spheres


def _read(data: bytes, source: str) -> tuple[list[Joint], list[str], dict[str, Sphere]]:
    """:func:`_robot` through yourdfpy: :class:`ConfigError` for a malformed description."""
    from lxml import etree
    from yourdfpy import URDF

    try:
        root = etree.fromstring(data, etree.XMLParser(remove_blank_text=True))
    except etree.XMLSyntaxError as exc:
        raise ConfigError(f"URDF {source} is not well-formed XML: {exc}") from None
    if root.tag != "robot":
        raise ConfigError(f"URDF {source}: the root element is <{root.tag}>, expected <robot>")
    if root.get("name") is None:
        root.set("name", "hand")  # yourdfpy needs a robot name; softgrasp does not
    for tag in ("link", "joint"):
        for e in root.findall(tag):
            if not e.get("name"):
                raise ConfigError(f"URDF {source}: a <{tag}> has no name")
    for e in root.findall("joint"):
        for end in ("parent", "child"):
            if e.find(end) is None or not e.find(end).get("link"):
                raise ConfigError(f"URDF {source}: joint '{e.get('name')}' has no <{end} link=...>")
    try:
        model = URDF.load(
            io.BytesIO(etree.tostring(root)),
            build_scene_graph=False,
            build_collision_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
        )
    except (ValueError, KeyError, AttributeError, IndexError, TypeError) as exc:
        raise ConfigError(f"URDF {source} cannot be read: {exc}") from None
    robot = model.robot
    links = [str(link.name) for link in robot.links]
    if not links:
        raise ConfigError(f"URDF {source} defines no <link>")
    if len(set(links)) != len(links):
        dup = next(n for n in links if links.count(n) > 1)
        raise ConfigError(f"URDF {source}: link '{dup}' is defined twice")
    joints = [_joint(j, f"URDF {source}") for j in robot.joints]
    spheres = {}
    for link in robot.links:
        s = _sphere(link, f"URDF {source}")
        if s is not None:
            spheres[str(link.name)] = s
    return joints, links, spheres


def read_urdf(
    path: str | os.PathLike[str],
    fingertips: Mapping[str, str] | None = None,
    radius: float | None = None,
) -> dict[str, FingerChain]:
    """:func:`parse_urdf` of the file ``path``; :class:`ConfigError` if it is missing or unreadable."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"URDF file {p} does not exist")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"URDF file {p} cannot be read: {exc}") from None
    return parse_urdf(data, str(p), fingertips, radius)


def packaged_urdf(
    name: str = "shadow_like", radius: float | None = None
) -> tuple[dict[str, FingerChain], str]:
    """The chains of a packaged hand (:data:`PACKAGED`) and the file's package name
    (``package:softgrasp/hand/shadow_like.urdf``: no machine path)."""
    from softgrasp.hand.packaged import PACKAGE_PREFIX

    file = PACKAGED[name]
    res = resources.files("softgrasp.hand").joinpath(file)
    return parse_urdf(res.read_bytes(), file, radius=radius), f"{PACKAGE_PREFIX}hand/{file}"
