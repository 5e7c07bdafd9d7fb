"""The simulation settings of softgrasp's MuJoCo scenes, and why they are what they are.

Names, gains and solver options shared by the grasp scene
(:mod:`softgrasp.execution.mujoco.mjcf`) and the indentation scene
(:mod:`softgrasp.execution.mujoco.indent`). Written for MuJoCo 4.0 (the ``discrete`` integrator
they rely on appeared in 3.13).

Choices
-------
* **Integrator** ``discrete``, solver ``CG``, elliptic friction cones. ``discrete`` is the only
  MuJoCo integrator implicit in position: flex elasticity, servo gains and joint damping enter
  the effective inertia ``M + h D + h^2 K``. MuJoCo 4 refuses flex elasticity under
  ``implicit``/``implicitfast`` (engine error) and ``PGS``; ``Euler`` integrates it explicitly
  and blew up (NaN in ``qacc``) within 4 steps of 2 ms: the 388-node sphere's highest mode
  (estimated ~6e3 rad/s) limits explicit steps to ~3e-4 s. ``CG`` is matrix-free; ``Newton``
  gave the same forces (within 1 %) at 1.5-2.5x the cost (it folds the flex stiffness into its
  Hessian). Where CG stops at its iteration cap, its contact forces are not resolved: on a soft,
  heavy object (a 60 mm ball of E = 5 kPa, 111 g) resting on the table it did so in 21 % of the
  steps and the ball sank to a dome. Such a step is taken again with ``Newton``, which converges
  there in tens of iterations; when CG stops at its cap again right after, the next is taken
  by Newton together with the one after it, and so on, the run of Newton steps doubling up to
  :data:`MAX_NEWTON_RUN` while CG keeps stopping at its cap between runs:
  :meth:`softgrasp.execution.mujoco.scene.MujocoScene.step`. Runs starting at one step cost a
  2 196-node sphere's execution 1.2 times its time with CG alone (runs of 25 steps from every
  cap: 1.8 times); the default plan's execution takes 0.7 % of its steps by Newton, at no cost
  measurable.
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
* **Friction impedance** :func:`impratio`: :data:`IMPRATIO` = 3 on the default 388-node sphere,
  growing with the cube root of the object's node count. MuJoCo's soft friction lets a held
  object creep down through the fingertips: a friction row's force f comes with a slip velocity
  ``v = R f / b`` (``b``: the reference damping of ``solref``; ``R``: the regulariser, the
  ``(1 - d) / d`` share of the row's inverse inertia, ~1 / the vertex mass, divided by
  ``impratio``). Holding a weight ``M g`` on ``n_c`` contact rows gives
  ``v ~ g (M / m_vertex) / (n_c impratio) = g N / (n_c impratio)``; a finer mesh puts
  ``n_c ~ N^(2/3)`` rows in the same patch, so the creep grows as ``N^(1/3)`` unless
  ``impratio`` does. A fingertip on a tetrahedral flex touches one or two boundary tetrahedra,
  whose facets tilt from facet to facet: creep carries the contacts onto facets sloping the other
  way. At 1 (MuJoCo's default) the 745- and 2 196-node spheres crept 2.5 mm during the 0.10 m
  lift and slid out 65-70 mm up, at the planned set-points. At 3 on every mesh the 388-node
  sphere holds at 1.15 times softgrasp's critical scale and drops at 0.85 times it, but the
  2 196-node one drops at 1.0 (slides 84 mm) and is lifted only at 1.25; with the cube-root
  growth (5.35 there) it is lifted at 1.0 and at 1.15 times the critical scale (slip 2.6 and
  2.7 mm) and dropped at 0.85 times it, as the 388-node sphere; the 745-node one (3.73) is lifted
  as planned (1.3 mm). At 10 on the 388-node sphere the creep is
  smaller still but the friction no longer relaxes at all while the weight passes from the table
  to the fingers: it then needs 0.92-1.0 of its set-points (softgrasp's critical scale: 0.80). At
  100 the friction rows are so stiff that the force-controlled closing chatters and never
  settles. So MuJoCo's critical scale depends on this setting by up to 25 %: read its margins
  with that uncertainty.
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
"""

from __future__ import annotations

__all__ = [
    "ARM_NAME",
    "ARM_JOINTS",
    "ARM_MASS",
    "ARM_KP",
    "ARM_DAMPING",
    "DEFAULT_TIMESTEP",
    "DEFAULT_DAMPING",
    "SOLVER",
    "SOLVER_ITERATIONS",
    "SOLVER_TOLERANCE",
    "MAX_NEWTON_RUN",
    "IMPRATIO",
    "IMPRATIO_NODES",
    "impratio",
    "JOINT_KP",
    "JOINT_DAMPING",
    "JOINT_ARMATURE",
    "CONTACT_SOLREF",
    "CONTACT_SOLIMP",
    "EQUALITY_SOLREF",
    "EQUALITY_SOLIMP",
    "OBJECT_NAME",
    "TABLE_BIT",
    "TIP_BIT",
    "OBJECT_BIT",
    "SPIN_ROLL",
    "LINK_RADIUS",
]

#: Name of the arm body carrying the palm, and of its three world-axis slide joints.
ARM_NAME = "arm"
ARM_JOINTS = ("arm_x", "arm_y", "arm_z")
#: Arm mass [kg], servo stiffness [N/m] and joint damping [N s/m]: stiff (a 1 N load deflects it
#: 20 um) and about critically damped (2 sqrt(kp m) ~ 280 N s/m) with the hand's small mass.
ARM_MASS = 1.0
ARM_KP = 5.0e4
ARM_DAMPING = 450.0

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
#: The most steps one run with the Newton solver takes after CG steps that stopped at their cap
#: (module docstring).
MAX_NEWTON_RUN = 800

#: Ratio of the friction constraints' impedance to the normal one's (elliptic cones) on a flex of
#: :data:`IMPRATIO_NODES` vertices (module docstring; :func:`impratio`).
IMPRATIO = 3.0
#: The node count at which the friction impedance ratio is :data:`IMPRATIO` (the default sphere).
IMPRATIO_NODES = 388


def impratio(n_nodes: int) -> float:
    """The friction impedance ratio of a scene whose object flex has ``n_nodes`` vertices:
    ``IMPRATIO (n_nodes / IMPRATIO_NODES)^(1/3)``, under which MuJoCo's friction creep at a held
    weight does not grow with the mesh's refinement (module docstring)."""
    if n_nodes < 1:
        raise ValueError(f"a flex has at least one vertex, got {n_nodes}")
    return IMPRATIO * (n_nodes / IMPRATIO_NODES) ** (1.0 / 3.0)


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
TABLE_BIT, TIP_BIT, OBJECT_BIT = 1, 2, 4
#: Torsional and rolling friction coefficients of every contact (condim 3 uses neither).
SPIN_ROLL = (0.005, 0.0001)
#: Radius of the decorative link capsules, relative to the fingertip radius.
LINK_RADIUS = 0.8
