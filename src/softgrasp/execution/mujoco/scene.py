"""A compiled MuJoCo grasp scene: :func:`load_scene` and the look-ups of :class:`MujocoScene`.

:func:`load_scene` compiles :func:`~softgrasp.execution.mujoco.mjcf.build_mjcf` of a
:class:`~softgrasp.execution.mujoco.spec.SceneSpec` and returns a :class:`MujocoScene`: the model,
the data and the index look-ups an executor needs (joint ``qpos`` addresses, servo slots,
fingertip geoms, flex vertices), the contact forces on the object and the arm's commands. MuJoCo
is imported only when a scene is loaded, so this module imports without it.

Notes: after :meth:`MujocoScene.step` the derived quantities MuJoCo stores (body and vertex
positions, contacts, contact forces) are those of the start of the last step, the ``mj_step``
convention; ``mujoco.mj_forward`` refreshes them. ``mj_rnePostConstraint`` (``cfrc_ext``) ignores
flex contacts in MuJoCo 4.0; forces on the object are read from the contacts themselves
(:func:`contact_force`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from softgrasp.errors import ConfigError, SimulationUnstable
from softgrasp.execution.mujoco.elements import actuator_name, tip_geom_name
from softgrasp.execution.mujoco.mjcf import build_mjcf
from softgrasp.execution.mujoco.options import ARM_JOINTS, MAX_NEWTON_RUN, OBJECT_NAME
from softgrasp.execution.mujoco.spec import SceneSpec, rigid_transform
from softgrasp.offscreen import prefer_headless_gl

__all__ = [
    "MUJOCO_MISSING",
    "MujocoScene",
    "blow_up",
    "contact_force",
    "import_mujoco",
    "load_scene",
]

#: Message of the :class:`ConfigError` raised when MuJoCo cannot be imported.
MUJOCO_MISSING = "MuJoCo is not installed (softgrasp's 'execute' extra): pip install 'softgrasp[execute]'"


def _log_warning(message: str) -> None:
    import logging

    logging.getLogger("softgrasp.mujoco").debug("MuJoCo: %s", message)


def import_mujoco() -> Any:
    """The ``mujoco`` module; :class:`ConfigError` (:data:`MUJOCO_MISSING`) if it is not installed.

    Imported for the first time, it renders offscreen through :data:`GL_BACKEND` unless the user
    chose otherwise (:func:`prefer_headless_gl`). MuJoCo's warnings go to the ``softgrasp.mujoco``
    logger (DEBUG) instead of stderr and a ``MUJOCO_LOG.TXT`` in the working folder; the scenes
    read them from ``data.warning``."""
    prefer_headless_gl()
    try:
        import mujoco
    except ImportError:
        raise ConfigError(MUJOCO_MISSING) from None
    if mujoco.get_mju_user_warning() is not _log_warning:
        mujoco.set_mju_user_warning(_log_warning)
    return mujoco


#: MuJoCo's warnings that it reset the simulation after a non-finite or huge state.
_BLOWUPS = {"mjWARN_BADQACC": "accelerations", "mjWARN_BADQVEL": "velocities", "mjWARN_BADQPOS": "positions"}


def blow_up(model: Any, data: Any, t_before: float) -> str | None:
    """What went wrong if MuJoCo met a NaN, Inf or huge value in the state during the steps
    since ``t_before`` [s] (it then resets the simulation to time 0 and goes on, so a run driven
    by the simulated time would never end), or the state is not finite; None if nothing did."""
    mujoco = import_mujoco()
    for name, what in _BLOWUPS.items():
        w = data.warning[getattr(mujoco.mjtWarning, name)]
        if w.number > 0:
            dof, where = int(w.lastinfo), ""
            if 0 <= dof < model.nv:
                body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.dof_bodyid[dof]))
                where = f" of body {body}" if body else ""
            return f"NaN, Inf or huge {what}{where}"
    if not (np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))):
        return "non-finite positions or velocities"
    if data.time < t_before:
        return "the simulation was reset"
    return None


def contact_force(model: Any, data: Any, geom: int) -> NDArray[np.float64]:
    """Total contact force [N] that geom ``geom`` exerts on what it touches, world frame, ``(3,)``.

    Sum over the active contacts of the geom (flex contacts included) of
    :func:`mujoco.mj_contactForce`, the force of side 0 on side 1 in the contact frame (rows of
    ``contact.frame``), negated where the geom is side 1. As of the last ``mj_forward``, or of the
    start of the last ``mj_step``.
    """
    mujoco = import_mujoco()
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


class MujocoScene:
    """A compiled scene: ``model`` (``mujoco.MjModel``), ``data`` (``mujoco.MjData``) and look-ups.

    Made by :func:`load_scene`. ``fingers`` are the hand's finger names; ``spec`` the
    :class:`SceneSpec` it was built from.
    """

    def __init__(self, model: Any, data: Any, spec: SceneSpec) -> None:
        mujoco = import_mujoco()
        self._mj = mujoco
        self.model = model
        self.data = data
        self.spec = spec
        self.fingers: tuple[str, ...] = tuple(spec.hand.fingers)
        #: Steps taken; those whose CG solve stopped at ``opt.iterations`` and were taken again
        #: with MuJoCo's Newton solver (:meth:`step`); and those Newton left capped too
        #: (:attr:`solver_capped_share`).
        self.steps = 0
        self.newton_steps = 0
        self.capped_steps = 0
        self._state_kind = mujoco.mjtState.mjSTATE_INTEGRATION
        self._saved = np.empty(mujoco.mj_stateSize(model, self._state_kind))
        self._newton_left = 0  # steps still to take with Newton (step)
        self._newton_run = 0  # how many the last capped CG step started (0: the last CG step was resolved)

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
                [ident(A, actuator_name(n)) for n in chain.joint_names], dtype=np.int64
            )
            self._tip[finger] = ident(G, tip_geom_name(chain.tip_link))
        self._flex = ident(mujoco.mjtObj.mjOBJ_FLEX, OBJECT_NAME)
        adr, num = int(model.flex_vertadr[self._flex]), int(model.flex_vertnum[self._flex])
        if num != spec.points.shape[0]:
            raise ConfigError(f"the compiled flex has {num} vertices, the spec {spec.points.shape[0]} points")
        self._verts = slice(adr, adr + num)
        self._vert_mass = np.array(model.body_mass[model.flex_vertbodyid[self._verts]], dtype=np.float64)
        self._arm_act = np.array([ident(A, actuator_name(n)) for n in ARM_JOINTS], dtype=np.int64)
        self._arm_qpos = np.array([model.jnt_qposadr[ident(J, n)] for n in ARM_JOINTS], dtype=np.int64)
        self._palm_body = ident(mujoco.mjtObj.mjOBJ_BODY, self._palm_name())
        self._table = ident(G, "table")

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
        """Total contact force [N] the fingertip exerts ON THE OBJECT, world frame, ``(3,)``
        (:func:`contact_force` of its sphere)."""
        return contact_force(self.model, self.data, self._tip[self._finger(finger)])

    def table_force(self) -> NDArray[np.float64]:
        """Total contact force [N] the table exerts on the object, world frame, ``(3,)``."""
        return contact_force(self.model, self.data, self._table)

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
        T = rigid_transform(pose, "palm pose")
        T0 = self.spec.palm_pose
        if np.abs(T[:3, :3] - T0[:3, :3]).max() > 1e-9:
            raise ConfigError("the arm only translates the palm: its orientation must stay the starting one")
        d = T[:3, 3] - T0[:3, 3]
        self.data.qpos[self._arm_qpos] = d
        self.data.qvel[self.model.jnt_dofadr[self.model.actuator_trnid[self._arm_act, 0]]] = 0.0
        self.data.ctrl[self._arm_act] = d
        self._mj.mj_kinematics(self.model, self.data)

    @property
    def solver_capped_share(self) -> float:
        """The share of the steps taken whose constraint solve stopped at its iteration cap
        (``opt.iterations``) instead of its tolerance even with Newton's solver (:meth:`step`):
        their contact forces are not resolved (a heavy, soft object then sinks into the table)."""
        return self.capped_steps / self.steps if self.steps else 0.0

    @property
    def newton_share(self) -> float:
        """The share of the steps taken again with MuJoCo's Newton solver (:meth:`step`)."""
        return self.newton_steps / self.steps if self.steps else 0.0

    def forward(self) -> None:
        """Recompute the derived quantities (positions, contacts, contact forces) of the current
        state (after :meth:`step` they are those of the start of the last step)."""
        self._mj.mj_forward(self.model, self.data)

    def step(self, n: int = 1) -> None:
        """Advance the simulation by ``n`` time steps, one at a time.

        A step whose constraint solve (the scene's ``CG``) stops at its iteration cap
        (``opt.iterations``) has not resolved its contact forces: a heavy, soft object resting on
        the table then sinks into it. Such a step is taken again from the same state with
        MuJoCo's ``Newton`` solver, which folds the flex's stiffness into its Hessian and
        converges there in tens of iterations (:data:`~softgrasp.execution.mujoco.options.SOLVER`
        says why CG is the scene's solver). A load CG cannot resolve often lasts: when CG stops at
        its cap again right after Newton's steps, the run of steps taken by Newton doubles (1, 2,
        4, ... up to :data:`~softgrasp.execution.mujoco.options.MAX_NEWTON_RUN`), and it starts
        over at 1 once a CG step is resolved."""
        if isinstance(n, bool) or int(n) != n or n < 1:
            raise ConfigError(f"n = {n} must be an integer >= 1")
        mj, model, data = self._mj, self.model, self.data
        t = float(data.time)
        cap = int(model.opt.iterations)
        cg, newton = int(model.opt.solver), int(mj.mjtSolver.mjSOL_NEWTON)
        for _ in range(int(n)):
            if self._newton_left == 0 or cg == newton:
                mj.mj_getState(model, data, self._saved, self._state_kind)
                mj.mj_step(model, data)
                if int(data.solver_niter[0]) < cap or cg == newton:
                    self._newton_run = 0
                    self.capped_steps += int(data.solver_niter[0]) >= cap
                    continue
                mj.mj_setState(model, data, self._saved, self._state_kind)  # again, by Newton
                self._newton_run = min(2 * self._newton_run, MAX_NEWTON_RUN) or 1
                self._newton_left = self._newton_run
            model.opt.solver = newton
            try:
                mj.mj_step(model, data)
            finally:
                model.opt.solver = cg
            self._newton_left -= 1
            self.newton_steps += 1
            self.capped_steps += int(data.solver_niter[0]) >= cap
        self.steps += int(n)
        what = blow_up(self.model, self.data, t)
        if what is not None:
            sp = self.spec
            raise SimulationUnstable(
                f"MuJoCo's simulation became unstable after t = {t:.3f} s ({what}) with the object's "
                f"E = {sp.young:g} Pa, mass {sp.mass:g} kg and fingertip mu = {sp.mu:g}: check the plan's "
                "object.material.E_Pa, object.mass_kg and parameters.contact.mu (or --material) "
                "and re-plan with physical values"
            )


def load_scene(spec: SceneSpec) -> MujocoScene:
    """Compile the MJCF of ``spec`` and return the scene at its ``initial`` keyframe (``q0``).

    :class:`ConfigError` if MuJoCo is not installed or rejects the model.
    """
    mujoco = import_mujoco()
    xml = build_mjcf(spec)
    try:
        model = mujoco.MjModel.from_xml_string(xml)
    except ValueError as exc:
        raise ConfigError(f"MuJoCo rejected the scene: {exc}") from None
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    return MujocoScene(model, data, spec)
