"""MuJoCo indentation scene: one fingertip pressing the soft object on the table, without a hand.

:func:`build_indent_mjcf` / :func:`load_indent_scene` write and compile the table, the object and
the options of the grasp scene (:func:`softgrasp.execution.mujoco.mjcf.build_mjcf`: same
constants, same object builder) with one fingertip sphere instead of the hand, on three
world-axis slides under stiff servos (:class:`IndentSpec`, :class:`IndentScene`): the MuJoCo peer
of softgrasp's indentation experiment (:mod:`softgrasp.experiments.indentation`,
``benchmarks/bench_indent.py``). On the 388-node sphere, 3 mm over its centre: 3.8 N, 2.0 x Hertz
(the coarse mesh's stiffening, :mod:`softgrasp.execution.mujoco.flex`), and the fingertip's servo
carries exactly that force (``tests/test_mujoco_indent.py``). Pressed deep (15 mm, R = 8 mm) the
sphere wraps the fingertip and MuJoCo resolves the contact with one point per touching tet (6-9
points on 2196 nodes, up to 60 deg from vertical); friction on the fingertip's flanks then
carries about a third of the force (13.3 N with mu = 0.8, 8.9 N with mu = 0, 549 nodes) and
relaxes by creep once the fingertip stops (-4 % in 0.5 s at 549 nodes, -34 % at 2196; flat with
mu = 0 at 549).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ConfigError, SimulationUnstable
from softgrasp.execution.mujoco.elements import (
    actuator_name,
    add_table,
    contact_attrs,
    element,
    fnum,
    fvec,
    mujoco_root,
    tip_geom_name,
)
from softgrasp.execution.mujoco.flex import add_object
from softgrasp.execution.mujoco.options import (
    DEFAULT_DAMPING,
    DEFAULT_TIMESTEP,
    OBJECT_BIT,
    OBJECT_NAME,
    TIP_BIT,
)
from softgrasp.execution.mujoco.scene import blow_up, contact_force, import_mujoco
from softgrasp.execution.mujoco.spec import SceneSpec, positive
from softgrasp.hand.kinematics import HandModel

__all__ = [
    "INDENT_TIP",
    "TIP_MASS",
    "TIP_KP",
    "TIP_DAMPING",
    "IndentSpec",
    "IndentScene",
    "build_indent_mjcf",
    "load_indent_scene",
]

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
        set_(self, "radius", positive(self.radius, "fingertip radius", "m"))
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

    The options (discrete integrator, CG, elliptic cones, the solver budget of
    :mod:`softgrasp.execution.mujoco.options`), the table (geom ``table``) and the object (flex
    :data:`OBJECT_NAME`) are those of :func:`~softgrasp.execution.mujoco.mjcf.build_mjcf`. Instead of a
    hand: a sphere of ``spec.radius`` (geom ``<INDENT_TIP>_sphere``, friction ``mu``, priority 1,
    colliding with the object only) on a gravity-compensated body on three world-axis slides whose
    ``qpos`` is the displacement from ``tip_start``, each driven by a position servo (:data:`TIP_KP`,
    :data:`TIP_DAMPING`): a real motion with a velocity, like the arm of the grasp scene.
    """
    if not isinstance(spec, IndentSpec):
        raise ConfigError(f"build_indent_mjcf needs an IndentSpec, got {type(spec).__name__}")
    pts = spec.points
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = 0.5 * (lo + hi)
    reach = max(float(np.max(hi - lo)), 0.25)

    root = mujoco_root("softgrasp_indentation", spec.timestep)
    element(root, "statistic", center=fvec(centre), extent=fnum(2.0 * reach))
    world = element(root, "worldbody")
    element(
        world, "light", name="key", pos=fvec(centre + [0.3, -0.3, 1.0]), dir="-0.3 0.3 -1", directional="true"
    )
    add_table(world, centre, reach, spec.table_z, spec.table_mu)
    tip = element(world, "body", name=INDENT_TIP, pos=fvec(spec.tip_start), gravcomp="1")
    element(tip, "inertial", pos="0 0 0", mass=fnum(TIP_MASS), diaginertia=fvec([1e-3, 1e-3, 1e-3]))
    for axis, name in zip(np.eye(3), _TIP_JOINTS, strict=True):
        element(tip, "joint", name=name, type="slide", axis=fvec(axis), damping=fnum(TIP_DAMPING))
    element(
        tip,
        "geom",
        name=tip_geom_name(INDENT_TIP),
        type="sphere",
        size=fnum(spec.radius),
        contype=str(TIP_BIT),
        conaffinity=str(OBJECT_BIT),
        rgba="0.9 0.75 0.6 1",
        **contact_attrs(spec.mu),
    )
    add_object(world, spec._object)
    actuator = element(root, "actuator")
    for name in _TIP_JOINTS:
        element(actuator, "position", name=actuator_name(name), joint=name, kp=fnum(TIP_KP))
    ET.indent(root, space="  ")
    return ET.tostring(root, encoding="unicode") + "\n"


class IndentScene:
    """A compiled indentation scene (made by :func:`load_indent_scene`): ``model`` (``MjModel``),
    ``data`` (``MjData``), ``spec`` and the fingertip's and the table's geom ids."""

    def __init__(self, model: Any, data: Any, spec: IndentSpec) -> None:
        mujoco = import_mujoco()
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
        self.tip_geom = ident(O.mjOBJ_GEOM, tip_geom_name(INDENT_TIP))
        self.table_geom = ident(O.mjOBJ_GEOM, "table")
        self._act = np.array([ident(O.mjOBJ_ACTUATOR, actuator_name(n)) for n in _TIP_JOINTS])
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
        t = float(self.data.time)
        self._mj.mj_step(self.model, self.data, nstep=int(n))
        what = blow_up(self.model, self.data, t)
        if what is not None:
            raise SimulationUnstable(
                f"MuJoCo's indentation became unstable after t = {t:.3f} s ({what}) with the object's "
                f"E = {self.spec.young:g} Pa and mass {self.spec.mass:g} kg: check the material"
            )


def load_indent_scene(spec: IndentSpec) -> IndentScene:
    """Compile :func:`build_indent_mjcf` of ``spec``: the scene at rest, the fingertip at
    ``tip_start``. :class:`ConfigError` if MuJoCo is missing or rejects the model."""
    mujoco = import_mujoco()
    try:
        model = mujoco.MjModel.from_xml_string(build_indent_mjcf(spec))
    except ValueError as exc:
        raise ConfigError(f"MuJoCo rejected the indentation scene: {exc}") from None
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return IndentScene(model, data, spec)
