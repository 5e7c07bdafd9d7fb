"""Benchmark of ``softgrasp sweep``: cases per minute for the default object (the rubber sphere at
its default mesh) on a local Dask cluster of 1 and of 2 worker processes, and the scaling
efficiency (rate with 2 workers over twice the rate with 1).

Peer measured in the same run: the same cases planned one after the other in this process, with
no Dask at all (what a loop in a user's script costs), so the ratios show both what the cluster
costs (start-up, transfer) and what the second worker gains.

Run: ``make bench`` or ``.venv/bin/python benchmarks/bench_sweep.py [--cases 8] [--mesh-size M]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time

from softgrasp.sweep.case import run_case
from softgrasp.sweep.engine import run_sweep
from softgrasp.sweep.spec import SweepSpec, sweep_cases


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=8, help="cases per configuration (default 8)")
    ap.add_argument("--mesh-size", type=float, default=None, help="mesh size [m] (default: the object's)")
    args = ap.parse_args()
    base: dict[str, object] = {"object": "sphere"}
    if args.mesh_size is not None:
        base["mesh_size"] = args.mesh_size
    mus = [0.5 + 0.4 * k / max(args.cases - 1, 1) for k in range(args.cases)]
    spec = SweepSpec("grid", args.cases, 0, False, base, {"mu": mus})
    cases = sweep_cases(spec)
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; {len(cases)} cases"
    )
    print("each case: softgrasp plan of the default sphere, mu from 0.5 to 0.9")

    t0 = time.perf_counter()
    for c in cases:
        row = run_case(c.options)
        assert row["status"] == "ok", row["error"]
    loop = time.perf_counter() - t0
    rate_loop = 60.0 * len(cases) / loop
    print(f"{'in-process loop (no Dask)':<30} {loop:7.1f} s  {rate_loop:6.1f} cases/min")
    rates = {}
    for workers in (1, 2):
        with tempfile.TemporaryDirectory() as tmp:
            res = run_sweep(spec, cases, tmp, workers=workers)
        assert res.failed == 0
        rates[workers] = 60.0 * res.ran / res.wall_time_s
        print(
            f"{f'Dask, {workers} worker(s)':<30} {res.wall_time_s:7.1f} s  {rates[workers]:6.1f} cases/min "
            f"({rates[workers] / rate_loop:.2f} x the loop; cluster start-up included)"
        )
    print(f"scaling efficiency 2 workers / (2 x 1 worker): {rates[2] / (2 * rates[1]):.0%}")


if __name__ == "__main__":
    main()
