"""Reading a hand file: a URDF (root element ``<robot>``, read through yourdfpy by
:mod:`softgrasp.hand.urdf`) or an MJCF (root ``<mujoco>``, read through MuJoCo's own parser).

An MJCF hand is compiled by MuJoCo (``mujoco.MjSpec.from_file(...).compile()``: default classes,
angles in degrees, ``euler``/``axisangle`` orientations and ``<include>`` files resolved) and its
body tree becomes the finger chains: each body is a link; a body's joints act in its frame, one
after the other, a hinge about its axis through its ``pos`` and a slide along its axis; the first
sphere geom of a body is its collision sphere (its ``pos`` the sphere's centre). A joint equality
``<joint joint1="a" joint2="b" polycoef="c0 c1 0 0 0"/>`` makes ``a`` mimic ``b``
(``q_a = c0 + c1 q_b``). Free joints (a floating hand's root) are left out: softgrasp places the
palm itself. Every hinge and slide of a finger needs a ``range``. The fingertips are named by the
same mapping as a URDF's (bodies instead of links).
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError
from softgrasp.hand.chain import FingerChain, Joint, Sphere, finger_chains
from softgrasp.hand.kinematics import HandModel
from softgrasp.offscreen import prefer_headless_gl

__all__ = ["is_mjcf", "read_hand", "read_mjcf"]


def _root_tag(path: Path) -> str:
    try:
        for _, elem in ET.iterparse(path, events=("start",)):
            return elem.tag
    except ET.ParseError as exc:
        raise ConfigError(f"hand file {path} is not well-formed XML: {exc}") from None
    except OSError as exc:
        raise ConfigError(f"hand file {path} cannot be read: {exc}") from None
    raise ConfigError(f"hand file {path} is empty")


def is_mjcf(path: str | os.PathLike[str]) -> bool:
    """Whether the hand file ``path`` is an MJCF (root element ``<mujoco>``)."""
    return _root_tag(Path(path)) == "mujoco"


def read_hand(
    path: str | os.PathLike[str],
    fingertips: Mapping[str, str] | None = None,
    radius: float | None = None,
) -> HandModel:
    """The hand of a URDF or MJCF file; ConfigError for a missing, malformed or unusable one."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(
            f"hand file {p} does not exist; give shadow_like, parallel_jaw, none, a URDF or an MJCF file"
        )
    if not is_mjcf(p):
        return HandModel.from_urdf(p, fingertips, radius)
    chains = read_mjcf(p, fingertips, radius)
    mapping = None if fingertips is None else MappingProxyType(dict(fingertips))
    return HandModel(MappingProxyType(chains), str(p), mapping, radius)


def _quat_matrix(q: NDArray[np.float64]) -> NDArray[np.float64]:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _shift(p: NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, 3] = p
    return T


def _compile(path: Path):  # type: ignore[no-untyped-def]
    prefer_headless_gl()  # MuJoCo's first import here: execute's pictures render offscreen too
    try:
        import mujoco
    except ImportError:
        raise ConfigError(
            f"reading the MJCF hand {path} needs MuJoCo: pip install 'softgrasp[execute]'"
        ) from None
    try:
        return mujoco, mujoco.MjSpec.from_file(str(path)).compile()
    except (ValueError, RuntimeError) as exc:
        raise ConfigError(f"MJCF {path}: MuJoCo cannot load it: {str(exc).strip()}") from None


def read_mjcf(
    path: str | os.PathLike[str],
    fingertips: Mapping[str, str] | None = None,
    radius: float | None = None,
) -> dict[str, FingerChain]:
    """The finger chains, by finger name, of the MJCF hand ``path`` (see the module's text)."""
    p = Path(path)
    source = f"MJCF {p}"
    mujoco, m = _compile(p)
    names = [m.body(b).name or f"body{b}" for b in range(m.nbody)]
    mimic: dict[int, tuple[int, float, float]] = {}
    for e in range(m.neq):
        if int(m.eq_type[e]) != int(mujoco.mjtEq.mjEQ_JOINT) or m.eq_obj2id[e] < 0:
            continue
        c = np.asarray(m.eq_data[e, :5], dtype=np.float64)
        if np.any(c[2:] != 0.0):
            raise ConfigError(f"{source}: joint equality {e} is not linear (polycoef beyond c1); softgrasp "
                              "follows linear couplings only")
        mimic[int(m.eq_obj1id[e])] = (int(m.eq_obj2id[e]), float(c[1]), float(c[0]))
    joints: list[Joint] = []
    for b in range(1, m.nbody):
        parent = names[m.body_parentid[b]] if m.body_parentid[b] > 0 else None
        frame = np.eye(4)
        frame[:3, :3] = _quat_matrix(np.asarray(m.body_quat[b], dtype=np.float64))
        frame[:3, 3] = m.body_pos[b]
        link, pending = parent, frame  # the frame reached so far, and what is left to pass to the body
        ids = [j for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])
               if int(m.jnt_type[j]) != int(mujoco.mjtJoint.mjJNT_FREE)]
        for k, j in enumerate(ids):
            jname = m.joint(j).name or f"joint{j}"
            kinds = {
                int(mujoco.mjtJoint.mjJNT_HINGE): "revolute",
                int(mujoco.mjtJoint.mjJNT_SLIDE): "prismatic",
            }
            kind = kinds.get(int(m.jnt_type[j]))
            if kind is None:
                raise ConfigError(
                    f"{source}: joint '{jname}' is a ball joint; softgrasp reads hinges and slides"
                )
            if not m.jnt_limited[j]:
                raise ConfigError(f"{source}: joint '{jname}' has no range; every finger joint needs limits")
            if link is None:
                raise ConfigError(f"{source}: the root body '{names[b]}' has a joint; the palm must be fixed "
                                  "or free (softgrasp places it)")
            at = np.asarray(m.jnt_pos[j], dtype=np.float64)
            child = names[b] if k == len(ids) - 1 and not at.any() else f"{names[b]}:{jname}"
            lo, hi = (float(v) for v in m.jnt_range[j])
            target, a, c = mimic.get(j, (-1, 1.0, 0.0))
            joints.append(
                Joint(
                    jname,
                    kind,
                    link,
                    child,
                    pending @ _shift(at),
                    np.asarray(m.jnt_axis[j], dtype=np.float64),
                    lo,
                    hi,
                    None if target < 0 else (m.joint(target).name or f"joint{target}"),
                    a,
                    c,
                )
            )
            link, pending = child, _shift(-at)
        if link is not None and link != names[b]:
            joints.append(Joint(f"{names[b]}:frame", "fixed", link, names[b], pending, np.zeros(3), 0.0, 0.0))
    links = sorted({names[b] for b in range(1, m.nbody)} | {j.child for j in joints})
    spheres: dict[str, Sphere] = {}
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        if b > 0 and int(m.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_SPHERE) and names[b] not in spheres:
            centre = tuple(float(v) for v in m.geom_pos[g])
            spheres[names[b]] = Sphere(float(m.geom_size[g, 0]), centre)  # type: ignore[arg-type]
    return finger_chains(joints, links, spheres, source, fingertips, radius)
