"""Benchmark of explicit dynamics with fingertip contact: steps/s, NumPy oracle vs compiled, per step, fused.

The scene: the default rubber sphere (radius 64 mm, 50 g, E = 79.3 kPa, nu = 0.45) meshed at 8 mm
(~2 200 nodes) resting on the table (friction 0.5), one rigid fingertip (R = 8 mm) pressed 2 mm
into its top and moving down at 5 mm/s, so that the fingertip-facet contact is active throughout.
In the same run it prints:

* ``simulate(..., method=m)`` at the stable time step, steps/s (best and median of a few repeats),
  node-steps/s, force evaluations/s and the ratios to the NumPy oracle and to the per-step compiled
  path, for semi-implicit Euler and RK4 on the NumPy oracles of the tests (``tests/oracles``: the
  body and fingertips of :func:`oracles.contact.oracle_scene`, the planes of :mod:`oracles.planes`)
  and on the compiled kernels step by step (``fused=False``), and for RK4 fused
  (:mod:`softgrasp.sim.fused.step`: many steps per compiled call) on one and on two threads. The
  blow-up monitor's work is included, as in every real run;
* where a step goes: the parts of the per-step path (each measured alone, compiled and on the
  NumPy oracles), and the compiled parts of a fused RK4 step (body forces on one and two of
  Numba's threads, with and without the energy and volumes of the monitor's check, the planes, the
  fingertip step: one detection, update and forces);
* an arithmetic bound: floating-point operations per force evaluation counted from the edges and
  tets, against two measured machine rates (a single-thread BLAS ``dgemm``, the best case for
  SIMD arithmetic, and a compiled scalar loop), and the steps/s each rate would allow;
* ``--profile``: the top entries of a cProfile of per-step semi-implicit steps, compiled and on the
  NumPy oracles;
* ``--kernels``: ``Body.internal_forces`` / ``internal_jacobian`` at ~500, ~2 200, ~7 500 and
  ~33 000 nodes, compiled and on the NumPy oracle (:class:`oracles.forces.OracleBody`);
* ``--compile``: cold (empty cache) and warm (cached) time to import softgrasp and evaluate the
  body's forces, energy and Jacobian once, and to compile the fused stepper, each in a fresh
  interpreter.

The load of the machine (``/proc/loadavg``: runnable tasks besides this one) is printed with each
timing: two threads only pay on two idle cores, and a timing taken while another job runs is slower.

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_dynamic.py [--profile] [--kernels]
[--compile]``. Timings are wall-clock; on a shared machine repeat them.
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import io
import os
import platform
import pstats
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from softgrasp.experiments.indentation import surface_height
from softgrasp.linalg import pardiso
from softgrasp.model.mesh import box
from softgrasp.model.objects import make_object
from softgrasp.physics.body import Body, build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.params import Fingertip
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim.explicit import make_integrator, simulate
from softgrasp.sim.fused.run import FusedRun
from softgrasp.sim.scene import Scene, State
from softgrasp.sim.stability import BlowupMonitor, stable_time_step

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from oracles import planes as oracle_planes  # noqa: E402 - the tests' directory first
from oracles.contact import oracle_scene  # noqa: E402
from oracles.forces import OracleBody  # noqa: E402

RADIUS = 0.008  #: fingertip radius [m]
DEPTH = 0.002  #: initial penetration of the fingertip [m]
SPEED = 0.005  #: fingertip speed, downwards [m/s] (the paper's closing speed)
#: Floating-point operations per element of one force evaluation, counted on the compiled kernels
#: (softgrasp.physics.forces_compiled; a square root or division counts as one): per edge, the spring
#: (difference 3, length 6, 1/L 1, strain 2, cubic law 6, tension 2, scaling 1, scatter 9) and
#: its dashpot (relative velocity 3, rate 6, force 2); per tet, the volume term (edge vectors 9,
#: three cross products 27, volume 6, J and psi' 4, coefficient 3, scatter 30).
FLOPS_PER_EDGE = 30 + 11
FLOPS_PER_TET = 79
METHODS = ("semi-implicit", "rk4")
EVALS_PER_STEP = {"semi-implicit": 1, "rk4": 4}
#: The laws a case runs on: the compiled kernels, or the NumPy oracles of the tests.
COMPILED, ORACLE = "compiled", "NumPy oracle"
#: The simulate() cases: (label, method, laws, fused, threads).
CASES = (
    (ORACLE, "semi-implicit", ORACLE, False, 1),
    ("compiled per step", "semi-implicit", COMPILED, False, 1),
    (ORACLE, "rk4", ORACLE, False, 1),
    ("compiled per step", "rk4", COMPILED, False, 1),
    ("compiled fused, 1 thread", "rk4", COMPILED, True, 1),
    ("compiled fused, 2 threads", "rk4", COMPILED, True, 2),
)
#: Mesh sizes [m] of the sphere and the BCC box division of the --kernels table.
KERNEL_SIZES = (("sphere", 0.014), ("sphere", 0.008), ("sphere", 0.005), ("box", 24))


# ----------------------------------------------------------------------------- the scene
def build_scene(mesh_size: float) -> tuple[Scene, State]:
    """Rubber sphere on the table with one fingertip pressed ``DEPTH`` into its top."""
    mesh, mat, mass = make_object("sphere", mesh_size)
    body = build_body(mesh, mat, mass=mass)
    x = np.asarray(mesh.points)
    # Press at the centroid of the facet under the top, DEPTH below that facet's plane.
    _, f = surface_height(x, mesh.facets, mesh.centroid[:2])
    xy = x[mesh.facets[f]].mean(axis=0)[:2]
    zs, _ = surface_height(x, mesh.facets, xy)
    tip = Fingertip(RADIUS, centre=[xy[0], xy[1], zs + RADIUS - DEPTH], velocity=[0.0, 0.0, -SPEED])
    table = PlaneContact(Plane([0, 0, 0], [0, 0, 1]), mu=0.5, name="table")
    scene = Scene(body, (table, FingertipContact((tip,))))
    return scene, scene.initial_state()


def finger_pairs(scene: Scene, state: State) -> int:
    """Touching (fingertip, facet) pairs in ``state``."""
    _, fingers = scene.interaction("fingers")
    return len(fingers.pairs(scene.body, state.x, state.t))


def on_laws(scene: Scene) -> tuple[tuple[str, Scene], ...]:
    """The compiled ``scene`` and its NumPy oracle twin: the body and fingertips of
    :func:`oracles.contact.oracle_scene`, the planes :class:`OraclePlaneContact`."""
    oracle = oracle_scene(scene)
    inters = tuple(
        oracle_planes.OraclePlaneContact(**{f.name: getattr(i, f.name) for f in dataclasses.fields(i)})
        if type(i) is PlaneContact
        else i
        for i in oracle.interactions
    )
    return (COMPILED, scene), (ORACLE, dataclasses.replace(oracle, interactions=inters))


# ----------------------------------------------------------------------------- timing helpers
def others_running(settle: float = 0.0) -> int:
    """Runnable tasks on the machine besides the calling thread (``/proc/loadavg``), -1 if unknown;
    after ``settle`` seconds of sleep (our own worker thread spins a while after a parallel run and
    counts as runnable meanwhile)."""
    time.sleep(settle)
    try:
        with open("/proc/loadavg", encoding="ascii") as fh:
            return int(fh.read().split()[3].split("/")[0]) - 1
    except (OSError, ValueError, IndexError):
        return -1


def repeat(fn: Callable[[], object], n: int) -> list[float]:
    """Wall times [s] of n calls of fn (after one warm-up call)."""
    fn()
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def per_call(fn: Callable[[], object], min_time: float = 0.3) -> float:
    """Best of five means [s] of fn() over runs of about min_time / 5 each."""
    fn()
    best = float("inf")
    for _ in range(5):
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < min_time / 5 or n == 0:
            fn()
            n += 1
        best = min(best, (time.perf_counter() - t0) / n)
    return best


def flops_per_eval(body: Body) -> float:
    """Counted floating-point operations of one internal force evaluation."""
    return FLOPS_PER_EDGE * len(body.edges) + FLOPS_PER_TET * body.mesh.n_tets


def machine_rates() -> tuple[float, float]:
    """(dgemm, compiled scalar loop) rates [flop/s] on one core."""
    a = np.random.default_rng(0).random((600, 600))
    t = min(repeat(lambda: a @ a, 5))
    gemm = 2 * 600**3 / t
    import numba

    @numba.njit(cache=True)
    def chains(n):  # six independent multiply-add chains (no SIMD: a latency/port bound)
        a, b, c, d, e, f = 1.0, 0.9, 0.8, 0.7, 0.6, 0.5
        for _ in range(n):
            a = a * 0.9999999 + 1e-7
            b = b * 0.9999999 + 1e-7
            c = c * 0.9999999 + 1e-7
            d = d * 0.9999999 + 1e-7
            e = e * 0.9999999 + 1e-7
            f = f * 0.9999999 + 1e-7
        return a + b + c + d + e + f

    n = 5_000_000
    t = min(repeat(lambda: chains(n), 3))
    return gemm, 12 * n / t


# ----------------------------------------------------------------------------- the sections
def bench_simulate(
    scene: Scene, s0: State, steps: int, fused_steps: int, repeats: int
) -> dict[tuple[str, str], tuple[list[float], int]]:
    """steps/s of simulate() per case of :data:`CASES` (one list entry per repeat) and the most
    other runnable tasks seen while it ran."""
    out: dict[tuple[str, str], tuple[list[float], int]] = {}
    scenes = dict(on_laws(scene))
    for label, method, laws, fused, threads in CASES:
        if threads > (os.cpu_count() or 1):
            continue
        if threads > 1 and others_running(settle=0.5) > 0:
            print(f"  {label} ({method}) skipped: another process is running (two threads would wait for it)")
            continue
        dt = stable_time_step(scene, method)
        n = fused_steps if fused else steps
        pardiso.set_threads(threads)
        sc = scenes[laws]
        try:
            kw = {"method": method, "dt": dt, "fused": fused}
            final = simulate(sc, s0, 5 * dt, **kw)  # warm-up (and compile)
            assert finger_pairs(scene, final) > 0
            busy = others_running()
            times = repeat(lambda kw=kw, n=n, dt=dt, sc=sc: simulate(sc, s0, n * dt, **kw), repeats)
            busy = max(busy, others_running())
        finally:
            pardiso.set_threads(None)
        out[(label, method)] = ([n / t for t in times], busy)
    return out


def step_breakdown(scene: Scene, s0: State) -> dict[str, dict[str, float]]:
    """Wall time [s] of the parts of one semi-implicit step of simulate(), each measured alone,
    compiled and on the NumPy oracles."""
    x, v, t, c = s0.x, 1e-3 * np.random.default_rng(1).standard_normal(s0.x.shape), s0.t, s0.contacts
    state = s0.replace(v=v)
    integ = make_integrator("semi-implicit")
    dt = stable_time_step(scene, "semi-implicit")
    res: dict[str, dict[str, float]] = {}

    def parts(sc: Scene) -> dict[str, float]:
        body = sc.body
        table_i, table = sc.interaction("table")
        finger_i, finger = sc.interaction("fingers")
        monitor = BlowupMonitor(sc, state, "semi-implicit")
        return {
            "Body.internal_forces": per_call(lambda: body.internal_forces(x, v)),
            "table.forces": per_call(lambda: table.forces(body, x, v, t, c[table_i])),
            "fingers.forces": per_call(lambda: finger.forces(body, x, v, t, c[finger_i])),
            "  of which detect": per_call(lambda: finger.pairs(body, x, t)),
            "Scene.forces": per_call(lambda: sc.forces(x, v, t, c)),
            "table.update": per_call(lambda: table.update(body, x, v, t, c[table_i])),
            "fingers.update": per_call(lambda: finger.update(body, x, v, t, c[finger_i])),
            "SemiImplicitEuler.step": per_call(lambda: integ.step(sc, state, dt)),
            "monitor (power: contact forces again)": per_call(lambda: monitor._power(state)),
        }

    for laws, sc in on_laws(scene):
        res[laws] = parts(sc)
    return res


def fused_breakdown(scene: Scene, s0: State) -> dict[str, float]:
    """Wall time [s] of a fused RK4 step and of its compiled parts, each measured alone."""
    import numba

    from softgrasp.sim.fused import body as fb
    from softgrasp.sim.fused import contacts as fc

    dt = stable_time_step(scene, "rk4")
    state = simulate(scene, s0, 20 * dt, method="rk4", dt=dt)
    two = (os.cpu_count() or 1) >= 2 and others_running(settle=0.5) == 0
    res: dict[str, float] = {}
    for threads in (1, 2) if two else (1,):
        run = FusedRun(scene, state, BlowupMonitor(scene, state, "rk4"))
        run.stepper.threads = threads
        res[f"fused RK4 step, {threads} thread(s) (50 steps / 50)"] = (
            per_call(lambda st=run.stepper: st.advance(50, dt)) / 50
        )
        assert run.stepper.failure is None
    # the parts, on a stepper of their own (they overwrite its buffers)
    st = FusedRun(scene, state, None).stepper
    st.advance(2, dt)
    x, v, t = st.x, st.v, st.t
    fint, info, fplane, ffinger, centres, x_ref, track, p0, near = st._work
    for label, check in (("body forces, 1 thread", False), ("  with the check's energy and volumes", True)):
        res[label] = per_call(lambda c=check: fb.body_forces(False, x, v, st._body, c, c, fint, info))
    res["planes: update and forces"] = per_call(
        lambda: fc.plane_step(x, v, t, st._pl, p0, st.pl_active.copy(), st.pl_anchor.copy(), True, fplane)
    )
    res["fingertip step (one detection, state update, forces)"] = per_call(
        lambda: fc.finger_step(x, v, t, st._fg, st._fstate, 0, x_ref, track, near, centres, ffinger, True)
    )
    if two:
        numba.set_num_threads(2)
        try:
            res["body forces, 2 of Numba's threads"] = per_call(
                lambda: fb.body_forces(True, x, v, st._body, False, False, fint, info)
            )
        finally:
            numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return res


def body_only_steps(body: Body, dt: float, steps: int = 300) -> float:
    """Semi-implicit steps/s of the body alone (internal forces + gravity, no contact, no monitor,
    a minimal Python loop): the ceiling of today's per-step design."""
    x = np.array(body.mesh.points, dtype=np.float64)
    v = np.zeros_like(x)
    g = body.mass[:, None] * body.gravity[None, :]
    inv_m = 1.0 / body.mass[:, None]

    def run() -> None:
        nonlocal x, v
        for _ in range(steps):
            v = v + dt * (body.internal_forces(x, v) + g) * inv_m
            x = x + dt * v

    return steps / min(repeat(run, 3))


def profile(scene: Scene, s0: State, steps: int, top: int = 14) -> dict[str, str]:
    """cProfile of ``steps`` per-step semi-implicit steps, compiled and on the NumPy oracles: the
    top entries by own time."""
    dt = stable_time_step(scene, "semi-implicit")
    out = {}
    for laws, sc in on_laws(scene):
        simulate(sc, s0, 5 * dt, method="semi-implicit", dt=dt, fused=False)
        pr = cProfile.Profile()
        pr.enable()
        simulate(sc, s0, steps * dt, method="semi-implicit", dt=dt, fused=False)
        pr.disable()
        buf = io.StringIO()
        st = pstats.Stats(pr, stream=buf)
        st.strip_dirs().sort_stats("tottime").print_stats(top)
        out[laws] = buf.getvalue()
    return out


def bench_kernels() -> None:
    """Body.internal_forces / internal_jacobian at four sizes, on the NumPy oracle
    (:class:`oracles.forces.OracleBody`) and compiled."""
    print(
        f"\n{'mesh':>14} {'nodes':>6} {'edges':>7} {'tets':>7} | {'forces oracle':>13} {'compiled':>9} "
        f"{'x':>5} | {'jacobian oracle':>15} {'compiled':>9} {'x':>5}"
    )
    for kind, size in KERNEL_SIZES:
        if kind == "sphere":
            mesh, mat, mass = make_object("sphere", size)
            label = f"sphere {size * 1e3:g} mm"
        else:
            mesh, mat, mass = box(0.05, size), make_object("sphere", 0.014)[1], None
            label = f"box n={size}"
        body = build_body(mesh, mat, mass=mass)
        rng = np.random.default_rng(0)
        x = np.asarray(mesh.points) + 1e-4 * rng.standard_normal(mesh.points.shape)
        v = 1e-2 * rng.standard_normal(x.shape)
        t = {}
        for laws, b in ((COMPILED, body), (ORACLE, OracleBody.of(body))):
            t[laws, "f"] = per_call(lambda b=b, x=x, v=v: b.internal_forces(x, v), 1.0)
            t[laws, "j"] = per_call(lambda b=b, x=x: b.internal_jacobian(x), 2.0)
        fn, fb = t[ORACLE, "f"], t[COMPILED, "f"]
        jn, jb = t[ORACLE, "j"], t[COMPILED, "j"]
        print(
            f"{label:>14} {mesh.n_nodes:>6} {len(mesh.edges):>7} {mesh.n_tets:>7} | {fn * 1e3:>10.3f} ms "
            f"{fb * 1e3:>6.3f} ms {fn / fb:>5.1f} | {jn * 1e3:>12.2f} ms {jb * 1e3:>6.2f} ms {jn / jb:>5.1f}"
        )


_COMPILE_SNIPPET = """
import time
t0 = time.perf_counter()
import numpy as np
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.params import Fingertip
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.model.material import Material
from softgrasp.model.mesh import box
t1 = time.perf_counter()
body = build_body(box(0.02, 2), Material(1e5, 0.45, 50.0))
x = np.asarray(body.mesh.points)
fc = FingertipContact((Fingertip(0.008, centre=[0.01, 0.01, 0.027]),))
t2 = time.perf_counter()
body.internal_forces(x, x)
body.internal_energy(x)
body.internal_jacobian(x)
t3 = time.perf_counter()
state = fc.init_state(body, x)
fc.forces(body, x, x, 0.0, state)
t4 = time.perf_counter()
from softgrasp.physics.planes import Plane, PlaneContact
from softgrasp.sim import Scene, simulate
scene = Scene(body, (PlaneContact(Plane([0, 0, 0], [0, 0, 1]), name="table"), fc))
simulate(scene, scene.initial_state(), 1e-6, method="rk4", dt=1e-7, fused=True)
t5 = time.perf_counter()
print(f"{t1 - t0:.3f} {t3 - t2:.3f} {t4 - t3:.3f} {t5 - t4:.3f}")
"""


def bench_compile() -> None:
    """Cold and warm import + first-call times in fresh interpreters."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        print(
            "\nfresh interpreter [s]: import (softgrasp, numba, kernel modules); first body forces, energy, "
            "Jacobian; first fingertip update and forces; first fused simulate"
        )
        for label in ("cold (empty cache)", "warm (cached)", "warm (cached)"):
            t0 = time.perf_counter()
            r = subprocess.run(
                [sys.executable, "-c", _COMPILE_SNIPPET], env=env, capture_output=True, text=True
            )
            wall = time.perf_counter() - t0
            if r.returncode:
                print(r.stderr)
                continue
            imp, body, finger, fused = r.stdout.split()
            print(
                f"  {label:>18}: import {imp}, body {body}, fingertip {finger}, fused {fused}; "
                f"interpreter wall {wall:.2f}"
            )


# ----------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh-size", type=float, default=0.008, help="sphere mesh size [m] (default 0.008)")
    ap.add_argument("--steps", type=int, default=300, help="steps per step-by-step run (default 300)")
    ap.add_argument("--fused-steps", type=int, default=3000, help="steps per fused run (default 3000)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per case (default 3)")
    ap.add_argument(
        "--profile", action="store_true", help="cProfile semi-implicit steps, compiled and NumPy oracle"
    )
    ap.add_argument("--kernels", action="store_true", help="internal forces/Jacobian at four sizes")
    ap.add_argument("--compile", action="store_true", help="cold and warm compile times")
    args = ap.parse_args()
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, NumPy {np.__version__}, "
        f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}; "
        f"the compiled kernels against the NumPy oracles of tests/oracles"
    )
    if args.compile:
        bench_compile()
    scene, s0 = build_scene(args.mesh_size)
    body = scene.body
    n = body.n_nodes
    print(
        f"\nsphere {args.mesh_size * 1e3:g} mm: {n} nodes, {len(body.edges)} edges, {body.mesh.n_tets} tets, "
        f"{len(body.mesh.facets)} facets; fingertip R = {RADIUS * 1e3:g} mm, {finger_pairs(scene, s0)} "
        f"touching facet(s) at t = 0"
    )
    rates = bench_simulate(scene, s0, args.steps, args.fused_steps, args.repeats)
    print(
        f"\nsimulate(), {args.steps} steps per step-by-step run, {args.fused_steps} per fused run, "
        f"x {args.repeats} (best / median); 'busy': most other runnable tasks seen"
    )
    print(
        f"{'method':>14} {'dt [s]':>9} {'path':>23} {'steps/s':>15} {'node-steps/s':>13} "
        f"{'evals/s':>8} {'x oracle':>8} {'x per step':>10} {'busy':>5}"
    )
    for method in METHODS:
        dt = stable_time_step(scene, method)
        base = max(rates[(ORACLE, method)][0])
        per_step = max(rates[("compiled per step", method)][0])
        for (label, m), (r, busy) in rates.items():
            if m != method:
                continue
            best, med = max(r), statistics.median(r)
            print(
                f"{method:>14} {dt:>9.2e} {label:>23} {best:>7.0f} / {med:>5.0f} {best * n:>13.3g} "
                f"{best * EVALS_PER_STEP[method]:>8.0f} {best / base:>8.1f} {best / per_step:>10.1f} "
                f"{busy:>5}"
            )

    print("\none semi-implicit step, per-step path, its parts measured alone [us]:")
    parts = step_breakdown(scene, s0)
    names = list(next(iter(parts.values())))
    print(f"{'':>38} " + " ".join(f"{b:>8}" for b in parts))
    for name in names:
        print(f"{name:>38} " + " ".join(f"{parts[b][name] * 1e6:>8.1f}" for b in parts))
    fused = fused_breakdown(scene, s0)
    if fused:
        print(f"\none fused RK4 step, its compiled parts measured alone [us] (busy {others_running()}):")
        for name, sec in fused.items():
            print(f"{name:>46} {sec * 1e6:>8.1f}")

    flops = flops_per_eval(body)
    gemm, scalar = machine_rates()
    t_body = parts[COMPILED]["Body.internal_forces"]
    print(
        f"\narithmetic bound: {flops / 1e6:.2f} Mflop per force evaluation ({FLOPS_PER_EDGE} per edge, "
        f"{FLOPS_PER_TET} per tet)"
    )
    print(
        f"  measured rates: dgemm {gemm / 1e9:.1f} Gflop/s, compiled scalar loop {scalar / 1e9:.1f} Gflop/s"
    )
    print(f"  compiled internal forces run at {flops / t_body / 1e9:.2f} Gflop/s ({t_body * 1e6:.0f} us)")
    for name in ("body forces, 1 thread", "body forces, 2 of Numba's threads"):
        if name in fused:
            print(f"  fused {name}: {flops / fused[name] / 1e9:.2f} Gflop/s ({fused[name] * 1e6:.0f} us)")
    for method in METHODS:
        k = EVALS_PER_STEP[method]
        print(
            f"  {method:>14}: {k} evaluation(s)/step -> at most {gemm / (k * flops):>7.0f} steps/s at the "
            f"dgemm rate, {scalar / (k * flops):>6.0f} at the scalar rate; 20 000 steps/s needs "
            f"{20000 * k * flops / 1e9:.1f} Gflop/s"
        )
    dt = stable_time_step(scene, "semi-implicit")
    for laws, b in ((COMPILED, body), (ORACLE, OracleBody.of(body))):
        print(
            f"  body alone, semi-implicit, minimal Python loop ({laws}): {body_only_steps(b, dt):.0f} steps/s"
        )

    if args.profile:
        for laws, text in profile(scene, s0, args.steps).items():
            print(f"\ncProfile, {args.steps} semi-implicit steps, {laws}:")
            print("\n".join(line for line in text.splitlines() if line.strip())[:4000])
    if args.kernels:
        bench_kernels()


if __name__ == "__main__":
    main()
