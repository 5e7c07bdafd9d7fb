"""What a MuJoCo grasp scene is made of: :class:`SceneSpec`, checked on construction.

The hand and its starting posture, the palm pose, the soft object (nodes, tetrahedra, mass and
material), the friction coefficients, the table height and the simulation's time step and flex
damping, in SI units (m, kg, Pa, s), world frame z up. :func:`softgrasp.execution.mujoco.mjcf.build_mjcf`
writes it as MJCF.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ConfigError, MaterialError, MeshError
from softgrasp.execution.mujoco.options import DEFAULT_DAMPING, DEFAULT_TIMESTEP
from softgrasp.hand.kinematics import HandModel

__all__ = ["SceneSpec", "positive", "rigid_transform"]


def rigid_transform(T: ArrayLike, what: str) -> NDArray[np.float64]:
    """``T`` as a read-only 4x4 rigid transform; :class:`ConfigError` naming ``what`` if it is not one."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise ConfigError(f"{what} must be a finite 4x4 transform; got shape {M.shape}")
    R = M[:3, :3]
    if (
        np.abs(R.T @ R - np.eye(3)).max() > 1e-6
        or np.linalg.det(R) <= 0.0
        or np.abs(M[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-12
    ):
        raise ConfigError(f"{what} must be a rigid transform (rotation with det +1, last row 0 0 0 1)")
    M = M.copy()
    M.setflags(write=False)
    return M


def positive(value: float, what: str, unit: str, error: type[Exception] = ConfigError) -> float:
    """``value`` as a float, or ``error`` naming ``what`` [``unit``] unless it is finite and > 0."""
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise error(f"{what} = {value} {unit} is invalid: it must be finite and > 0 {unit}".rstrip())
    return v


@dataclass(frozen=True, eq=False)
class SceneSpec:
    """Everything :func:`build_mjcf` needs; SI units (m, kg, Pa, s), world frame z up.

    Attributes
    ----------
    hand:
        The hand's kinematic model.
    palm_pose:
        ``(4, 4)`` transform from the palm (root link) frame to the world.
    q0:
        Initial independent joint vector of each finger (finger name -> ``q``, the order of
        :meth:`HandModel.joint_names`), inside the finger's limits. A finger left out starts at
        ``0`` clipped into its limits.
    points:
        ``(N, 3)`` object node positions in the world [m], resting on the table.
    tets:
        ``(M, 4)`` positively oriented tetrahedra (node indices).
    mass:
        Object total mass [kg], spread evenly over the nodes by MuJoCo's flexcomp.
    young, poisson:
        Object Young's modulus [Pa] and Poisson's ratio, ``0 <= poisson < 0.5``.
    mu:
        Fingertip-object Coulomb friction coefficient.
    table_z:
        Height of the table top [m]; no node may start below it.
    table_mu:
        Table-object friction coefficient.
    timestep:
        Simulation time step [s] (:data:`DEFAULT_TIMESTEP`).
    damping:
        Rayleigh damping time of the flex elasticity [s] (:data:`DEFAULT_DAMPING`): the damping
        matrix is ``damping`` times the elastic stiffness matrix, so a mode of angular frequency
        ``w`` gets damping ratio ``damping * w / 2``.
    """

    hand: HandModel
    palm_pose: NDArray[np.float64]
    q0: Mapping[str, NDArray[np.float64]]
    points: NDArray[np.float64]
    tets: NDArray[np.int64]
    mass: float
    young: float
    poisson: float
    mu: float
    table_z: float
    table_mu: float = 0.5
    timestep: float = DEFAULT_TIMESTEP
    damping: float = DEFAULT_DAMPING

    def __post_init__(self) -> None:
        if not isinstance(self.hand, HandModel):
            raise ConfigError(f"hand must be a HandModel, got {type(self.hand).__name__}")
        set_ = object.__setattr__
        set_(self, "palm_pose", rigid_transform(self.palm_pose, "palm_pose"))
        if not isinstance(self.q0, Mapping):
            raise ConfigError("q0 must map finger names to joint vectors")
        q0: dict[str, NDArray[np.float64]] = {}
        for finger in self.q0:
            if finger not in self.hand.fingers:
                raise ConfigError(
                    f"q0 names unknown finger {finger!r}; this hand has {', '.join(self.hand.fingers)}"
                )
        for finger, chain in self.hand.fingers.items():
            if finger in self.q0:
                q = np.asarray(self.q0[finger], dtype=np.float64)
                if q.shape != (chain.dof,) or not np.all(np.isfinite(q)):
                    raise ConfigError(
                        f"q0[{finger!r}] must be {chain.dof} finite values {chain.joint_names}; "
                        f"got shape {q.shape}"
                    )
                tol = 1e-9
                if np.any(q < chain.lower - tol) or np.any(q > chain.upper + tol):
                    raise ConfigError(
                        f"q0[{finger!r}] = {np.round(q, 4).tolist()} is outside the finger's joint limits "
                        f"{np.round(chain.lower, 4).tolist()} .. {np.round(chain.upper, 4).tolist()}"
                    )
                q = np.clip(q, chain.lower, chain.upper)
            else:
                q = np.clip(np.zeros(chain.dof), chain.lower, chain.upper)
            q.setflags(write=False)
            q0[finger] = q
        set_(self, "q0", MappingProxyType(q0))

        pts = np.asarray(self.points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 4 or not np.all(np.isfinite(pts)):
            raise MeshError(f"points must be (N, 3) finite coordinates with N >= 4; got shape {pts.shape}")
        tets = np.asarray(self.tets)
        if tets.ndim != 2 or tets.shape[1] != 4 or tets.shape[0] == 0:
            raise MeshError(f"tets must have shape (M, 4), M >= 1; got {tets.shape}")
        if not np.issubdtype(tets.dtype, np.integer):
            raise MeshError("tets must hold integer node indices")
        tets = tets.astype(np.int64)
        if tets.min() < 0 or tets.max() >= pts.shape[0]:
            raise MeshError(f"tets refer to node indices outside 0..{pts.shape[0] - 1}")
        if np.unique(tets).size != pts.shape[0]:
            raise MeshError("every node must belong to a tetrahedron (MuJoCo would leave it floating)")
        pts, tets = pts.copy(), tets.copy()
        pts.setflags(write=False)
        tets.setflags(write=False)
        set_(self, "points", pts)
        set_(self, "tets", tets)

        set_(self, "mass", positive(self.mass, "object mass", "kg"))
        set_(self, "young", positive(self.young, "Young's modulus", "Pa", MaterialError))
        nu = float(self.poisson)
        if not (math.isfinite(nu) and 0.0 <= nu < 0.5):
            raise MaterialError(f"Poisson's ratio = {self.poisson} is invalid: MuJoCo needs 0 <= nu < 0.5")
        set_(self, "poisson", nu)
        for name in ("mu", "table_mu"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0.0):
                raise ConfigError(f"{name} = {getattr(self, name)} is invalid: it must be finite and >= 0")
            set_(self, name, v)
        z = float(self.table_z)
        if not math.isfinite(z):
            raise ConfigError(f"table_z = {self.table_z} m is invalid: it must be finite")
        low = float(pts[:, 2].min())
        if low < z - 1e-6:
            raise ConfigError(
                f"the object starts {1e3 * (z - low):.3f} mm below the table top z = {z} m; "
                "rest it on the table first"
            )
        set_(self, "table_z", z)
        set_(self, "timestep", positive(self.timestep, "timestep", "s"))
        d = float(self.damping)
        if not (math.isfinite(d) and d >= 0.0):
            raise ConfigError(f"damping = {self.damping} s is invalid: it must be finite and >= 0 s")
        set_(self, "damping", d)

    def joint_values(self, finger: str) -> dict[str, float]:
        """Value of every moving joint of ``finger`` (mimic joints included) at ``q0``."""
        chain = self.hand.chain(finger)
        q = self.q0[finger]
        return {
            j.name: (g * q[k] + b)
            for j, k, g, b in zip(
                chain.joints, chain.drive_index, chain.drive_gain, chain.drive_offset, strict=True
            )
            if k >= 0
        }
