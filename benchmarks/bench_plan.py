"""Benchmark of the grasp planner: wall time and peak memory of the default plan (rubber sphere,
three fingers, 0.5 mm increments, the hand's placement, the quasi-static release and 1 s implicit
hold) from about 500 to about 32 000 nodes, and the growth exponent of its cost.

Every plan runs in a fresh process (so that its peak resident memory is its own: meshing and body
included): ``plan s`` is that first plan's time, and so includes the process's one-time costs
(importing Numba and loading the compiled kernels from its disk cache, about 0.5-0.8 s here); below
10 000 nodes the same process then plans three more times (``warm s``, the best of them: what
every later plan of a session or a sweep worker costs). Each row also gives the plan's Newton
systems and, beyond PARDISO's size, its multigrid V-cycles (``GraspPlan.solver_stats``): counts
that do not drift with the machine's throughput. Peers measured in the same run: the
reference linear solver (SciPy's sparse LU of the symmetrised Newton matrix up to 1 500 unknowns,
multigrid-preconditioned CG beyond; ``--reference``), and the
dynamic solver (the paper's explicit RK4 through every increment at 50 mm/s, then a static rest;
``--dynamic``, the ~500-node mesh only: its cost grows as N^(4/3) per simulated second), and the
nodal volume term (``--nodal``, below 10 000 nodes: the body without volumetric locking, whose
Newton matrices have about four times the blocks).

``--cli N`` times the whole default ``softgrasp plan`` command instead, its figures drawn by a
child process and, as the peer, in its own process (``FigureWorker("inline")``).

Run: ``make bench`` or ``.venv/bin/python benchmarks/bench_plan.py [--quick] [--large]
[--reference] [--dynamic] [--nodal] [--cli N]``.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import platform
import resource
import time

import numpy as np

#: Sphere mesh sizes [m] and the node counts they give: 549, 2 196, 7 576; with --large 27 749
#: and 32 543 (the target's ~32 000).
SIZES = (0.014, 0.008, 0.005)
LARGE = (0.0031, 0.00295)
#: Warm plans after the first (``warm s`` is the best of them: the benchmark machine's throughput
#: drifts by up to +-20 % from minute to minute, and the best is the least disturbed figure).
WARM_REPEATS = 3


def _run(h: float, solver: str, linsolve: str, volume: str, out) -> None:  # pragma: no cover - child
    from softgrasp.grasp.planner import PlanConfig, plan_grasp
    from softgrasp.linalg.solve import SolverCache
    from softgrasp.model.objects import make_object
    from softgrasp.physics.body import build_body

    t0 = time.perf_counter()
    mesh, mat, mass = make_object("sphere", h)
    body = build_body(mesh, mat, mass=mass, volume=volume)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    try:
        plan = plan_grasp(body, PlanConfig(solver=solver), cache=SolverCache(method=linsolve))
        result = {
            "forces": [f.force_norm for f in plan.fingers],
            "increments": plan.increments,
            "margin": plan.friction_margin,
            "systems": plan.solver_stats.get("systems", 0),
            "cycles": plan.solver_stats.get("multigrid_cycles", 0),
            "phases": tuple(
                plan.solver_stats.get(k, 0)
                for k in ("settle_systems", "closing_systems", "hold_check_systems", "margin_systems")
            ),
        }
    except Exception as exc:  # noqa: BLE001 - reported, not hidden
        result = {"error": f"{type(exc).__name__}: {exc}"}
    result.update(
        nodes=body.n_nodes,
        build_s=t_build,
        plan_s=time.perf_counter() - t0,
        peak_MB=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    )
    if "error" not in result and body.n_nodes < 10_000:
        warm = []
        for _ in range(WARM_REPEATS):
            t0 = time.perf_counter()
            plan_grasp(body, PlanConfig(solver=solver), cache=SolverCache(method=linsolve))
            warm.append(time.perf_counter() - t0)
        result["warm_s"] = min(warm)
    out.send(result)


def measure(h: float, solver: str = "quasistatic", linsolve: str = "auto", volume: str = "element") -> dict:
    """One plan in a fresh process: nodes, build and plan seconds, peak MB, forces."""
    ctx = mp.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_run, args=(h, solver, linsolve, volume, send))
    p.start()
    result = recv.recv()
    p.join()
    return result


def _row(r: dict, label: str, ref: float | None) -> str:
    ratio = f"{r['plan_s'] / ref:>6.2f}" if ref else f"{'1':>6}"
    warm = f"{r['warm_s']:>7.2f}" if "warm_s" in r else f"{'-':>7}"
    if "error" in r:
        head = f"{r['nodes']:>6} {label:>22} {r['plan_s']:>8.2f} {warm} {ratio} {r['peak_MB']:>8.0f}"
        return f"{head}  {r['error']}"
    f = " / ".join(f"{v:.3f}" for v in r["forces"])
    return (
        f"{r['nodes']:>6} {label:>22} {r['plan_s']:>8.2f} {warm} {ratio} {r['peak_MB']:>8.0f} "
        f"{r['increments']:>5} {r['margin']:>7.1%}  {f}   (mesh+body {r['build_s']:.1f} s; "
        f"{r['systems']} Newton systems: settle {r['phases'][0]}, closing {r['phases'][1]}, hold checks "
        f"{r['phases'][2]}; the critical scale's checks {r['phases'][3]} more"
        + (f"; {r['cycles']} V-cycles)" if r["cycles"] else ")")
    )


def cli(repeats: int) -> None:
    """Wall time of the whole default ``softgrasp plan`` command (imports, meshing, plan, files and
    its three figures), with the figures drawn by a child process (the default) and, as the peer in
    the same run, in the command's own process."""
    import shutil
    import statistics
    import subprocess
    import sys
    import tempfile

    times: dict[str, list[float]] = {"child": [], "inline": []}
    out = tempfile.mkdtemp(prefix="bench_plan_cli_")
    for _ in range(repeats):
        for mode in times:
            # The command itself, its figure worker in the mode measured.
            script = (
                "import functools, softgrasp.viz.worker as w; "
                f"w.FigureWorker.__init__ = functools.partialmethod(w.FigureWorker.__init__, {mode!r}); "
                "from softgrasp.cli import main; main()"
            )
            t0 = time.perf_counter()
            command = [sys.executable, "-c", script, "plan", "--out", out]
            subprocess.run(command, check=True, capture_output=True)
            times[mode].append(time.perf_counter() - t0)
    shutil.rmtree(out, ignore_errors=True)
    med = {m: statistics.median(v) for m, v in times.items()}
    print(f"softgrasp plan (default object), {repeats} runs each, alternating:")
    for m, v in times.items():
        print(f"  figures {m:>6}: median {med[m]:.2f} s, best {min(v):.2f} s")
    print(f"  child / inline: {med['child'] / med['inline']:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only the ~500 and ~2 000-node meshes")
    ap.add_argument("--large", action="store_true", help="also the 27 749 and 32 543-node meshes")
    ap.add_argument("--reference", action="store_true", help="also the reference linear solver (slow)")
    ap.add_argument("--dynamic", action="store_true", help="also the dynamic solver on the ~500-node mesh")
    ap.add_argument("--nodal", action="store_true", help="also the nodal volume term below 10 000 nodes")
    ap.add_argument(
        "--cli",
        type=int,
        default=0,
        metavar="N",
        help="only the whole `softgrasp plan` command on the default object, N times each with its "
        "figures drawn by a child process and in its own process (inline), alternating",
    )
    args = ap.parse_args()
    if args.cli:
        cli(args.cli)
        return
    print(
        f"softgrasp plan benchmark on {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"SOFTGRASP_THREADS={os.environ.get('SOFTGRASP_THREADS', 'auto')}"
    )
    print(
        f"{'nodes':>6} {'solver':>22} {'plan s':>8} {'warm s':>7} {'ratio':>6} {'peak MB':>8} {'incr':>5} "
        f"{'margin':>7}  thumb / first / middle N"
    )
    sizes = list(SIZES[:2] if args.quick else SIZES) + (list(LARGE) if args.large else [])
    fast: list[tuple[int, float]] = []
    for h in sizes:
        r = measure(h)
        print(_row(r, "quasi-static", None), flush=True)
        if "error" not in r:
            fast.append((r["nodes"], r["plan_s"]))
        if args.reference and r["nodes"] < 10_000:
            print(_row(measure(h, linsolve="reference"), "quasi-static, reference", r["plan_s"]), flush=True)
        if args.dynamic and h == SIZES[0]:
            print(_row(measure(h, "dynamic"), "dynamic (RK4)", r["plan_s"]), flush=True)
        if args.nodal and r["nodes"] < 10_000:
            print(_row(measure(h, volume="nodal"), "quasi-static, nodal", r["plan_s"]), flush=True)
    if len(fast) >= 2:
        n, t = np.array(fast, dtype=float).T
        slope = float(np.polyfit(np.log(n), np.log(t), 1)[0])
        pairs = ", ".join(
            f"{int(n[i])}->{int(n[i + 1])}: {math.log(t[i + 1] / t[i]) / math.log(n[i + 1] / n[i]):.2f}"
            for i in range(len(n) - 1)
        )
        print(f"cost ~ N^{slope:.2f} over {int(n[0])}-{int(n[-1])} nodes (successive: {pairs})")


if __name__ == "__main__":
    main()
