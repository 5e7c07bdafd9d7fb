"""Benchmark of the fingertip contact: force evaluations vs facet count, and indentation runs.

(a) One fingertip (R = 8 mm) pressed 2 mm into the top of the rubber sphere (radius 64 mm) at mesh
    sizes 16, 8, 6 and 4 mm: the same contact patch on ever more facets. It times
    ``FingertipContact.forces`` (detection included) per evaluation, and ``detect`` with its two
    broad phases measured side by side: the surface nodes near the fingertip through the mesh's
    node-to-facet index (what the contact model uses), and the peer, a k-d tree of all facet
    centroids rebuilt on every call (O(F log F)); the ratio tree / nodes is printed.
(b) The indentation test (default depth 5 mm, R = 8 mm, ~0.25 mm increments) on the foam cube at
    about 2 000 and 8 000 nodes: wall time, Newton iterations, force at 5 mm.

Run: ``make bench`` or ``.venv/bin/python benchmarks/bench_contact.py [--quick]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from softgrasp.experiments.indentation import indentation_test, surface_height
from softgrasp.model.objects import CUBE_SIZE, make_object
from softgrasp.physics.body import build_body
from softgrasp.physics.fingertip.contact import FingertipContact
from softgrasp.physics.fingertip.geometry import FacetIndex, detect
from softgrasp.physics.fingertip.params import Fingertip

#: Sphere mesh sizes [m] of part (a).
SPHERE_SIZES = (0.016, 0.008, 0.006, 0.004)
#: Cube divisions of part (b): 2 215 and 7 295 nodes.
CUBE_DIVISIONS = (9, 14)
RADIUS = 0.008
DEPTH = 0.002


def _per_call(fn, min_time: float = 0.5) -> float:
    """Mean wall time [s] of ``fn()`` over enough repetitions to last ``min_time``."""
    fn()
    n, t = 0, 0.0
    t0 = time.perf_counter()
    while t < min_time:
        fn()
        n += 1
        t = time.perf_counter() - t0
    return t / n


def bench_forces(h: float) -> dict[str, float]:
    mesh, mat, mass = make_object("sphere", h)
    body = build_body(mesh, mat, mass=mass)
    x = np.asarray(mesh.points)
    facets = mesh.facets
    # Press at the centroid of the facet under the top (away from its edges, where the facet test
    # is blind on a convex mesh), 2 mm below that facet's plane along z.
    _, f = surface_height(x, facets, mesh.centroid[:2])
    xy = x[facets[f]].mean(axis=0)[:2]
    zs, _ = surface_height(x, facets, xy)
    tip = Fingertip(RADIUS, centre=[xy[0], xy[1], zs + RADIUS - DEPTH])
    fc = FingertipContact((tip,))
    state = fc.init_state(body, x)
    v = np.zeros_like(x)
    radii = np.array([RADIUS])
    centres = tip.centre[None]
    touched = len(fc.pairs(body, x, 0.0))

    index = FacetIndex.of(mesh)
    return {
        "h": h,
        "nodes": mesh.n_nodes,
        "facets": len(facets),
        "touched": touched,
        "forces": _per_call(lambda: fc.forces(body, x, v, 0.0, state)),
        "nodes_bp": _per_call(lambda: detect(x, facets, centres, radii, closest=True, index=index)),
        "tree_bp": _per_call(lambda: detect(x, facets, centres, radii, closest=True)),
    }


def bench_indent(n: int) -> dict[str, float]:
    mesh, mat, mass = make_object("cube", CUBE_SIZE / n)
    body = build_body(mesh, mat, mass=mass)
    res = indentation_test(body)
    return {
        "nodes": mesh.n_nodes,
        "tets": mesh.n_tets,
        "steps": len(res.force_N) - 1,
        "newton": int(res.newton_iterations[1:].sum()),
        "wall": res.wall_time_s,
        "force": float(res.force_N[-1]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two sphere sizes, smaller cube only")
    args = ap.parse_args()
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, NumPy {np.__version__}"
    )
    print(f"\n(a) FingertipContact.forces, R = {RADIUS * 1e3:g} mm, {DEPTH * 1e3:g} mm into the sphere")
    print(
        f"{'h [mm]':>7} {'nodes':>7} {'facets':>7} {'touched':>7} {'forces [ms]':>11} "
        f"{'detect, node index [ms]':>23} {'detect, k-d tree [ms]':>21} {'tree/index':>10}"
    )
    for h in SPHERE_SIZES[: 2 if args.quick else None]:
        r = bench_forces(h)
        print(
            f"{r['h'] * 1e3:>7g} {r['nodes']:>7} {r['facets']:>7} {r['touched']:>7} "
            f"{1e3 * r['forces']:>11.3f} {1e3 * r['nodes_bp']:>23.3f} {1e3 * r['tree_bp']:>21.3f} "
            f"{r['tree_bp'] / r['nodes_bp']:>10.2f}"
        )
    print("\n(b) indentation test, foam cube, depth 5 mm, R = 8 mm")
    print(f"{'nodes':>7} {'tets':>7} {'steps':>6} {'Newton its':>10} {'wall [s]':>9} {'F(5 mm) [N]':>12}")
    for n in CUBE_DIVISIONS[: 1 if args.quick else None]:
        r = bench_indent(n)
        print(
            f"{r['nodes']:>7} {r['tets']:>7} {r['steps']:>6} {r['newton']:>10} {r['wall']:>9.1f} "
            f"{r['force']:>12.4g}"
        )


if __name__ == "__main__":
    main()
