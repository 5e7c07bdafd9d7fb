"""Forward kinematics of a multi-finger hand and its analytic positional Jacobian.

:class:`HandModel` is a hand read from a URDF (:mod:`softgrasp.hand.urdf`) or an MJCF
(:mod:`softgrasp.io.mjcf_hand`, through MuJoCo): its fingers' serial chains, each ending at a fingertip sphere. A finger's joint vector ``q`` holds its independent
joints in root-to-tip order; mimic joints follow their drivers. Chains are evaluated through a
:class:`ChainStack` (several chains and a batch of configurations at once) by the compiled
:func:`forward` and :func:`joint_columns`, which the IK descent (:mod:`softgrasp.hand.descent`) calls too.

All positions are in the palm (root link) frame unless a palm pose is given; SI units (m, rad).
Kernels are compiled with Numba (:data:`jit`: ``cache=True``, an on-disk cache, so only the first
run compiles; ``fastmath=False``; ``error_model="numpy"``, a division by zero gives inf/nan like
NumPy).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from types import MappingProxyType
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ConfigError
from softgrasp.hand.chain import FINGER_NAMES, FingerChain, Joint
from softgrasp.hand.reach import HandReach, grasp_fingers

__all__ = [
    "FINGER_NAMES",
    "Joint",
    "FingerChain",
    "HandModel",
    "ChainStack",
    "Kinematics",
    "chain_stack",
    "stack_kinematics",
]

#: ``-[a]x = a @ _LEVI_CIVITA`` (reshaped to 3 x 3): the Levi-Civita symbol as ``eps[k, 3 i + j]``.
_LEVI_CIVITA = np.zeros((3, 9))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI_CIVITA[_k, 3 * _i + _j], _LEVI_CIVITA[_k, 3 * _j + _i] = 1.0, -1.0
_LEVI_CIVITA.setflags(write=False)


@dataclass(frozen=True, eq=False)
class ChainStack:
    """Finger chains as the arrays of the compiled forward kinematics (:func:`softgrasp.hand.fk.forward`), for several
    chains and a batch of configurations at once (:func:`chain_stack` builds and caches it).

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
    ``(L, C)`` its kind; ``lengths`` is ``length`` as an array.
    """

    chains: tuple[FingerChain, ...]
    n: int
    starts: tuple[int, ...]
    length: tuple[int, ...]
    basis: NDArray[np.float64]
    axis: NDArray[np.float64]
    prismatic: NDArray[np.bool_]
    column: NDArray[np.int64]
    gain: NDArray[np.float64]
    offset: NDArray[np.float64]
    lengths: NDArray[np.int64]
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
    column = np.zeros((L, C), dtype=np.int64)
    gain = np.zeros((L, C))
    offset = np.zeros((L, C))
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
        "lengths": np.array([len(c.joints) for c in chains], dtype=np.int64),
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

    Each chain's transforms are multiplied root to tip (:func:`softgrasp.hand.fk.forward`). A revolute joint's
    Jacobian column is ``a x (p_tip - p_joint)``, a prismatic one's ``a`` (``a`` the joint axis in
    the output frame); a mimic joint adds its column times its multiplier to its driver's.
    """
    from softgrasp.hand.fk import batch  # compiled: imported at the first use, not with the model

    qa = np.ascontiguousarray(q, dtype=np.float64)
    B = qa.shape[0]
    if rot is None:
        R = np.broadcast_to(np.eye(3), (B, 3, 3))
        p = np.zeros((B, 3))
    else:
        assert pos is not None
        R, p = rot, pos
    C, L = len(stack.chains), stack.basis.shape[0]
    tips = np.empty((B, C, 3))
    J = np.empty((B if jacobian else 0, C, 3, stack.n))
    o = np.empty((B if origins else 0, C, L, 3))
    batch(
        stack.basis,
        stack.axis,
        stack.prismatic,
        stack.column,
        stack.gain,
        stack.offset,
        stack.lengths,
        np.array(R, dtype=np.float64, order="C"),  # a writable copy (a broadcast identity is read-only): one
        np.array(p, dtype=np.float64, order="C"),  # compiled kernel for every call
        qa,
        tips,
        J,
        o,
    )
    return Kinematics(tips, J if jacobian else None, o if origins else None)


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
    """Kinematic model of a hand: ``fingers`` maps finger names to their :class:`FingerChain`.

    ``source`` names its file (a packaged hand by its package name), ``fingertips`` the finger to
    link mapping it was read with (None: the ``<prefix>_tip`` naming), ``radius`` the fingertip
    radius that overrode the spheres' (None: the spheres'), ``reach`` the initial grasp's coarse
    layout limits (:class:`~softgrasp.hand.reach.HandReach`).
    """

    fingers: Mapping[str, FingerChain]
    source: str = "<memory>"
    fingertips: Mapping[str, str] | None = None
    radius: float | None = None
    reach: HandReach = HandReach()

    @classmethod
    def from_urdf(
        cls,
        path: str | os.PathLike[str],
        fingertips: Mapping[str, str] | None = None,
        radius: float | None = None,
    ) -> HandModel:
        """Read a URDF file (:func:`softgrasp.hand.urdf.read_urdf`); :class:`ConfigError` for a
        missing, malformed or unusable description."""
        from softgrasp.hand.urdf import read_urdf

        chains = read_urdf(path, fingertips, radius)
        return cls(MappingProxyType(chains), str(Path(path)), _frozen(fingertips), radius)

    @classmethod
    def packaged(cls, name: str = "shadow_like", radius: float | None = None) -> HandModel:
        """A hand packaged with softgrasp (:data:`softgrasp.hand.urdf.PACKAGED`): ``shadow_like``
        (thumb, first, middle) or ``parallel_jaw`` (left, right; an 85 mm opening)."""
        from softgrasp.hand.urdf import packaged_urdf

        chains, source = packaged_urdf(name, radius)
        reach = HandReach(max_aperture=0.085) if name == "parallel_jaw" else HandReach()
        return cls(MappingProxyType(chains), source, None, radius, reach)

    @classmethod
    def default(cls) -> HandModel:
        """The packaged Shadow-like hand (``shadow_like.urdf``): fingers thumb, first, middle."""
        return _default_hand()

    def with_reach(self, reach: HandReach) -> HandModel:
        """This hand with other layout limits."""
        return replace(self, reach=reach)

    @property
    def grasp_fingers(self) -> tuple[str, ...]:
        """The fingers the planner uses (:func:`softgrasp.hand.reach.grasp_fingers`), the opposing
        finger first."""
        return grasp_fingers(self.fingers, self.source)

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



def _frozen(m: Mapping[str, str] | None) -> Mapping[str, str] | None:
    return None if m is None else MappingProxyType(dict(m))


@lru_cache(maxsize=1)
def _default_hand() -> HandModel:
    """The packaged Shadow-like hand, read once (its chains are immutable)."""
    return HandModel.packaged("shadow_like")
