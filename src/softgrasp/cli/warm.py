"""Loading the compiled kernels before their first use, on a background thread.

A fresh process pays once for the compiled kernels: importing Numba and loading every kernel a
static solve calls from Numba's disk cache (about 0.5-0.8 s on the 2-core benchmark machine; a
first run on a machine compiles them instead). The command line starts :func:`warm_up_in_background`
before it meshes the object. gmsh meshes in C with the interpreter released, so the loading
overlaps the meshing instead of following it.

The warm-up solves one tiny static problem: a 30 mm box on a table under gravity, pressed by one
fingertip (sparse LU, not PARDISO, so that no solver threads start), and places the default hand
on its own fingertips. It calls the kernels through
the same code path, with the same argument types, as a plan. It is only an optimisation: a failure
is ignored, and the real call then meets the same problem and reports it.

The modules the warm-up uses are imported before its thread starts, by the calling thread: two
threads importing the same modules at once can deadlock in the interpreter's import locks when a
Ctrl-C lands inside one of the imports (the process then hangs instead of stopping).

Numba's worker threads are then started by the warm-up thread. TBB's layer resets them in a forked
child only when the fork comes from the thread that started them (from another, Numba warns that
the child's TBB may be in an invalid state); the command line forks no process after the warm-up
(its figure worker is a new program, started by exec).

The install (:func:`main`) also compiles the kernels a default plan does not load: the compiled
Runge-Kutta stepper (``plan --solver dynamic``, the experiments' dynamics), the multigrid solver
of large meshes and the nodal volume term (``--volume-term nodal``) (:func:`warm_up_solvers`,
about 40 s on a first install), so that no command compiles after installing.

A first run (or the first after an edit of a kernel's source, which keys the cache:
:mod:`softgrasp.jitcache`) compiles instead of loading: :func:`cold` tells it beforehand from the
cache's index of a few kernels the warm-up compiles first and last, so that the command line can
say why it waits (:data:`COMPILE_TIME_S`). It then compiles the fingertip contact's kernels in a
second process (a new program, :func:`start_fingertip_compile`, which first reads the default
hand into the cache folder so that this one need not import the URDF library) while this one
compiles the rest, and loads them from the cache once that process is done: about 11-15 s instead
of 22-28 s on the 2-core benchmark machine (``benchmarks/bench_cli.py``, first run).

While a plan command starts (its imports and this loading), Python's cyclic garbage collector is
paused (:func:`pause_collector`, :func:`resume_collector`): what is made then lives as long as
the process.
"""

from __future__ import annotations

import gc
import threading

import numpy as np

from softgrasp.backend import compiled

__all__ = [
    "COMPILE_TIME_S",
    "WarmUp",
    "cold",
    "main",
    "pause_collector",
    "solvers_cold",
    "resume_collector",
    "warm_up",
    "warm_up_in_background",
    "warm_up_solvers",
]

#: About how long compiling the kernels takes on a first run [s] (on the 2-core benchmark machine,
#: the fingertip contact's in a second process: 10-12 s of a 13-14 s first plan; more where the
#: machine is slower).
COMPILE_TIME_S = 15
#: About how long compiling the other solvers' kernels takes on a first install [s]
#: (:func:`warm_up_solvers`; about 38 s on the 2-core benchmark machine).
SOLVERS_COMPILE_TIME_S = 40

#: What the kernels of each package compute, as a first run names them while it compiles them.
KERNEL_GROUPS = (
    ("softgrasp.physics.fingertip", "fingertip contact"),
    ("softgrasp.physics", "body forces"),
    ("softgrasp.linalg", "sparse assembly"),
    ("softgrasp.hand", "hand kinematics"),
    ("softgrasp.sim", "time stepping"),
)


def kernel_group(module: str) -> str:
    """What a kernel of ``module`` computes (:data:`KERNEL_GROUPS`), or "" for another module's."""
    return next((name for prefix, name in KERNEL_GROUPS if module.startswith(prefix)), "")


def cold() -> bool:
    """Whether the kernels a plan loads first are not yet compiled on disk for the current
    sources (:func:`softgrasp.jitcache.cached`): the warm-up then compiles them. Imports Numba
    and the kernels' modules (about half a second)."""
    from softgrasp import jitcache
    from softgrasp.hand import descent
    from softgrasp.physics import volume

    return not all(jitcache.cached(k) for k in (volume._inverted, descent._solve))


def solvers_cold() -> bool:
    """Whether the kernels :func:`warm_up_solvers` loads are not yet compiled on disk for the
    current sources (the compiled Runge-Kutta stepper's, the multigrid smoother its problem runs
    and the nodal volume term's Jacobian and exact product)."""
    from softgrasp import jitcache
    from softgrasp.linalg import smoothers
    from softgrasp.physics import nodal_volume
    from softgrasp.sim.fused import rk4

    nodal = (nodal_volume._jacobian, nodal_volume._difference_product)
    kernels = (rk4.advance, smoothers._l1_block_inverse, *nodal)
    return not all(jitcache.cached(k) for k in kernels)


def _problem():
    """The warm-up's tiny problem: a 30 mm rubber box, its table, one fingertip pressing its top
    at load parameter ``t``; returns (body, x, table, fingers, t)."""
    from softgrasp.model.material import preset
    from softgrasp.model.mesh.generate import box
    from softgrasp.physics import forces_compiled as elastic
    from softgrasp.physics.body import build_body
    from softgrasp.physics.fingertip.contact import FingertipContact
    from softgrasp.physics.fingertip.params import ContactParams, Fingertip
    from softgrasp.physics.planes import Plane, PlaneContact

    mesh = box(0.03, 2)
    body = build_body(mesh, preset("rubber"), mass=0.02)
    x = np.asarray(mesh.points, dtype=np.float64)
    elastic.count_inverted(x, mesh.tets)
    top = float(x[:, 2].max())
    centre = np.array([*x[:, :2].mean(axis=0), top + 0.008 - 0.0002])
    tip = Fingertip(0.008, centre=centre, velocity=np.array([0.0, 0.0, -1.0]))
    fingers = FingertipContact((tip,), ContactParams(mu=0.8))
    table = PlaneContact(Plane(np.zeros(3), np.array([0.0, 0.0, 1.0])), mu=0.5)
    return body, x, table, fingers, 0.0002


def warm_up_fingertips() -> None:
    """Compile (or load) the fingertip contact's kernels alone: the calls a static solve and the
    planner make on it, on the warm-up's problem. A first run runs this in a second process
    while :func:`warm_up` compiles the other kernels (:func:`start_fingertip_compile`); that
    process first reads the default hand (yourdfpy and its mesh library import for about a
    second) into softgrasp's cache folder, under the entry's lock
    (:func:`softgrasp.usercache.making`), so that the first process, which compiles more,
    reads it from there instead."""
    if not compiled():
        return
    from softgrasp.hand.kinematics import HandModel

    HandModel.default()
    body, x, _, fingers, t = _problem()
    x = x.copy()  # writable, as a solve's positions are (another type to the kernels)
    state = fingers.init_state(body, x, t)
    fingers.static_forces(body, x, t, state)
    fingers.energy(body, x, t, state)
    fingers.jacobian(body, x, t, state)
    state = fingers.refresh(body, x, t, state)
    fingers.report(body, x, None, t, state, static=True)
    fingers.contact_frames(body, x, t, state)
    from softgrasp.grasp.force_control import _law_travels

    _law_travels(body, fingers, np.array([0.1]), t)  # the force controller's first move


def start_fingertip_compile():
    """:func:`warm_up_fingertips` in a new process (a new program: nothing forked), when this
    process may use two cores or more; the ``subprocess.Popen``, or None."""
    import os
    import subprocess
    import sys

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    if cores < 2:
        return None
    import atexit

    try:
        child = subprocess.Popen(
            [sys.executable, "-c", "from softgrasp.cli.warm import warm_up_fingertips; warm_up_fingertips()"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    except OSError:
        return None
    atexit.register(_stop, child)  # a command that ends early leaves no compiler behind
    return child


def _stop(child) -> None:
    if child.poll() is None:
        child.kill()
        child.wait()


#: Longest wait [s] for the fingertip kernels' process before compiling them here.
FINGERTIP_WAIT_S = 120.0


def warm_up(split: bool = False) -> None:
    """Load (or compile) the kernels a static solve with a table and fingertips uses, by solving
    a tiny such problem, and the hand placement's. Does nothing in a forked child whose Numba
    threads were lost. ``split`` (a first run): the fingertip contact's kernels compile in a
    second process (:func:`start_fingertip_compile`) while this one compiles the body's, the
    solver's and the hand's on the problem without its fingertip, then loads them from the
    cache for the whole problem."""
    if not compiled():
        return
    from softgrasp.linalg.solve import SolverCache
    from softgrasp.sim.scene import Scene
    from softgrasp.sim.static import solve_static

    child = start_fingertip_compile() if split else None  # first: it reads the hand first
    body, _, table, fingers, t = _problem()
    if child is not None:
        try:
            alone = Scene(body, (table,))
            solve_static(alone, alone.initial_state(), t=t, cache=SolverCache(method="direct"))
            _place_hand()
        finally:
            try:
                child.wait(timeout=FINGERTIP_WAIT_S)
            except Exception:  # noqa: BLE001 - a child that does not finish: compile here
                child.kill()
    scene = Scene(body, (table, fingers))
    rest, _ = solve_static(scene, scene.initial_state(), t=t, cache=SolverCache(method="direct"))
    fingers.report(body, rest.x, None, t, rest.contacts[1], static=True)
    fingers.contact_frames(body, rest.x, t, rest.contacts[1])
    if child is None:
        _place_hand()
    global _loaded
    _loaded = True


#: Whether :func:`warm_up` has run to its end in this process (or in the warm server this
#: process was forked from: :mod:`softgrasp.cli.zygote`); a :class:`WarmUp` then does nothing.
_loaded = False


def warm_up_solvers() -> None:
    """Load (or compile) the kernels a default plan does not use, on the warm-up's problem: a few
    steps of the compiled explicit Runge-Kutta stepper (:func:`softgrasp.sim.explicit.simulate`),
    a static solve by multigrid (:class:`~softgrasp.linalg.solve.SolverCache` ``amg``) and one
    of the body with the nodal volume term (:mod:`softgrasp.physics.nodal_volume`)."""
    if not compiled():
        return
    from dataclasses import replace

    from softgrasp.linalg.solve import SolverCache
    from softgrasp.physics.nodal_volume import NodalVolume
    from softgrasp.sim.explicit import simulate
    from softgrasp.sim.scene import Scene
    from softgrasp.sim.static import solve_static

    body, _, table, fingers, t = _problem()
    scene = Scene(body, (table, fingers))
    simulate(scene, scene.initial_state(), 2e-5)
    solve_static(scene, scene.initial_state(), t=t, cache=SolverCache(method="amg"))
    nodal = Scene(replace(body, volume="nodal"), (table, fingers))
    solve_static(nodal, nodal.initial_state(), t=t, cache=SolverCache())
    # the exact product of large nodal bodies (Body.newton_correction), which this one is not
    x = np.array(body.mesh.points)
    term = NodalVolume(body.mesh.tets, body.mesh.volumes, body.n_nodes, body.kappa, body.barrier)
    term.add_difference(x, np.zeros_like(x), np.zeros_like(x))


def _place_hand() -> None:
    """The hand's placement (its compiled WDLS): the default hand reaching its own fingertips."""
    from softgrasp.hand.kinematics import HandModel
    from softgrasp.hand.placement import place_hand

    hand = HandModel.default()
    mid = {f: hand.forward(f, 0.5 * np.add(*hand.limits(f))) for f in hand.grasp_fingers}
    place_hand(hand, mid)


def _quietly(split: bool = False) -> None:
    try:
        warm_up(split)
    except Exception:  # noqa: BLE001 - an optimisation only: the real call reports the problem
        pass


class WarmUp(threading.Thread):
    """:func:`warm_up` on a daemon thread, having first found whether the cache is :func:`cold`.

    Attributes
    ----------
    checked: set once :attr:`cold` is known.  cold: whether the warm-up compiles the kernels.
    compiling: what the kernel being compiled computes (:func:`kernel_group`), "" before any.
    """

    def __init__(self) -> None:
        super().__init__(name="softgrasp-warm-up", daemon=True)
        self.checked = threading.Event()
        self.cold = False
        self.compiling = ""

    def run(self) -> None:
        if _loaded:
            self.checked.set()
            return
        try:
            self.cold = cold()
        except Exception:  # noqa: BLE001 - only what the command line says while it waits
            self.cold = False
        finally:
            self.checked.set()
        if not self.cold:
            _quietly()
            return
        resume_collector()  # compiling makes garbage
        from numba.core import event

        warm = self

        class _Compiling(event.Listener):  # Numba's compile events: which kernel compiles now
            def on_start(self, ev: event.Event) -> None:
                group = kernel_group(getattr(ev.data["dispatcher"].py_func, "__module__", ""))
                if group:
                    warm.compiling = group

            def on_end(self, ev: event.Event) -> None:
                pass

        with event.install_listener("numba:compile", _Compiling()):
            _quietly(split=True)


#: Whether :func:`pause_collector` paused the garbage collector and it is not resumed yet.
_collector_paused = False
_COLLECTOR_LOCK = threading.Lock()


def pause_collector() -> None:
    """Pause Python's cyclic garbage collector while a command starts. The modules it imports and
    the kernels it loads live as long as the process: the collector's passes over them as they
    are made (about 300 before a default plan's set-points) find nothing to free and cost about
    0.07 s. Nothing if the collector is off already."""
    global _collector_paused
    with _COLLECTOR_LOCK:
        if gc.isenabled():
            gc.disable()
            _collector_paused = True


def resume_collector() -> None:
    """End :func:`pause_collector`'s pause, once the kernels are loaded: what exists then is
    moved to the permanent generation (no later pass visits it) and the collector runs again.
    A first run resumes it as soon as it knows that it compiles (compiling leaves garbage)."""
    global _collector_paused
    with _COLLECTOR_LOCK:
        if _collector_paused:
            gc.freeze()
            gc.enable()
            _collector_paused = False


def _import_modules() -> None:
    """Import what :func:`cold` and :func:`warm_up` use (module docstring: no concurrent imports)."""
    import importlib

    for name in (
        "softgrasp.jitcache",
        "softgrasp.hand.descent",
        "softgrasp.physics.volume",
        "softgrasp.linalg.solve",
        "softgrasp.model.material",
        "softgrasp.model.mesh.generate",
        "softgrasp.physics.forces_compiled",
        "softgrasp.physics.body",
        "softgrasp.physics.fingertip.contact",
        "softgrasp.physics.fingertip.params",
        "softgrasp.physics.planes",
        "softgrasp.sim.scene",
        "softgrasp.sim.static",
        "softgrasp.hand.kinematics",
        "softgrasp.hand.placement",
    ):
        importlib.import_module(name)


def warm_up_in_background() -> WarmUp:
    """Import the warm-up's modules here, then start :func:`warm_up` on a daemon thread and return
    it (joining it is optional)."""
    if compiled():
        _import_modules()
    thread = WarmUp()
    thread.start()
    return thread


def main() -> int:
    """Compile the kernels a plan uses now, once, instead of on the first plan, then the other
    solvers' (:func:`warm_up_solvers`): what the Makefile's install runs (``python -m
    softgrasp.cli.warm``). Says so when it compiles; a failure is reported in one line and does
    not fail the install (the first plan then compiles and meets the same problem)."""
    import sys

    if not compiled():
        return 0
    try:
        first = cold()
        if first:
            print(
                f"softgrasp: compiling kernels (first run only, ~{COMPILE_TIME_S} s)",
                file=sys.stderr,
                flush=True,
            )
        warm_up(split=first)
        if solvers_cold():
            print(
                "softgrasp: compiling the dynamic and multigrid solvers' and the nodal volume term's "
                f"kernels (once, ~{SOLVERS_COMPILE_TIME_S} s)",
                file=sys.stderr,
                flush=True,
            )
        warm_up_solvers()
    except Exception as exc:  # noqa: BLE001 - an optimisation only
        print(
            f"softgrasp: the kernels were not compiled ahead ({exc}); the first plan compiles them",
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
