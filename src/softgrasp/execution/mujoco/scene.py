"""MuJoCo scene of a grasp: a table, the soft object as a 3-D flex and the hand on an arm.

:func:`build_mjcf` writes the MJCF text of a :class:`SceneSpec`; :func:`load_scene` compiles it
and returns a :class:`MujocoScene` (model, data and the index look-ups an executor needs). The
builder is pure Python; MuJoCo is imported only inside :func:`load_scene` and
:class:`MujocoScene`, so this module imports without it. Written for MuJoCo 4.0 (the ``discrete``
integrator it relies on appeared in 3.13).

Scene
-----
* **Table**: a static box geom whose top face is at ``table_z``.
* **Object**: a ``flexcomp`` of type ``direct``, ``dim=3``, radius 0, built from ``points`` and
  ``tets``. flexcomp gives every point a body with three world-axis slide joints and the mass
  ``mass / N`` (uniform, unlike softgrasp's volume-lumped node masses; the sum is ``mass``) and
  keeps the order of ``points`` for the flex vertices. Elasticity is MuJoCo's continuum model
  (Saint Venant-Kirchhoff on linear tets, Lame constants from ``young`` and ``poisson``) with a
  Rayleigh damping time ``damping``; no edge constraints; self-collision off.
* **Arm**: a 1 kg body at the palm's position on three world-axis slide joints, each a stiff
  position servo (:data:`ARM_KP`), commanded by :meth:`MujocoScene.command_palm` (a real motion,
  with velocity: friction carries a grasped object along). A mocap palm would be teleported with
  zero velocity in the contact solver, so friction would hold the object in place while the
  fingers slid up past it (measured: the sphere stayed on the table at any grip). The hand's
  bodies are gravity-compensated by the arm (``gravcomp``).
* **Hand**: the palm (root link) rides on the arm at ``palm_pose``; below it a body per URDF link
  at its joint ``origin``, a hinge (revolute) or slide (prismatic) joint about the URDF ``axis``
  with the joint's own limits (fixed joints weld), a capsule per link segment and a sphere per
  moving joint for looks (and link inertia; density 1000 kg/m^3, no collisions) and a sphere of
  the finger's radius centred on every fingertip link: the only hand geoms that collide, and only
  with the object. A mimic joint is an equality ``q = offset + multiplier q_mimic``; every
  independent joint has a position servo whose ``ctrl`` is its target [rad or m]. The keyframe
  ``initial`` holds ``q0`` and the servo targets, so the XML alone starts where :func:`load_scene`
  does.

Choices
-------
* **Integrator** ``discrete``, solver ``CG``, elliptic friction cones. ``discrete`` is the only
  MuJoCo integrator implicit in position: flex elasticity, servo gains and joint damping enter
  the effective inertia ``M + h D + h^2 K``. MuJoCo 4 refuses flex elasticity under
  ``implicit``/``implicitfast`` (engine error) and ``PGS``; ``Euler`` integrates it explicitly
  and blew up (NaN in ``qacc``) within 4 steps of 2 ms: the 388-node sphere's highest mode
  (estimated ~6e3 rad/s) limits explicit steps to ~3e-4 s. ``CG`` is matrix-free; ``Newton``
  gave the same forces (within 1 %) at 1.5-2.5x the cost (it folds the flex stiffness into its
  Hessian).
* **Solver budget**: each step solves ``(M + h D + h^2 K) a = f`` for ``qacc_smooth`` by
  block-Jacobi PCG capped by ``iterations`` and stopped at the relative residual ``tolerance``.
  MuJoCo's default cap (100) ran out on the rubber sphere (``mjWARN_INERTIA``, "Flex stiffness
  is too ill-conditioned for the effective-metric block preconditioner"), so
  :data:`SOLVER_ITERATIONS` is 1000. :data:`SOLVER_TOLERANCE` stays at MuJoCo's 1e-8; 1e-6
  is 20-40 % faster and moved the 3 mm indentation force by 1.2 % (2.905 vs 2.940 N; 2.941 N
  at 1e-10).
* **Time step** :data:`DEFAULT_TIMESTEP` = 2 ms. The 3 mm indentation force is 2.904 N at 1 ms
  and 2.940 N at 2 ms (-1.2 %, the level at which the frictional contact's sticking history
  shifts it), 2.85 N at 5 ms (-3 %) and 2.60 N at 10 ms (-12 %), where contact rows stiffer than
  the step are replaced (``refsafe``); at 20 ms the resting sphere bounces (table reaction off
  by 32 %). No step size produced NaN: the position-implicit integrator degrades by damping, not
  by blowing up. 2 ms is also the contact time constant, the stiffest one a step resolves.
* **Flex damping** :data:`DEFAULT_DAMPING` = 2e-4 s, softgrasp's own damping time of the rubber
  sphere (:func:`softgrasp.physics.body.build_body`: damping ratio 0.1 of the fundamental mode,
  ~1000 rad/s). Larger values slow the PCG (``h D`` adds to ``h^2 K``) without changing the
  quasi-static response; at 2 ms backward-Euler dissipation dominates anyway for modes with
  ``w h > 1``.
* **Friction**: MuJoCo combines the parameters of two colliding geoms (here a geom and the flex)
  by element-wise maximum of the friction and solmix-weighted mean of solref/solimp, unless one
  side has a higher ``priority``, whose condim, friction, solref and solimp are then used as they
  are. ``<contact><pair>`` does not take flexes. So the table and the fingertips have priority 1
  and the flex 0: table-object contacts get ``table_mu`` and fingertip-object contacts ``mu``
  exactly, whatever the flex's friction. ``condim`` 3 (point contact with Coulomb friction, the
  planner's model). Rolling friction would be useless anyway: flex vertices have no rotation.
* **Contact softness** :data:`CONTACT_SOLREF`, :data:`CONTACT_SOLIMP`: MuJoCo's soft contacts
  penetrate by ``(1 - d) timeconst^2 x (force / effective mass)``, and a flex vertex weighs
  ~0.1 g, so the default (0.02 s, d = 0.9-0.95) lets a fingertip sink centimetres. With
  timeconst = 2 ms (= h, the stiffest the step resolves) and d = 0.999-0.9999 the penetration is
  0.11 mm at 3.6 N (0.49 mm with d = 0.99-0.999).
* **Collision filter**: contype/conaffinity bits table 1, fingertips 2, object 4; the object
  accepts 1 and 2, the table and the fingertips only 4, every other hand geom 0.
* **Servos** :data:`JOINT_KP` = 200 N m/rad, :data:`JOINT_DAMPING` = 1 N m s/rad,
  :data:`JOINT_ARMATURE` = 1e-4 kg m^2: 3 N on the tip of the straight, horizontal first finger
  moves it 0.19 mm (0.5 N: 0.03 mm); targets are reached within 6e-5 rad in 0.5 s; the servo
  time constant is damping / kp = 5 ms (overdamped). The mimic equalities use
  :data:`EQUALITY_SOLREF` / :data:`EQUALITY_SOLIMP`: ``|J1 - J2|`` stays below 1.5e-4 rad while
  the fingers swing across their range and 1e-7 rad under a 3 N tip load (with MuJoCo's default
  solref/solimp gravity alone would open it by ~1e-2 rad on these gram-light links).

Validation (MuJoCo 4.0.0, softgrasp's rubber sphere: R = 64 mm, 50 g, E = 79.3 kPa, nu = 0.45;
``tests/test_mujoco_scene.py``)
-----------------------------------------------------------------------------------------------
* Affine patch test: the flex's elastic energy for uniaxial, volumetric and shear strains equals
  ``V (mu tr(e^2) + lambda/2 tr(e)^2)`` to 1.5e-4: ``young`` and ``poisson`` mean what they say.
* Resting, 388 nodes: after 1 s the table carries ``m g`` to 2e-4, the centre of mass sags
  0.16 mm and rocks by ~0.2-0.5 mm on its support tripod, no warning. The 2196-node sphere
  (``make_object("sphere", 0.008)``) also carries ``m g`` (1.5e-3) but is only neutrally stable:
  its elastic sag (0.37 mm) exceeds the relief of its small support facets, and it rolls ~9 mm
  in the first second (independent of damping, step size and node masses).
* Fingertip (first finger pointing down) pressed into the top node: the force grows
  monotonically, nearly linearly (0.52 / 1.03 / 2.01 / 2.94 N at 0.5 / 1 / 2 / 3 mm). Hertz for a
  rigid 8 mm fingertip (``E* = E / (1 - nu^2)``, ``R_eff = (1/0.064 + 1/0.008)^-1``) gives
  1.84 N at 3 mm: ratio 1.60 on the 388-node mesh (about 2.0 pressing on a face), 1.09 (1.07)
  on 2196 nodes. The coarse mesh is stiffer than the continuum: its 16 mm elements are larger than
  the Hertz contact radius (4.6 mm at 3 mm), so the load acts like a punch of element size on
  linear tets that stiffen (lock) at nu = 0.45; refining converges to Hertz.
* Cost (one core of a 2-core machine shared with another job, so +-20 %): 388 nodes with the
  hand 3.5 s of wall time per simulated second (~7 ms per 2 ms step); 2196 nodes 36 s (~70 ms
  per step). Most of it is the ``qacc_smooth`` PCG and the constraint solve, both scaling with
  the flex size; the hand costs nothing noticeable.

Indentation scene
-----------------
:func:`build_indent_mjcf` / :func:`load_indent_scene` write and compile the same table, object
and options with one fingertip sphere instead of the hand, on three world-axis slides under stiff
servos (:class:`IndentSpec`, :class:`IndentScene`): the MuJoCo peer of softgrasp's indentation
experiment (``benchmarks/bench_indent.py``). :func:`contact_force` sums a geom's contact forces.
On the 388-node sphere, 3 mm over its centre: 3.8 N, 2.0 x Hertz (the coarse mesh's stiffening
above), and the fingertip's servo carries exactly that force (``tests/test_mujoco_indent.py``).
Pressed deep (15 mm, R = 8 mm) the sphere wraps the fingertip and MuJoCo resolves the contact
with one point per touching tet (6-9 points on 2196 nodes, up to 60 deg from vertical); friction
on the fingertip's flanks then carries about a third of the force (13.3 N with mu = 0.8, 8.9 N
with mu = 0, 549 nodes) and relaxes by creep once the fingertip stops (-4 % in 0.5 s at 549 nodes,
-34 % at 2196; flat with mu = 0 at 549).

Notes: after :meth:`MujocoScene.step` the derived quantities MuJoCo stores (body and vertex
positions, contacts, contact forces) are those of the start of the last step, the ``mj_step``
convention; ``mujoco.mj_forward`` refreshes them. ``mj_rnePostConstraint`` (``cfrc_ext``) ignores
flex contacts in MuJoCo 4.0; forces on the object are read from the contacts themselves.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.physics.body import STANDARD_GRAVITY
from softgrasp.errors import ConfigError, MaterialError, MeshError
from softgrasp.hand.kinematics import HandModel

__all__ = [
    "MUJOCO_MISSING",
    "DEFAULT_TIMESTEP",
    "DEFAULT_DAMPING",
    "JOINT_KP",
    "JOINT_DAMPING",
    "JOINT_ARMATURE",
    "CONTACT_SOLREF",
    "CONTACT_SOLIMP",
    "EQUALITY_SOLREF",
    "EQUALITY_SOLIMP",
    "SOLVER",
    "SOLVER_ITERATIONS",
    "SOLVER_TOLERANCE",
    "OBJECT_NAME",
    "SceneSpec",
    "MujocoScene",
    "build_mjcf",
    "load_scene",
    "INDENT_TIP",
    "TIP_MASS",
    "TIP_KP",
    "TIP_DAMPING",
    "IndentSpec",
    "IndentScene",
    "build_indent_mjcf",
    "contact_force",
    "load_indent_scene",
]

#: Name of the arm body carrying the palm, and of its three world-axis slide joints.
ARM_NAME = "arm"
ARM_JOINTS = ("arm_x", "arm_y", "arm_z")
#: Arm mass [kg], servo stiffness [N/m] and joint damping [N s/m]: stiff (a 1 N load deflects it
#: 20 um) and about critically damped (2 sqrt(kp m) ~ 280 N s/m) with the hand's small mass.
ARM_MASS = 1.0
ARM_KP = 5.0e4
ARM_DAMPING = 450.0

#: Message of the :class:`ConfigError` raised when MuJoCo cannot be imported.
MUJOCO_MISSING = (
    "MuJoCo is not installed: pip install 'mujoco>=4.0', or reinstall softgrasp with its extra: "
    "pip install -e '.[execute]'"
)

#: Default simulation time step [s] (converged: 1 ms gives the same contact forces; module docstring).
DEFAULT_TIMESTEP = 2e-3
#: Default Rayleigh damping time of the flex elasticity [s] (damping matrix = damping x stiffness).
DEFAULT_DAMPING = 2e-4

#: Constraint solver (also preconditions the flex's implicit ``M + h D + h^2 K`` solve).
SOLVER = "CG"
#: Iteration cap of the constraint solver and of the ``M + h D + h^2 K`` solve for ``qacc_smooth``.
SOLVER_ITERATIONS = 1000
#: Relative tolerance of both solves.
SOLVER_TOLERANCE = 1e-8

#: Position-servo stiffness of every independent joint [N m/rad or N/m].
JOINT_KP = 200.0
#: Viscous damping of every hand joint [N m s/rad or N s/m].
JOINT_DAMPING = 1.0
#: Armature (reflected rotor inertia) of every hand joint [kg m^2 or kg].
JOINT_ARMATURE = 1e-4

#: solref (time constant [s], damping ratio) of the fingertip and table contacts.
CONTACT_SOLREF = (0.002, 1.0)
#: solimp of the fingertip and table contacts.
CONTACT_SOLIMP = (0.999, 0.9999, 0.001, 0.5, 2.0)
#: solref of the mimic joint equalities.
EQUALITY_SOLREF = (0.002, 1.0)
#: solimp of the mimic joint equalities.
EQUALITY_SOLIMP = (0.999, 0.9999, 0.001, 0.5, 2.0)

#: Name of the object flex (its vertex bodies are ``object_0``, ``object_1``, ...).
OBJECT_NAME = "object"

# collision bits: table 1, fingertips 2, object 4
_TABLE_BIT, _TIP_BIT, _OBJECT_BIT = 1, 2, 4
#: Torsional and rolling friction coefficients of every contact (condim 3 uses neither).
_SPIN_ROLL = (0.005, 0.0001)
#: Radius of the decorative link capsules, relative to the fingertip radius.
_LINK_RADIUS = 0.8


# ---------------------------------------------------------------------- spec


def _rigid(T: ArrayLike, what: str) -> NDArray[np.float64]:
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


def _positive(value: float, what: str, unit: str, error: type[Exception] = ConfigError) -> float:
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
        set_(self, "palm_pose", _rigid(self.palm_pose, "palm_pose"))
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

        set_(self, "mass", _positive(self.mass, "object mass", "kg"))
        set_(self, "young", _positive(self.young, "Young's modulus", "Pa", MaterialError))
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
        set_(self, "timestep", _positive(self.timestep, "timestep", "s"))
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


# ---------------------------------------------------------------------- XML helpers


def _num(v: float) -> str:
    return f"{float(v):.12g}"


def _vec(values: ArrayLike) -> str:
    return " ".join(_num(v) for v in np.asarray(values, dtype=np.float64).ravel())


def _quat(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix (Shepperd's method)."""
    t = float(np.trace(R))
    if t > 0.0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    qa = np.array(q)
    qa /= np.linalg.norm(qa)
    return qa if qa[0] >= 0.0 else -qa


def _sub(parent: ET.Element, tag: str, **attrs: Any) -> ET.Element:
    return ET.SubElement(parent, tag, {k: str(v) for k, v in attrs.items() if v is not None})


def _add_table(world: ET.Element, centre, reach: float, table_z: float, table_mu: float) -> None:
    """The table: a 20 mm box of half-width ``reach`` around ``centre`` with its top at ``table_z``."""
    thickness = 0.02
    _sub(
        world,
        "geom",
        name="table",
        type="box",
        size=_vec([reach, reach, 0.5 * thickness]),
        pos=_vec([centre[0], centre[1], table_z - 0.5 * thickness]),
        contype=str(_TABLE_BIT),
        conaffinity=str(_OBJECT_BIT),
        rgba="0.45 0.42 0.38 1",
        **_contact_attrs(table_mu),
    )


def _root(model: str, timestep: float) -> ET.Element:
    """The ``<mujoco>`` element with softgrasp's compiler and solver options (discrete integrator,
    elliptic friction cones)."""
    root = ET.Element("mujoco", model=model)
    _sub(root, "compiler", angle="radian", autolimits="true")
    _sub(
        root,
        "option",
        timestep=_num(timestep),
        gravity=_vec([0.0, 0.0, -STANDARD_GRAVITY]),
        integrator="discrete",
        solver=SOLVER,
        cone="elliptic",
        iterations=str(SOLVER_ITERATIONS),
        tolerance=_num(SOLVER_TOLERANCE),
    )
    return root


def _contact_attrs(mu: float) -> dict[str, str]:
    return {
        "condim": "3",
        "priority": "1",
        "friction": _vec([mu, *_SPIN_ROLL]),
        "solref": _vec(CONTACT_SOLREF),
        "solimp": _vec(CONTACT_SOLIMP),
    }


def _tip_geom_name(tip_link: str) -> str:
    return f"{tip_link}_sphere"


def _actuator_name(joint: str) -> str:
    return f"{joint}_servo"


# ---------------------------------------------------------------------- builder


def _add_hand(world: ET.Element, spec: SceneSpec) -> list[tuple[str, float]]:
    """Append the arm, the palm and the finger bodies; return ``(joint, q0 value)`` in qpos order."""
    hand = spec.hand
    chains = list(hand.fingers.values())
    roots = {c.joints[0].parent for c in chains}
    if len(roots) != 1:
        raise ConfigError(f"the fingers do not share one palm link: {sorted(roots)}")
    root = roots.pop()
    radius = min(c.radius for c in chains)
    T = spec.palm_pose
    # The arm: a body at the palm's position on three world-axis slides, each a stiff position
    # servo, carrying the palm at its orientation. (A mocap palm would be moved kinematically, with
    # zero velocity in the contact solver: friction then holds the object where it is instead of
    # carrying it along with the fingers.)
    arm = _sub(world, "body", name=ARM_NAME, pos=_vec(T[:3, 3]))
    _sub(arm, "inertial", pos="0 0 0", mass=_num(ARM_MASS), diaginertia=_vec([1e-3, 1e-3, 1e-3]))
    for axis, name in zip(np.eye(3), ARM_JOINTS, strict=True):
        _sub(arm, "joint", name=name, type="slide", axis=_vec(axis), damping=_num(ARM_DAMPING))
    palm = _sub(arm, "body", name=root, quat=_vec(_quat(T[:3, :3])))

    # a decorative palm plate under the finger bases (palm frame: z = palm normal)
    bases = np.array([c.joints[0].origin[:3, 3] for c in chains])
    lo = np.minimum(bases.min(axis=0), 0.0) - radius
    hi = np.maximum(bases.max(axis=0), 0.0) + radius
    half = 0.5 * (hi - lo)
    centre = 0.5 * (hi + lo)
    half[2], centre[2] = 1.2 * radius, -1.2 * radius
    _sub(
        palm,
        "geom",
        name=f"{root}_plate",
        type="box",
        size=_vec(half),
        pos=_vec(centre),
        contype="0",
        conaffinity="0",
        group="1",
        rgba="0.55 0.55 0.6 1",
    )

    values: dict[str, float] = {}
    for finger in hand.fingers:
        values.update(spec.joint_values(finger))
    bodies: dict[str, ET.Element] = {root: palm}
    tip_links = {c.tip_link: c for c in chains}
    for chain in chains:
        for joint in chain.joints:
            if joint.child in bodies:
                continue  # a link shared with a finger already built
            parent = bodies[joint.parent]
            p = joint.origin[:3, 3]
            if joint.parent != root and float(np.linalg.norm(p)) > 1e-9:
                _sub(
                    parent,
                    "geom",
                    type="capsule",
                    fromto=_vec([0.0, 0.0, 0.0, *p]),
                    size=_num(_LINK_RADIUS * radius),
                    contype="0",
                    conaffinity="0",
                    group="1",
                    rgba="0.8 0.7 0.6 1",
                )
            body = _sub(parent, "body", name=joint.child, pos=_vec(p), quat=_vec(_quat(joint.origin[:3, :3])))
            bodies[joint.child] = body
            if joint.movable:
                _sub(
                    body,
                    "joint",
                    name=joint.name,
                    type="hinge" if joint.kind == "revolute" else "slide",
                    axis=_vec(joint.axis),
                    range=_vec([joint.lower, joint.upper]),
                    damping=_num(JOINT_DAMPING),
                    armature=_num(JOINT_ARMATURE),
                )
                _sub(
                    body,
                    "geom",
                    type="sphere",
                    size=_num(_LINK_RADIUS * radius),
                    contype="0",
                    conaffinity="0",
                    group="1",
                    rgba="0.7 0.6 0.5 1",
                )
            if joint.child in tip_links:
                tip = tip_links[joint.child]
                _sub(
                    body,
                    "geom",
                    name=_tip_geom_name(tip.tip_link),
                    type="sphere",
                    size=_num(tip.radius),
                    contype=str(_TIP_BIT),
                    conaffinity=str(_OBJECT_BIT),
                    rgba="0.9 0.75 0.6 1",
                    **_contact_attrs(spec.mu),
                )
    for body in arm.iter("body"):
        body.set("gravcomp", "1")  # the arm carries the hand's weight (a real arm's controller does)
    values.update(dict.fromkeys(ARM_JOINTS, 0.0))
    # MuJoCo numbers the joints in depth-first (document) order of the body tree
    return [(j.get("name", ""), values[j.get("name", "")]) for j in arm.iter("joint")]


def _add_object(world: ET.Element, spec: SceneSpec) -> None:
    flex = _sub(
        world,
        "flexcomp",
        name=OBJECT_NAME,
        type="direct",
        dim="3",
        point=_vec(spec.points),
        element=" ".join(str(int(i)) for i in spec.tets.ravel()),
        mass=_num(spec.mass),
        radius="0",
        rgba="0.85 0.3 0.25 1",
    )
    # the table and the fingertips have priority 1: their friction and solver parameters win
    _sub(
        flex,
        "contact",
        selfcollide="none",
        contype=str(_OBJECT_BIT),
        conaffinity=str(_TABLE_BIT | _TIP_BIT),
        condim="3",
        priority="0",
        friction=_vec([min(spec.mu, spec.table_mu), *_SPIN_ROLL]),
        solref=_vec(CONTACT_SOLREF),
        solimp=_vec(CONTACT_SOLIMP),
    )
    _sub(flex, "edge", equality="false")
    _sub(flex, "elasticity", young=_num(spec.young), poisson=_num(spec.poisson), damping=_num(spec.damping))


def build_mjcf(spec: SceneSpec) -> str:
    """MJCF text of the scene of ``spec`` (see the module docstring); needs no MuJoCo.

    Names: the flex is :data:`OBJECT_NAME`, bodies and joints carry their URDF link and joint
    names, the palm body the root link's name, fingertip spheres ``<tip link>_sphere``, servos
    ``<joint>_servo``; the table geom is ``table``. The keyframe ``initial`` holds ``q0``
    (mimic joints included) and the servo targets.
    """
    if not isinstance(spec, SceneSpec):
        raise ConfigError(f"build_mjcf needs a SceneSpec, got {type(spec).__name__}")
    pts = spec.points
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = 0.5 * (lo + hi)
    extent = float(np.max(hi - lo))
    palm_xyz = spec.palm_pose[:3, 3]
    reach = max(extent, float(np.linalg.norm(palm_xyz[:2] - centre[:2])) + 0.15, 0.25)

    root = _root("softgrasp_scene", spec.timestep)
    visual = _sub(root, "visual")
    _sub(visual, "global", offwidth="1280", offheight="960", azimuth="135", elevation="-25")
    _sub(visual, "headlight", ambient="0.35 0.35 0.35", diffuse="0.5 0.5 0.5", specular="0.1 0.1 0.1")
    _sub(visual, "quality", shadowsize="4096")
    asset = _sub(root, "asset")
    _sub(
        asset,
        "texture",
        name="sky",
        type="skybox",
        builtin="gradient",
        rgb1="0.75 0.8 0.85",
        rgb2="0.2 0.22 0.25",
        width="256",
        height="256",
    )
    _sub(
        root,
        "statistic",
        center=_vec([centre[0], centre[1], 0.5 * (spec.table_z + palm_xyz[2])]),
        extent=_num(2.0 * reach),
    )

    world = _sub(root, "worldbody")
    _sub(
        world,
        "light",
        name="key",
        pos=_vec(centre + [0.3, -0.3, 1.0]),
        dir=_vec([-0.3, 0.3, -1.0]),
        directional="true",
        castshadow="true",
        diffuse="0.6 0.6 0.6",
    )
    _sub(
        world,
        "light",
        name="fill",
        pos=_vec(centre + [-0.4, 0.4, 0.8]),
        dir=_vec([0.4, -0.4, -0.8]),
        directional="true",
        castshadow="false",
        diffuse="0.3 0.3 0.3",
    )
    eye = centre + np.array([0.45, -0.45, 0.35]) * max(1.0, extent / 0.13)
    look = centre - eye
    x_axis = np.cross(look, [0.0, 0.0, 1.0])
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(x_axis, look)
    y_axis /= np.linalg.norm(y_axis)
    _sub(world, "camera", name="overview", pos=_vec(eye), xyaxes=_vec([*x_axis, *y_axis]), fovy="45")
    _add_table(world, centre, reach, spec.table_z, spec.table_mu)

    order = _add_hand(world, spec)
    _add_object(world, spec)

    equality = _sub(root, "equality")
    actuator = _sub(root, "actuator")
    done: set[str] = set()  # joints shared by several fingers get one equality and one servo
    ctrl: list[float] = []
    for name in ARM_JOINTS:
        _sub(actuator, "position", name=_actuator_name(name), joint=name, kp=_num(ARM_KP))
        ctrl.append(0.0)
    for finger, chain in spec.hand.fingers.items():
        for joint in chain.joints:
            if joint.movable and joint.mimic is not None and joint.name not in done:
                done.add(joint.name)
                _sub(
                    equality,
                    "joint",
                    name=f"{joint.name}_mimic",
                    joint1=joint.name,
                    joint2=joint.mimic,
                    polycoef=_vec([joint.offset, joint.multiplier, 0.0, 0.0, 0.0]),
                    solref=_vec(EQUALITY_SOLREF),
                    solimp=_vec(EQUALITY_SOLIMP),
                )
        for k, name in enumerate(chain.joint_names):
            if name in done:
                continue
            done.add(name)
            _sub(
                actuator,
                "position",
                name=_actuator_name(name),
                joint=name,
                kp=_num(JOINT_KP),
                ctrlrange=_vec([chain.lower[k], chain.upper[k]]),
            )
            ctrl.append(float(spec.q0[finger][k]))
    if len(equality) == 0:
        root.remove(equality)

    n_flex_dof = 3 * spec.points.shape[0]
    qpos = [v for _, v in order] + [0.0] * n_flex_dof
    keyframe = _sub(root, "keyframe")
    _sub(
        keyframe,
        "key",
        name="initial",
        qpos=_vec(qpos),
        ctrl=_vec(ctrl),
    )

    ET.indent(root, space="  ")
    return ET.tostring(root, encoding="unicode") + "\n"


# ---------------------------------------------------------------------- loading


def _import_mujoco() -> Any:
    try:
        import mujoco
    except ImportError:
        raise ConfigError(MUJOCO_MISSING) from None
    return mujoco


class MujocoScene:
    """A compiled scene: ``model`` (``mujoco.MjModel``), ``data`` (``mujoco.MjData``) and look-ups.

    Made by :func:`load_scene`. ``fingers`` are the hand's finger names; ``spec`` the
    :class:`SceneSpec` it was built from.
    """

    def __init__(self, model: Any, data: Any, spec: SceneSpec) -> None:
        mujoco = _import_mujoco()
        self._mj = mujoco
        self.model = model
        self.data = data
        self.spec = spec
        self.fingers: tuple[str, ...] = tuple(spec.hand.fingers)

        def ident(kind: Any, name: str) -> int:
            i = mujoco.mj_name2id(model, kind, name)
            if i < 0:
                raise ConfigError(f"the compiled scene has no {kind.name[6:].lower()} named {name!r}")
            return int(i)

        J, A, G = mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_ACTUATOR, mujoco.mjtObj.mjOBJ_GEOM
        self._qpos: dict[str, NDArray[np.int64]] = {}
        self._act: dict[str, NDArray[np.int64]] = {}
        self._tip: dict[str, int] = {}
        for finger in self.fingers:
            chain = spec.hand.chain(finger)
            self._qpos[finger] = np.array(
                [model.jnt_qposadr[ident(J, n)] for n in chain.joint_names], dtype=np.int64
            )
            self._act[finger] = np.array(
                [ident(A, _actuator_name(n)) for n in chain.joint_names], dtype=np.int64
            )
            self._tip[finger] = ident(G, _tip_geom_name(chain.tip_link))
        self._flex = ident(mujoco.mjtObj.mjOBJ_FLEX, OBJECT_NAME)
        adr, num = int(model.flex_vertadr[self._flex]), int(model.flex_vertnum[self._flex])
        if num != spec.points.shape[0]:
            raise ConfigError(f"the compiled flex has {num} vertices, the spec {spec.points.shape[0]} points")
        self._verts = slice(adr, adr + num)
        self._vert_mass = np.array(model.body_mass[model.flex_vertbodyid[self._verts]], dtype=np.float64)
        self._arm_act = np.array([ident(A, _actuator_name(n)) for n in ARM_JOINTS], dtype=np.int64)
        self._arm_qpos = np.array([model.jnt_qposadr[ident(J, n)] for n in ARM_JOINTS], dtype=np.int64)
        self._palm_body = ident(mujoco.mjtObj.mjOBJ_BODY, self._palm_name())

    def _palm_name(self) -> str:
        return next(iter(self.spec.hand.fingers.values())).joints[0].parent

    def _finger(self, finger: str) -> str:
        if finger not in self._tip:
            raise ConfigError(f"unknown finger {finger!r}; this hand has {', '.join(self.fingers)}")
        return finger

    def joint_qpos_index(self, finger: str) -> NDArray[np.int64]:
        """``qpos`` addresses of the finger's independent joints, in :class:`HandModel` order."""
        return self._qpos[self._finger(finger)].copy()

    def actuator_index(self, finger: str) -> NDArray[np.int64]:
        """Indices of the position servos of the finger's independent joints (``data.ctrl`` slots)."""
        return self._act[self._finger(finger)].copy()

    def tip_geom(self, finger: str) -> int:
        """Geom id of the finger's fingertip sphere."""
        return self._tip[self._finger(finger)]

    def fingertip_position(self, finger: str) -> NDArray[np.float64]:
        """World position [m] of the fingertip sphere centre (as of the last step or forward)."""
        return np.array(self.data.geom_xpos[self._tip[self._finger(finger)]], dtype=np.float64)

    def fingertip_force(self, finger: str) -> NDArray[np.float64]:
        """Total contact force [N] the fingertip exerts ON THE OBJECT, world frame, ``(3,)``.

        Sum over the active contacts of the fingertip sphere: :func:`mujoco.mj_contactForce` gives
        the force in the contact frame (rows of ``contact.frame``; normal from ``geom[0]`` to
        ``geom[1]``), which is the force of side 0 on side 1; it is negated when the fingertip is
        side 1.
        """
        gid = self._tip[self._finger(finger)]
        return self._contact_sum(lambda c: 1.0 if c.geom[0] == gid else -1.0 if c.geom[1] == gid else 0.0)

    def table_force(self) -> NDArray[np.float64]:
        """Total contact force [N] the table exerts on the object, world frame, ``(3,)``."""
        gid = self._mj.mj_name2id(self.model, self._mj.mjtObj.mjOBJ_GEOM, "table")
        return self._contact_sum(lambda c: 1.0 if c.geom[0] == gid else -1.0 if c.geom[1] == gid else 0.0)

    def _contact_sum(self, sign_of: Any) -> NDArray[np.float64]:
        total = np.zeros(3)
        f6 = np.zeros(6)
        for i in range(int(self.data.ncon)):
            c = self.data.contact[i]
            if c.efc_address < 0:
                continue
            s = sign_of(c)
            if s == 0.0:
                continue
            self._mj.mj_contactForce(self.model, self.data, i, f6)
            total += s * (c.frame.reshape(3, 3).T @ f6[:3])
        return total

    def object_nodes(self) -> NDArray[np.float64]:
        """``(N, 3)`` flex vertex positions in the world [m] (as of the last step or forward), in
        the order of ``points``."""
        return np.array(self.data.flexvert_xpos[self._verts], dtype=np.float64)

    def object_mass(self) -> NDArray[np.float64]:
        """``(N,)`` flex vertex masses [kg] of the compiled model."""
        return self._vert_mass.copy()

    def object_com(self) -> NDArray[np.float64]:
        """Mass-weighted centre [m] of the flex vertices (masses of the compiled model)."""
        m = self._vert_mass
        return (m @ self.object_nodes()) / float(m.sum())

    def palm_pose(self) -> NDArray[np.float64]:
        """Current palm-to-world transform (4, 4) (as of the last step or forward)."""
        T = np.eye(4)
        T[:3, :3] = np.asarray(self.data.xmat[self._palm_body], dtype=np.float64).reshape(3, 3)
        T[:3, 3] = self.data.xpos[self._palm_body]
        return T

    def command_palm(self, offset: ArrayLike) -> None:
        """Command the arm to carry the palm ``offset`` [m] (world frame) from its starting pose;
        the arm's servos move it there over the next steps (it keeps its orientation)."""
        d = np.asarray(offset, dtype=np.float64)
        if d.shape != (3,) or not np.all(np.isfinite(d)):
            raise ConfigError(f"the palm offset must be 3 finite numbers [m], got {offset!r}")
        self.data.ctrl[self._arm_act] = d

    def set_palm(self, pose: ArrayLike) -> None:
        """Put the palm at ``pose`` (4, 4) at once (arm joints and servo targets): a teleport for
        setting up a scene, not a motion (nothing it touches is carried along). Only the
        starting orientation is possible: the arm translates."""
        T = _rigid(pose, "palm pose")
        T0 = self.spec.palm_pose
        if np.abs(T[:3, :3] - T0[:3, :3]).max() > 1e-9:
            raise ConfigError("the arm only translates the palm: its orientation must stay the starting one")
        d = T[:3, 3] - T0[:3, 3]
        self.data.qpos[self._arm_qpos] = d
        self.data.qvel[self.model.jnt_dofadr[self.model.actuator_trnid[self._arm_act, 0]]] = 0.0
        self.data.ctrl[self._arm_act] = d
        self._mj.mj_kinematics(self.model, self.data)

    def forward(self) -> None:
        """Recompute the derived quantities (positions, contacts, contact forces) of the current
        state (after :meth:`step` they are those of the start of the last step)."""
        self._mj.mj_forward(self.model, self.data)

    def step(self, n: int = 1) -> None:
        """Advance the simulation by ``n`` time steps."""
        if isinstance(n, bool) or int(n) != n or n < 1:
            raise ConfigError(f"n = {n} must be an integer >= 1")
        self._mj.mj_step(self.model, self.data, nstep=int(n))


def load_scene(spec: SceneSpec) -> MujocoScene:
    """Compile the MJCF of ``spec`` and return the scene at its ``initial`` keyframe (``q0``).

    :class:`ConfigError` if MuJoCo is not installed or rejects the model.
    """
    mujoco = _import_mujoco()
    xml = build_mjcf(spec)
    try:
        model = mujoco.MjModel.from_xml_string(xml)
    except ValueError as exc:
        raise ConfigError(f"MuJoCo rejected the scene: {exc}") from None
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    return MujocoScene(model, data, spec)


# ---------------------------------------------------------------------- indentation scene
#
# One fingertip pressing the object on the table, without a hand: the MuJoCo peer of
# softgrasp's indentation experiment (:mod:`softgrasp.experiments.indentation`), used by
# ``benchmarks/bench_indent.py``. Table, object and solver options are written as in
# :func:`build_mjcf` (same constants, same object builder).

#: Name of the fingertip body and the prefix of its sphere geom (``<name>_sphere``), its world-axis
#: slide joints (``<name>_x``, ``_y``, ``_z``) and their position servos (``<joint>_servo``).
INDENT_TIP = "fingertip"
#: Mass of the fingertip's carriage [kg] (gravity-compensated).
TIP_MASS = 1.0
#: Position-servo stiffness of each fingertip slide [N/m]: a 10 N load deflects it 10 um.
TIP_KP = 1.0e6
#: Damping of each fingertip slide [N s/m]: critical for :data:`TIP_MASS` (2 sqrt(kp m)); at
#: 10 mm/s the servo lags its target by 20 um.
TIP_DAMPING = 2.0e3
_TIP_JOINTS = tuple(f"{INDENT_TIP}_{a}" for a in "xyz")


@dataclass(frozen=True, eq=False)
class IndentSpec:
    """A one-fingertip indentation scene for :func:`build_indent_mjcf`; SI units, world z up.

    Attributes
    ----------
    points, tets, mass, young, poisson, table_z, table_mu, timestep, damping:
        The object and the table, as in :class:`SceneSpec` (and validated by it).
    radius:
        Fingertip radius [m].
    tip_start:
        ``(3,)`` fingertip centre at the start [m], clear of the object's nodes and above the
        table. The fingertip rides on three world-axis slides, each a stiff position servo
        (:data:`TIP_KP`), commanded by :meth:`IndentScene.command`.
    mu:
        Fingertip-object Coulomb friction coefficient.
    """

    points: NDArray[np.float64]
    tets: NDArray[np.int64]
    mass: float
    young: float
    poisson: float
    radius: float
    tip_start: NDArray[np.float64]
    mu: float = 0.8
    table_z: float = 0.0
    table_mu: float = 0.5
    timestep: float = DEFAULT_TIMESTEP
    damping: float = DEFAULT_DAMPING
    _object: SceneSpec = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # the object and table fields go through SceneSpec's checks; its hand is never written
        obj = SceneSpec(
            hand=HandModel.default(),
            palm_pose=np.eye(4),
            q0={},
            points=self.points,
            tets=self.tets,
            mass=self.mass,
            young=self.young,
            poisson=self.poisson,
            mu=self.mu,
            table_z=self.table_z,
            table_mu=self.table_mu,
            timestep=self.timestep,
            damping=self.damping,
        )
        set_ = object.__setattr__
        for name in ("points", "tets", "mass", "young", "poisson", "mu", "table_z", "table_mu"):
            set_(self, name, getattr(obj, name))
        set_(self, "timestep", obj.timestep)
        set_(self, "damping", obj.damping)
        set_(self, "_object", obj)
        set_(self, "radius", _positive(self.radius, "fingertip radius", "m"))
        c = np.asarray(self.tip_start, dtype=np.float64)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ConfigError(f"tip_start must be 3 finite numbers [m], got {self.tip_start!r}")
        gap = float(np.min(np.linalg.norm(self.points - c, axis=1))) - self.radius
        if gap < 0.0:
            raise ConfigError(f"the fingertip starts {-1e3 * gap:.3f} mm inside the object's nodes")
        if c[2] - self.radius < self.table_z:
            raise ConfigError("the fingertip starts below the table top")
        c.setflags(write=False)
        set_(self, "tip_start", c)


def build_indent_mjcf(spec: IndentSpec) -> str:
    """MJCF text of a one-fingertip indentation scene; needs no MuJoCo.

    The options (discrete integrator, CG, elliptic cones, :data:`SOLVER_ITERATIONS`,
    :data:`SOLVER_TOLERANCE`), the table (geom ``table``) and the object (flex
    :data:`OBJECT_NAME`) are those of :func:`build_mjcf`. Instead of a hand: a sphere of
    ``spec.radius`` (geom ``<INDENT_TIP>_sphere``, friction ``mu``, priority 1, colliding with the
    object only) on a gravity-compensated body on three world-axis slides whose ``qpos`` is the
    displacement from ``tip_start``, each driven by a position servo (:data:`TIP_KP`,
    :data:`TIP_DAMPING`): a real motion with a velocity, like the arm of :func:`build_mjcf`.
    """
    if not isinstance(spec, IndentSpec):
        raise ConfigError(f"build_indent_mjcf needs an IndentSpec, got {type(spec).__name__}")
    pts = spec.points
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = 0.5 * (lo + hi)
    reach = max(float(np.max(hi - lo)), 0.25)

    root = _root("softgrasp_indentation", spec.timestep)
    _sub(root, "statistic", center=_vec(centre), extent=_num(2.0 * reach))
    world = _sub(root, "worldbody")
    _sub(
        world, "light", name="key", pos=_vec(centre + [0.3, -0.3, 1.0]), dir="-0.3 0.3 -1", directional="true"
    )
    _add_table(world, centre, reach, spec.table_z, spec.table_mu)
    tip = _sub(world, "body", name=INDENT_TIP, pos=_vec(spec.tip_start), gravcomp="1")
    _sub(tip, "inertial", pos="0 0 0", mass=_num(TIP_MASS), diaginertia=_vec([1e-3, 1e-3, 1e-3]))
    for axis, name in zip(np.eye(3), _TIP_JOINTS, strict=True):
        _sub(tip, "joint", name=name, type="slide", axis=_vec(axis), damping=_num(TIP_DAMPING))
    _sub(
        tip,
        "geom",
        name=_tip_geom_name(INDENT_TIP),
        type="sphere",
        size=_num(spec.radius),
        contype=str(_TIP_BIT),
        conaffinity=str(_OBJECT_BIT),
        rgba="0.9 0.75 0.6 1",
        **_contact_attrs(spec.mu),
    )
    _add_object(world, spec._object)
    actuator = _sub(root, "actuator")
    for name in _TIP_JOINTS:
        _sub(actuator, "position", name=_actuator_name(name), joint=name, kp=_num(TIP_KP))
    ET.indent(root, space="  ")
    return ET.tostring(root, encoding="unicode") + "\n"


def contact_force(model: Any, data: Any, geom: int) -> NDArray[np.float64]:
    """Total contact force [N] that geom ``geom`` exerts on what it touches, world frame, ``(3,)``.

    Sum over the active contacts of the geom (flex contacts included) of
    :func:`mujoco.mj_contactForce`, the force of side 0 on side 1 in the contact frame (rows of
    ``contact.frame``), negated where the geom is side 1. As of the last ``mj_forward``, or of the
    start of the last ``mj_step``.
    """
    mujoco = _import_mujoco()
    total = np.zeros(3)
    f6 = np.zeros(6)
    for i in range(int(data.ncon)):
        c = data.contact[i]
        if c.efc_address < 0:
            continue
        s = 1.0 if c.geom[0] == geom else -1.0 if c.geom[1] == geom else 0.0
        if s == 0.0:
            continue
        mujoco.mj_contactForce(model, data, i, f6)
        total += s * (c.frame.reshape(3, 3).T @ f6[:3])
    return total


class IndentScene:
    """A compiled indentation scene (made by :func:`load_indent_scene`): ``model`` (``MjModel``),
    ``data`` (``MjData``), ``spec`` and the fingertip's and the table's geom ids."""

    def __init__(self, model: Any, data: Any, spec: IndentSpec) -> None:
        mujoco = _import_mujoco()
        self._mj = mujoco
        self.model = model
        self.data = data
        self.spec = spec

        def ident(kind: Any, name: str) -> int:
            i = mujoco.mj_name2id(model, kind, name)
            if i < 0:
                raise ConfigError(f"the compiled indentation scene has no {kind.name[6:].lower()} {name!r}")
            return int(i)

        O = mujoco.mjtObj
        self.tip_geom = ident(O.mjOBJ_GEOM, _tip_geom_name(INDENT_TIP))
        self.table_geom = ident(O.mjOBJ_GEOM, "table")
        self._act = np.array([ident(O.mjOBJ_ACTUATOR, _actuator_name(n)) for n in _TIP_JOINTS])
        joints = [ident(O.mjOBJ_JOINT, n) for n in _TIP_JOINTS]
        self._qpos = np.array(model.jnt_qposadr[joints], dtype=np.int64)
        self._dof = np.array(model.jnt_dofadr[joints], dtype=np.int64)
        flex = ident(O.mjOBJ_FLEX, OBJECT_NAME)
        adr, num = int(model.flex_vertadr[flex]), int(model.flex_vertnum[flex])
        if num != spec.points.shape[0]:
            raise ConfigError(f"the compiled flex has {num} vertices, the spec {spec.points.shape[0]} points")
        self._verts = slice(adr, adr + num)

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return float(self.data.time)

    def tip_position(self) -> NDArray[np.float64]:
        """Fingertip centre [m], ``(3,)`` (as of the last step or forward)."""
        return np.array(self.data.geom_xpos[self.tip_geom], dtype=np.float64)

    def _offset(self, centre: ArrayLike) -> NDArray[np.float64]:
        c = np.asarray(centre, dtype=np.float64)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ConfigError(f"a fingertip centre must be 3 finite numbers [m], got {centre!r}")
        return c - self.spec.tip_start

    def command(self, centre: ArrayLike) -> None:
        """Command the fingertip centre to ``centre`` [m]; the servos move it there."""
        self.data.ctrl[self._act] = self._offset(centre)

    def place(self, centre: ArrayLike) -> None:
        """Put the fingertip at ``centre`` [m] at once, at rest, with its servos holding it there:
        a teleport for setting up (nothing it touches is carried along), not a motion."""
        d = self._offset(centre)
        self.data.qpos[self._qpos] = d
        self.data.qvel[self._dof] = 0.0
        self.data.ctrl[self._act] = d
        self._mj.mj_kinematics(self.model, self.data)

    def fingertip_force(self) -> NDArray[np.float64]:
        """Contact force [N] of the fingertip ON THE OBJECT, world frame, ``(3,)``."""
        return contact_force(self.model, self.data, self.tip_geom)

    def table_force(self) -> NDArray[np.float64]:
        """Contact force [N] of the table on the object, world frame, ``(3,)``."""
        return contact_force(self.model, self.data, self.table_geom)

    def object_nodes(self) -> NDArray[np.float64]:
        """``(N, 3)`` flex vertex positions [m] in the order of ``spec.points`` (as of the last
        step or forward)."""
        return np.array(self.data.flexvert_xpos[self._verts], dtype=np.float64)

    def forward(self) -> None:
        """Recompute positions, contacts and contact forces of the current state."""
        self._mj.mj_forward(self.model, self.data)

    def step(self, n: int = 1) -> None:
        """Advance the simulation by ``n`` time steps."""
        if isinstance(n, bool) or int(n) != n or n < 1:
            raise ConfigError(f"n = {n} must be an integer >= 1")
        self._mj.mj_step(self.model, self.data, nstep=int(n))


def load_indent_scene(spec: IndentSpec) -> IndentScene:
    """Compile :func:`build_indent_mjcf` of ``spec``: the scene at rest, the fingertip at
    ``tip_start``. :class:`ConfigError` if MuJoCo is missing or rejects the model."""
    mujoco = _import_mujoco()
    try:
        model = mujoco.MjModel.from_xml_string(build_indent_mjcf(spec))
    except ValueError as exc:
        raise ConfigError(f"MuJoCo rejected the indentation scene: {exc}") from None
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return IndentScene(model, data, spec)
