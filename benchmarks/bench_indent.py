"""Benchmark: one-fingertip indentation of the rubber sphere, softgrasp vs MuJoCo flex, same run.

The scene (the speed issue's target): the paper's rubber sphere (radius 64 mm, 50 g, E = 79.3 kPa,
nu = 0.45; :func:`softgrasp.model.objects.make_object`) rests on a table (friction 0.5); a rigid spherical
fingertip of R = 8 mm (friction 0.8) presses straight down on its top, 15 mm of travel from first
contact at 10 mm/s (1.5 s), then holds still until 2 s after first contact. Both engines get the
same tet mesh (softgrasp's own points and tets), the same E, nu and mass, in one process run, one
mesh size after the other.

How each side simulates it
--------------------------
* **softgrasp, quasi-static:** :func:`softgrasp.experiments.indentation.indentation_test`, the
  library's indentation experiment: a static solve settles the sphere on the table, first contact is
  found by bisection on the settled shape, then the 15 mm are cut into increments (``--increment``,
  default 0.5 mm = 50 ms of the motion), each a static Newton equilibrium with stick/slip friction;
  the same test with half the increment is run too, and the change of the force at 15 mm is printed
  (the increment-convergence check). Why it is a legitimate "2 s simulated": the motion is slow next
  to the sphere's dynamics (fundamental mode ~1 000 rad/s; the press lasts 1.5 s), so inertia and
  the body's damping do nothing measurable and the trajectory is a sequence of equilibria; and the
  model has no rate effect once the fingertip stops (elastic springs, dampers acting on velocities
  only), so the 0.5 s hold is the last equilibrium and costs nothing. Its wall time includes the
  settling solve and the first-contact search.
* **softgrasp, implicit:** the same scene as backward-Euler dynamics
  (:func:`softgrasp.sim.implicit.implicit_euler_step`, steps of ``--dt``, default 0.05 s = 0.5 mm
  of travel, a step whose Newton solve fails split in halves as ``indentation_test`` does) through
  the whole 2 s: 1.5 s pressing, then 0.5 s with the fingertip held still (30 + 10
  Newton solves, each with an inertia term; with dt omega ~ 50 every mode is damped, so it is
  quasi-static too, but it really integrates the hold). The sphere is settled by the same static
  solve, or, where that finds no rest (a fine sphere is neutrally stable on its facets and rolls,
  in MuJoCo too), by 0.1 s of backward Euler; the fingertip starts touching the settled surface
  above the sphere's centre. Its wall time includes the settling.
  ``--solver`` picks ``static``, ``implicit`` or ``both`` (default: both, one table row each).
* **MuJoCo 4.0 flex:** :func:`softgrasp.execution.mujoco.indent.load_indent_scene` builds the same object
  (``flexcomp`` dim 3 from softgrasp's points and tets, ``young``/``poisson``, mass spread evenly
  over the vertices), the table and the fingertip on three world-axis slides under stiff position
  servos (1e6 N/m, critically damped: 10 um under 10 N), with the settings of
  :mod:`softgrasp.execution.mujoco.options` (integrator ``discrete``, CG, elliptic cones, 2 ms steps, stiff
  contacts: solref 2 ms / solimp 0.999-0.9999, fingertip priority so its friction 0.8 is used as
  is, table 0.5). It settles 0.3 s under gravity (timed apart), the fingertip is placed 1 mm above
  the settled top over the vertices' mean (x, y) and moves down at 10 mm/s; first contact is the
  first step with a fingertip contact force. The timed run is the 2 s from first contact: the
  servo target keeps moving 1.5 s more, then holds. Travel is the measured fingertip centre's
  drop since first contact; force is the norm of the summed contact forces of the fingertip on
  the flex (:func:`softgrasp.execution.mujoco.scene.contact_force`), recorded every 5 steps.

Reported per mesh size: nodes, wall times [s] (softgrasp's whole test; MuJoCo's 2 s after first
contact, its compile and settle apart), the ratio MuJoCo / softgrasp, the force at the end of the
press (15 mm) and at 2 s for both, their relative difference, and Hertz for scale: the fingertip on
the sphere (R_eff = (1/64 + 1/8)^-1 mm) in series with the sphere on the table (R = 64 mm, already
carrying m g), E* = E / (1 - nu^2). At 15 mm Hertz is far outside its validity (the contact radius
would exceed the fingertip's radius): it is an order of magnitude, not a reference. With
``--diagnose`` the first mesh is also run (i) by softgrasp with a 10x stiffer contact law (K of
Eq. 11 times 10), which shows how much of softgrasp's travel is the contact law's own penetration,
and (ii) by both without fingertip friction, which shows friction's share of the force and of
MuJoCo's relaxation during the hold.

``--repeat N`` runs each side N times per size and keeps the fastest (all wall times are printed).
A PNG of force vs travel and force vs time (both sides, every size) goes to ``--out`` (default a
new temporary directory), with the figures as JSON.

Measured (commit bbf2c37 with the speed work in progress, MuJoCo 4.0.0, 2 shared cores, one BLAS
thread, ``--diagnose --repeat 2``, fastest of two; walls moved 20-40 % between runs of the day):

| nodes | softgrasp | sg wall [s] | MuJoCo [s] | ratio | F(15 mm) sg / MJ [N] | diff | F(2 s) sg / MJ [N] |
|---:|---|---:|---:|---:|---|---:|---|
| 549 | quasi-static | 2.29 | 14.9 | 6.5 | 10.01 / 13.32 | -25 % | 10.01 / 12.80 |
| 549 | implicit | 4.31 | 14.9 | 3.5 | 10.11 / 13.32 | -24 % | 10.11 / 12.80 |
| 2 196 | quasi-static | 14.8 | 90.3 | 6.1 | 7.76 / 7.91 | -2 % | 7.76 / 5.20 |
| 2 196 | implicit | 26.0 | 90.3 | 3.5 | 6.91 / 7.91 | -13 % | 6.91 / 5.20 |

Hertz (for scale): 11.9 N. MuJoCo alone on 7 576 nodes (``--sizes 0.005``): 659 s for the 2 s
(330 s of wall per simulated s, 123 contacts), 6.58 N at 15 mm; both softgrasp paths failed to
converge there (quasi-static at 10 mm of travel after 528 s). The MuJoCo figures are 4-7x the
issue's (1 / 16 / 106 s per simulated s): a deep press makes 35-120 contacts, and the cores were
shared.

Why the forces differ (``--diagnose`` on 549 nodes):

* **Mesh convergence of the flex.** MuJoCo's force at 15 mm falls from 13.3 N (549 nodes) to
  7.9 N (2 196) and 6.6 N (7 576): coarse linear tets lock at nu = 0.45 (see
  :mod:`softgrasp.execution.mujoco.scene`). softgrasp's falls less (10.0 -> 7.8 N). The -25 % at 549 nodes is
  mostly MuJoCo's coarse-mesh stiffness; at 2 196 nodes the two agree within 2 % at 15 mm.
* **Curve shape.** softgrasp follows Hertz's delta^1.5 at small travel (0.80 N at 2 mm on 549
  nodes, Hertz 0.8 N); MuJoCo is nearly linear from the start (2.24 N at 2 mm; 1.34 N on 2 196
  nodes): it resolves the contact by one point per touching tet, a punch of element size. Below
  ~8 mm the curves differ by up to a factor 2-3 even where they meet at 15 mm.
* **Where the travel goes.** softgrasp's contact law (K = 2 E* sqrt(R), Eq. 11) penetrates
  6.2-7.0 mm of the 15 mm, its body deforms the rest; MuJoCo's contact is nearly rigid (0.3 mm).
  With K x 10 softgrasp gives 17.6 N (+32 % over MuJoCo): the force depends on that choice.
* **Friction and the hold.** At 15 mm the sphere wraps the 8 mm fingertip; MuJoCo's friction on
  the fingertip's flanks carries a third of its force (13.3 N with mu 0.8, 8.9 N with mu 0) and
  creeps once the fingertip stops: -4 % in the 0.5 s hold on 549 nodes, -34 % on 2 196 (flat with
  mu 0). softgrasp's friction resultant is 0.3-1.1 N, and its hold keeps the force (elastic
  stick), hence the +49 % at 2 s on 2 196 nodes. softgrasp without friction did not converge
  (5.5 mm).
* **Hertz** is only a scale: at 15 mm its contact radius would exceed the fingertip's radius.

Run (2 cores shared: one BLAS thread, and repeat where it matters)::

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_indent.py [--fine] [--solver both]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq

from softgrasp.errors import NotConverged, SoftgraspError
from softgrasp.execution.mujoco.indent import IndentSpec, load_indent_scene
from softgrasp.experiments.indentation import indentation_test, surface_height
from softgrasp.linalg.solve import SolverCache
from softgrasp.model.material import Material
from softgrasp.model.mesh.tetmesh import TetMesh
from softgrasp.model.objects import SPHERE_RADIUS, make_object
from softgrasp.physics.body import STANDARD_GRAVITY, Body, build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import ContactParams, Fingertip
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim.implicit import implicit_euler_step
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.static import solve_static

#: Mesh sizes [m] run by default (549 and 2 196 nodes) and with --fine (7 576 nodes).
SIZES = (0.014, 0.008)
FINE_SIZE = 0.005
#: Fingertip radius [m], travel from first contact [m], speed [m/s], simulated time from first contact [s].
RADIUS = 0.008
DEPTH = 0.015
SPEED = 0.010
DURATION = 2.0
#: Friction: fingertip-object and table-object.
MU = 0.8
TABLE_MU = 0.5
#: softgrasp implicit: settling time [s] by backward Euler where no static rest exists.
SG_SETTLE = 0.1
#: softgrasp implicit: how often a failing step may be halved.
SG_HALVINGS = 4
#: MuJoCo: settling time [s] before the fingertip moves, start gap above the top [m], record period [steps].
MJ_SETTLE = 0.3
MJ_GAP = 1e-3
MJ_RECORD = 5
#: Travels [m] at which the details compare the force curves.
CHECKPOINTS = (0.002, 0.005, 0.010, 0.015)
CHECKPOINT_LABEL = " / ".join(f"{1e3 * d:g}" for d in CHECKPOINTS)
#: Name of the quasi-static run at half the increment (the increment-convergence check).
HALF_INCREMENT = "softgrasp quasi-static, half increment"
#: Issue's tolerance on the force difference.
TOLERANCE = 0.25


@dataclass
class Run:
    """One side's run on one mesh: wall time [s] and the force record.

    time_s, travel_m, force_N: time since first contact [s], fingertip travel since first contact
    [m], norm of the fingertip's force on the object [N], each (K,).
    """

    name: str
    wall_s: float
    time_s: NDArray[np.float64]
    travel_m: NDArray[np.float64]
    force_N: NDArray[np.float64]
    extra: dict[str, Any] = field(default_factory=dict)
    error: str | None = None

    @property
    def ok(self) -> bool:
        """Whether the run finished (``error`` holds the failure's message otherwise)."""
        return self.error is None

    def at_time(self, t: float) -> tuple[float, float]:
        """(travel [m], force [N]) at the record entry closest to time ``t`` [s]."""
        k = int(np.argmin(np.abs(self.time_s - t)))
        return float(self.travel_m[k]), float(self.force_N[k])


# ---------------------------------------------------------------------- softgrasp


def softgrasp_static(
    body: Body, increment: float, params: ContactParams | None = None, name: str = "softgrasp quasi-static"
) -> Run:
    """softgrasp's indentation experiment (quasi-static increments of ``increment`` [m]); contact
    ``params`` default to the paper's law with friction :data:`MU`."""
    steps = max(1, round(DEPTH / increment))
    r = indentation_test(
        body,
        depth=DEPTH,
        radius=RADIUS,
        speed=SPEED,
        steps=steps,
        params=params if params is not None else ContactParams(mu=MU),
        table_mu=TABLE_MU,
    )
    # the hold: the last equilibrium, unchanged (nothing in the model depends on time at rest)
    t = np.append(r.penetration_m / SPEED, DURATION)
    return Run(
        name,
        r.wall_time_s,
        t,
        np.append(r.penetration_m, r.penetration_m[-1]),
        np.append(r.force_N, r.force_N[-1]),
        {
            "increments": steps,
            "newton_iterations": int(r.newton_iterations.sum()),
            "contact_depth_m": float(r.contact_depth_m[-1]),
            "friction_N": float(r.tangential_force_N[-1]),
            "halvings": r.halvings,
        },
    )


def _euler(
    scene: Scene, state: State, t_end: float, dt: float, cache: SolverCache, record, halvings: list[int]
) -> State:
    """Backward Euler from ``state.t`` to ``t_end`` in equal steps of at most ``dt`` [s]; a step
    whose Newton solve fails is split in halves (up to :data:`SG_HALVINGS` times; the splits are
    counted in ``halvings[0]``). ``record`` is called with every accepted state."""
    n = max(1, math.ceil((t_end - state.t) / dt - 1e-9))
    h = (t_end - state.t) / n
    for k in range(1, n + 1):
        target = state.t + h if k < n else t_end
        parts = 1
        while state.t < target - 1e-12:
            try:
                new = implicit_euler_step(scene, state, (target - state.t) / parts, cache=cache)
            except NotConverged:
                if parts >= 2**SG_HALVINGS:
                    raise
                parts *= 2
                halvings[0] += 1
                continue
            state = new
            parts = max(1, parts - 1)
            record(state)
    return state


def softgrasp_implicit(body: Body, dt: float) -> Run:
    """Backward-Euler dynamics of the same scene: press 1.5 s, hold to 2 s, steps of ``dt`` [s]."""
    t_start = time.perf_counter()
    x0 = np.asarray(body.mesh.points)
    table = PlaneContact(
        Plane(np.array([0.0, 0.0, float(x0[:, 2].min())]), np.array([0.0, 0.0, 1.0])),
        mu=TABLE_MU,
        name="table",
    )
    cache = SolverCache()
    rest = Scene(body, (table,))
    halvings = [0]
    try:
        settled, _ = solve_static(rest, rest.initial_state(), cache=cache)
        settle = "static"
    except NotConverged:
        # No static rest without the fingertip (a sphere neutrally stable on its facets): settle
        # by backward Euler for SG_SETTLE s instead and press where the sphere then is.
        settled = _euler(rest, rest.initial_state(), SG_SETTLE, dt, cache, lambda st: None, halvings)
        settled = State(settled.x, np.zeros_like(settled.x), 0.0, settled.contacts)
        settle = f"implicit {SG_SETTLE:g} s"
    xy = settled.x[:, :2].mean(axis=0) - body.mesh.points[:, :2].mean(axis=0) + body.mesh.centroid[:2]
    zs, _ = surface_height(settled.x, body.mesh.facets, xy)
    params = ContactParams(mu=MU)
    press = Fingertip(RADIUS, centre=np.array([xy[0], xy[1], zs + RADIUS]), velocity=np.array([0, 0, -SPEED]))
    finger = FingertipContact((press,), params)
    rows: list[tuple[float, float, float]] = []
    n_contacts = [0]

    def recorder(fc: FingertipContact):
        def record(st: State) -> None:
            rep = fc.report(body, st.x, st.v, st.t, st.contacts[1])
            n_contacts[0] = int(rep.contacts[0])
            rows.append((st.t, SPEED * min(st.t, DEPTH / SPEED), float(np.linalg.norm(rep.force[0]))))

        return record

    state = State(
        settled.x, np.zeros_like(settled.x), 0.0, (settled.contacts[0], finger.init_state(body, settled.x))
    )
    recorder(finger)(state)
    state = _euler(Scene(body, (table, finger)), state, DEPTH / SPEED, dt, cache, recorder(finger), halvings)
    if n_contacts[0] == 0:
        raise RuntimeError("softgrasp implicit: the fingertip is not in contact at the end of the press")
    held = FingertipContact((Fingertip(RADIUS, centre=press.centre_at(DEPTH / SPEED)),), params)
    _euler(Scene(body, (table, held)), state, DURATION, dt, cache, recorder(held), halvings)
    a = np.array(rows)
    extra = {"dt_s": dt, "steps": len(rows) - 1, "halvings": halvings[0], "settled": settle}
    return Run("softgrasp implicit", time.perf_counter() - t_start, a[:, 0], a[:, 1], a[:, 2], extra)


# ---------------------------------------------------------------------- MuJoCo


def mujoco_flex(
    mesh: TetMesh, material: Material, mass: float, mu: float = MU, name: str = "MuJoCo flex"
) -> Run:
    """MuJoCo 4 flex: the same mesh, material, table and fingertip motion (module docstring)."""
    pts = np.asarray(mesh.points)
    top = float(pts[:, 2].max())
    t0 = time.perf_counter()
    spec = IndentSpec(
        points=pts,
        tets=mesh.tets,
        mass=mass,
        young=material.E,
        poisson=material.nu,
        radius=RADIUS,
        tip_start=np.array([0.0, 0.0, top + RADIUS + 0.01]),
        mu=mu,
        table_z=float(pts[:, 2].min()),
        table_mu=TABLE_MU,
    )
    scene = load_indent_scene(spec)
    compile_s = time.perf_counter() - t0
    dt = float(scene.model.opt.timestep)

    t0 = time.perf_counter()
    scene.step(round(MJ_SETTLE / dt))
    scene.forward()
    settle_s = time.perf_counter() - t0
    x = scene.object_nodes()
    xy = x[:, :2].mean(axis=0)
    start = np.array([xy[0], xy[1], float(x[:, 2].max()) + RADIUS + MJ_GAP])
    scene.place(start)

    # approach at SPEED until the first step that reports a fingertip force (the contacts and
    # positions read after mj_step are those of the start of that step)
    k = 0
    while not np.any(scene.fingertip_force()):
        k += 1
        if k * dt * SPEED > 5 * MJ_GAP:
            raise RuntimeError("MuJoCo: the fingertip never touched the sphere")
        scene.command(start - [0.0, 0.0, SPEED * k * dt])
        scene.step()
    # first contact: the state at the start of approach step k; the current state is one step later
    z_first = float(scene.tip_position()[2])

    rows: list[tuple[float, float, float]] = []
    n_steps = round(DURATION / dt)
    n_press = round(DEPTH / SPEED / dt)
    t0 = time.perf_counter()
    for j in range(1, n_steps):
        # step j runs from j dt to (j + 1) dt after first contact; the ramp stops at 1.5 s
        scene.command(start - [0.0, 0.0, SPEED * (k + min(j, n_press)) * dt])
        scene.step()
        if j % MJ_RECORD == 0 or j == n_press:
            # the positions and contacts read after mj_step are those of the step's start
            tip, force = scene.tip_position(), scene.fingertip_force()
            rows.append((j * dt, z_first - float(tip[2]), float(np.linalg.norm(force))))
    scene.forward()  # the final state, 2 s after first contact
    tip, force = scene.tip_position(), scene.fingertip_force()
    rows.append((n_steps * dt, z_first - float(tip[2]), float(np.linalg.norm(force))))
    wall = time.perf_counter() - t0
    warnings = {int(i): int(w.number) for i, w in enumerate(scene.data.warning) if w.number}
    a = np.array(rows)
    return Run(
        name,
        wall,
        a[:, 0],
        a[:, 1],
        a[:, 2],
        {
            "compile_s": compile_s,
            "settle_s": settle_s,
            "timestep_s": dt,
            "contacts_end": int(scene.data.ncon),
            "table_force_end_N": float(scene.table_force()[2]),
            "warnings": float(sum(warnings.values())),
            "sphere_shift_mm": float(1e3 * np.linalg.norm(xy - pts[:, :2].mean(axis=0))),
        },
    )


# ---------------------------------------------------------------------- Hertz


def hertz_force(travel: float, material: Material, mass: float) -> float:
    """Hertz's force [N] for a fingertip travel [m] from first contact: the rigid fingertip on the
    sphere in series with the sphere on the rigid table, which already carries m g."""
    E_star = material.E / (1.0 - material.nu**2)
    R_eff = 1.0 / (1.0 / SPHERE_RADIUS + 1.0 / RADIUS)

    def delta(F: float, R: float) -> float:
        return (3.0 * F / (4.0 * E_star * math.sqrt(R))) ** (2.0 / 3.0)

    W = mass * STANDARD_GRAVITY
    if travel <= 0.0:
        return 0.0
    return float(
        brentq(
            lambda F: delta(F, R_eff) + delta(F + W, SPHERE_RADIUS) - delta(W, SPHERE_RADIUS) - travel,
            0.0,
            1e4,
        )
    )


# ---------------------------------------------------------------------- driver


def _attempt(name: str, fn, *args) -> Run:
    """Run one side; a solver failure is reported (as a run without records), not fatal."""
    t0 = time.perf_counter()
    try:
        return fn(*args)
    except (SoftgraspError, RuntimeError) as exc:
        empty = np.zeros(0)
        return Run(name, time.perf_counter() - t0, empty, empty, empty, error=f"{type(exc).__name__}: {exc}")


def _timed(repeat: int, name: str, fn, *args) -> Run:
    """:func:`_attempt` ``repeat`` times; the fastest run, with every wall time in ``extra``."""
    runs = []
    for _ in range(repeat):
        runs.append(_attempt(name, fn, *args))
        status = f"{runs[-1].wall_s:.1f} s" if runs[-1].ok else f"failed after {runs[-1].wall_s:.1f} s"
        print(f"    {name}: {status}", flush=True)
    best = min(runs, key=lambda r: (not r.ok, r.wall_s))
    if repeat > 1:
        best.extra["walls_s"] = [round(r.wall_s, 2) for r in runs]
    return best


def bench_size(
    h: float, solvers: tuple[str, ...], increment: float, dt: float, diagnose: bool, repeat: int = 1
) -> dict:
    mesh, material, mass = make_object("sphere", h)
    assert mass is not None
    print(f"  h = {h * 1e3:g} mm: {mesh.n_nodes} nodes", flush=True)
    t0 = time.perf_counter()
    body = build_body(mesh, material, mass=mass)
    build_s = time.perf_counter() - t0
    runs: list[Run] = []
    if "static" in solvers:
        runs.append(_timed(repeat, "softgrasp quasi-static", softgrasp_static, body, increment))
    if "implicit" in solvers:
        runs.append(_timed(repeat, "softgrasp implicit", softgrasp_implicit, body, dt))
    mj = _timed(repeat, "MuJoCo flex", mujoco_flex, mesh, material, mass)
    diag: list[Run] = []
    if "static" in solvers:
        # Is the quasi-static path converged in its increment? The same test at half of it.
        name = HALF_INCREMENT
        diag.append(_timed(1, name, softgrasp_static, body, 0.5 * increment, None, name))
    if diagnose:
        stiff = ContactParams(mu=MU, prefactor=10.0 * ContactParams().prefactor)
        name = "softgrasp quasi-static, K x10"
        diag.append(_timed(1, name, softgrasp_static, body, increment, stiff, name))
        name = "softgrasp quasi-static, mu 0"
        diag.append(_timed(1, name, softgrasp_static, body, increment, ContactParams(mu=0.0), name))
        name = "MuJoCo flex, mu 0"
        diag.append(_timed(1, name, mujoco_flex, mesh, material, mass, 0.0, name))
    return {
        "h": h,
        "nodes": mesh.n_nodes,
        "tets": len(mesh.tets),
        "build_s": build_s,
        "material": material,
        "mass": mass,
        "softgrasp": runs,
        "mujoco": mj,
        "diagnostic": diag,
    }


def _row(res: dict, sg: Run, mj: Run, hertz: float) -> str:
    t_press = DEPTH / SPEED
    cells = [str(res["nodes"]), sg.name.removeprefix("softgrasp ")]
    cells.append(f"{sg.wall_s:.2f}" if sg.ok else f"failed after {sg.wall_s:.1f}")
    cells.append(f"{mj.wall_s:.2f}" if mj.ok else f"failed after {mj.wall_s:.1f}")
    cells.append(f"{mj.wall_s / sg.wall_s:.2f}" if sg.ok and mj.ok else "-")
    f_sg = sg.at_time(t_press)[1] if sg.ok else math.nan
    d_mj, f_mj = mj.at_time(t_press) if mj.ok else (math.nan, math.nan)
    cells.append(f"{f_sg:.3f}")
    cells.append(f"{f_mj:.3f} (at {d_mj * 1e3:.2f} mm)")
    diff = (f_sg - f_mj) / f_mj
    cells.append(f"{diff:+.0%}" + ("" if abs(diff) <= TOLERANCE or math.isnan(diff) else " (!)"))
    f_sg_end = sg.at_time(DURATION)[1] if sg.ok else math.nan
    f_mj_end = mj.at_time(DURATION)[1] if mj.ok else math.nan
    cells.append(f"{f_sg_end:.3f} / {f_mj_end:.3f}")
    cells.append(f"{hertz:.2f}")
    return "| " + " | ".join(cells) + " |"


def _increment_check(res: dict) -> str | None:
    """The relative change of the quasi-static F(15 mm) when the increment is halved."""
    main = [r for r in res["softgrasp"] if r.name == "softgrasp quasi-static" and r.ok]
    half = [r for r in res["diagnostic"] if r.name == HALF_INCREMENT]
    if not main or not half:
        return None
    if not half[0].ok:
        return f"    {HALF_INCREMENT}: failed ({half[0].error})"
    f1 = main[0].at_time(DEPTH / SPEED)[1]
    f2 = half[0].at_time(DEPTH / SPEED)[1]
    return (
        f"    increment convergence: F(15 mm) {f1:.4f} N, with half the increment {f2:.4f} N "
        f"({(f1 - f2) / f2:+.2%}); wall {main[0].wall_s:.2f} s vs {half[0].wall_s:.2f} s"
    )


def report(results: list[dict]) -> None:
    print(
        "\n| nodes | softgrasp solver | softgrasp wall [s] | MuJoCo wall [s] | MuJoCo / softgrasp "
        "| F(15 mm) sg [N] | F(15 mm) MJ [N] | sg vs MJ | F(2 s) sg / MJ [N] | Hertz [N] |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|---|---:|")
    for res in results:
        hertz = hertz_force(DEPTH, res["material"], res["mass"])
        for sg in res["softgrasp"]:
            print(_row(res, sg, res["mujoco"], hertz))
    print("\nDetails")
    for res in results:
        mj = res["mujoco"]
        print(f"  {res['nodes']} nodes, {res['tets']} tets (h = {res['h'] * 1e3:g} mm):")
        print(f"    softgrasp build_body {res['build_s']:.2f} s")
        if mj.ok:
            e = mj.extra
            print(
                f"    MuJoCo: compile {e['compile_s']:.2f} s, settle {MJ_SETTLE:g} s simulated in "
                f"{e['settle_s']:.2f} s ({e['settle_s'] / MJ_SETTLE:.1f} s/s), the 2 s run "
                f"{mj.wall_s / DURATION:.1f} s of wall per simulated s; {e['contacts_end']:.0f} contacts "
                f"at the end, table {e['table_force_end_N']:.2f} N, {e['warnings']:.0f} warnings, the "
                f"sphere moved {e['sphere_shift_mm']:.2f} mm while settling"
                + (f"; 2 s runs {e['walls_s']} s" if "walls_s" in e else "")
            )
        else:
            print(f"    MuJoCo failed: {mj.error}")
        if mj.ok:
            e_press = mj.time_s <= DEPTH / SPEED + 1e-9
            curve = " / ".join(
                f"{np.interp(d, mj.travel_m[e_press], mj.force_N[e_press]):.2f}" for d in CHECKPOINTS
            )
            print(f"    MuJoCo at {CHECKPOINT_LABEL} mm: {curve} N; {mj.at_time(DURATION)[1]:.3f} N at 2 s")
        check = _increment_check(res)
        if check:
            print(check)
        for sg in [*res["softgrasp"], *res["diagnostic"]]:
            if not sg.ok:
                print(f"    {sg.name} failed: {sg.error}")
                continue
            extra = ", ".join(
                f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in sg.extra.items()
            )
            press = sg.time_s <= DEPTH / SPEED + 1e-9
            curve = " / ".join(
                f"{np.interp(d, sg.travel_m[press], sg.force_N[press]):.2f}" for d in CHECKPOINTS
            )
            print(f"    {sg.name}: at {CHECKPOINT_LABEL} mm {curve} N; {extra}")
            if "contact_depth_m" in sg.extra and mj.ok:
                body_travel = DEPTH - sg.extra["contact_depth_m"]
                press = mj.time_s <= DEPTH / SPEED + 1e-9
                on_mj = float(np.interp(body_travel, mj.travel_m[press], mj.force_N[press]))
                print(
                    f"      its contact law takes {sg.extra['contact_depth_m'] * 1e3:.2f} mm of the 15 mm; "
                    f"MuJoCo's force at the remaining {body_travel * 1e3:.2f} mm: {on_mj:.3f} N"
                )


def _runs(res: dict) -> list[Run]:
    """All runs of one mesh size: softgrasp's, MuJoCo's and the diagnostic's."""
    return [*res["softgrasp"], res["mujoco"], *res["diagnostic"]]


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(13, 5.2))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    styles = {"softgrasp quasi-static": "-o", "softgrasp implicit": "-.s", "MuJoCo flex": "--"}
    for c, res in zip(colours, results, strict=False):
        n = res["nodes"]
        for run in _runs(res):
            if not run.ok:
                continue
            st = styles.get(run.name, ":" if run.name.startswith("MuJoCo") else ":^")
            ms = 3 if "o" in st or "s" in st or "^" in st else 0
            press = run.time_s <= DEPTH / SPEED + 1e-9
            ax1.plot(
                1e3 * run.travel_m[press],
                run.force_N[press],
                st,
                color=c,
                ms=ms,
                lw=1.3,
                label=f"{run.name}, {n} nodes",
            )
            ax2.plot(run.time_s, run.force_N, st, color=c, ms=ms, lw=1.3, label=f"{run.name}, {n} nodes")
    d = np.linspace(0.0, DEPTH, 61)
    res0 = results[0]
    ax1.plot(
        1e3 * d,
        [hertz_force(x, res0["material"], res0["mass"]) for x in d],
        "k:",
        lw=1,
        label="Hertz (for scale)",
    )
    ax1.set_xlabel("fingertip travel since first contact [mm]")
    ax1.set_ylabel("fingertip force on the sphere [N]")
    ax1.set_title("Force vs travel (pressing, 10 mm/s)")
    ax2.set_xlabel("time since first contact [s]")
    ax2.set_ylabel("fingertip force on the sphere [N]")
    ax2.set_title("Force vs time (press 1.5 s, hold to 2 s)")
    ax2.axvline(DEPTH / SPEED, color="0.6", lw=0.8)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.set_xlim(left=0.0)
        ax.set_ylim(bottom=0.0)
    ax1.legend(fontsize=7, loc="upper left")
    fig.suptitle(
        "Rubber sphere (R 64 mm, 50 g, E 79.3 kPa, nu 0.45), fingertip R 8 mm: softgrasp vs MuJoCo 4 flex"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def to_json(results: list[dict]) -> list[dict]:
    out = []
    for res in results:
        runs = _runs(res)
        out.append(
            {
                "h_m": res["h"],
                "nodes": res["nodes"],
                "tets": res["tets"],
                "hertz_15mm_N": hertz_force(DEPTH, res["material"], res["mass"]),
                "runs": [
                    {
                        "name": r.name,
                        "wall_s": r.wall_s,
                        "extra": r.extra,
                        "error": r.error,
                        "time_s": r.time_s.tolist(),
                        "travel_m": r.travel_m.tolist(),
                        "force_N": r.force_N.tolist(),
                    }
                    for r in runs
                ],
            }
        )
    return out


def _source_state() -> str:
    """The commit the run measured and whether ``src/`` had uncommitted changes (timings move with them)."""
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "src"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split("\n")
    except (OSError, subprocess.CalledProcessError):
        return "(not a git checkout)"
    n = sum(1 for line in dirty if line.strip())
    return f"at commit {head}" + (f" with {n} uncommitted file(s) under src/" if n else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--sizes", type=float, nargs="+", default=list(SIZES), help="mesh sizes [m] (default 0.014 0.008)"
    )
    ap.add_argument(
        "--fine", action="store_true", help=f"also run mesh size {FINE_SIZE} m (~7 600 nodes; slow)"
    )
    ap.add_argument(
        "--solver", choices=("static", "implicit", "both"), default="both", help="softgrasp's path(s)"
    )
    ap.add_argument(
        "--increment", type=float, default=0.5e-3, help="quasi-static travel increment [m] (default 0.5 mm)"
    )
    ap.add_argument("--dt", type=float, default=0.05, help="implicit time step [s]")
    ap.add_argument(
        "--diagnose",
        action="store_true",
        help="first size only: also softgrasp with a 10x stiffer contact law, and both sides with mu = 0",
    )
    ap.add_argument("--repeat", type=int, default=1, help="runs of each side per size; the fastest is kept")
    ap.add_argument("--out", type=Path, default=None, help="output directory (default: a new temporary one)")
    args = ap.parse_args()
    sizes = [*args.sizes, *([FINE_SIZE] if args.fine else [])]
    solvers = ("static", "implicit") if args.solver == "both" else (args.solver,)
    out = args.out if args.out is not None else Path(tempfile.mkdtemp(prefix="bench_indent_"))
    out.mkdir(parents=True, exist_ok=True)

    import mujoco
    import scipy

    print(f"softgrasp {_source_state()}")
    env = ", ".join(
        f"{k}={os.environ.get(k, '(unset)')}" for k in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    )
    print(
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"NumPy {np.__version__}, SciPy {scipy.__version__}, MuJoCo {mujoco.__version__}; {env}"
    )
    print(
        f"Scene: fingertip R {RADIUS * 1e3:g} mm, mu {MU}, table mu {TABLE_MU}; {DEPTH * 1e3:g} mm at "
        f"{SPEED * 1e3:g} mm/s from first contact, {DURATION:g} s simulated; softgrasp {', '.join(solvers)} "
        f"(increment {args.increment * 1e3:g} mm, dt {args.dt:g} s)"
    )
    results = []
    for i, h in enumerate(sizes):
        res = bench_size(h, solvers, args.increment, args.dt, args.diagnose and i == 0, args.repeat)
        results.append(res)
    report(results)
    png = out / "bench_indent.png"
    plot(results, png)
    (out / "bench_indent.json").write_text(json.dumps(to_json(results), indent=1))
    print(f"\nwrote {png} and {out / 'bench_indent.json'}")


if __name__ == "__main__":
    main()
