"""``softgrasp plan --uncertain``: robust set-points after the nominal plan, and their summary."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

__all__ = ["robust"]


def robust(args: argparse.Namespace, plan, uncertain: list, out: Path, t0: float) -> int:
    """Robust set-points around the saved nominal ``plan``; print them, their check and the
    drivers. Exit status 1 when no set-points met the goal."""
    import numpy as np

    from softgrasp.api.robust import robust_plan

    bars: dict[str, object] = {}

    def progress(stage: str, done: int, total: int) -> None:
        from tqdm import tqdm

        if stage not in bars:
            for b in bars.values():
                b.close()  # type: ignore[attr-defined]
            bars[stage] = tqdm(
                total=total, desc=stage, unit=" cases", leave=False, disable=None, file=sys.stderr
            )
        bar = bars[stage]
        bar.n = done  # type: ignore[attr-defined]
        bar.refresh()  # type: ignore[attr-defined]

    uncertain_text = ", ".join(f"{u.name} {u.low:.4g}..{u.high:.4g}" for u in uncertain)
    print(f"robust set-points over {args.samples} samples of {uncertain_text} on {args.workers} workers")
    try:
        res = robust_plan(
            plan,
            uncertain,
            samples=args.samples,
            seed=args.seed,
            quantile=args.quantile,
            workers=args.workers,
            scheduler=args.scheduler,
            progress=progress,
        )
    finally:
        for b in bars.values():
            b.close()  # type: ignore[attr-defined]
    wall = time.perf_counter() - t0
    print("finger    nominal N   robust N   samples need N (median..max)")
    for j, name in enumerate(res.fingers):
        need = res.required[:, j][np.isfinite(res.required[:, j])]
        print(
            f"{name:<9} {res.nominal[j]:9.3f} {res.setpoints[j]:10.3f}   "
            f"{np.median(need):.3f}..{need.max():.3f}"
        )
    d = res.describe()
    goal = "every sample" if res.quantile is None else f"{res.quantile:.0%} of the samples"
    print(
        f"robust set-points held {res.held_fraction:.0%} of {len(res.samples)} samples (goal: {goal}); "
        f"the nominal ones failed on {res.nominal_failure_fraction:.0%}"
    )
    if res.scale > 1:
        print(
            f"the samples' largest set-points were raised x{res.scale:.3g} ({res.rounds} checks) to hold them"
        )
    if d["smallest_friction_margin"] is not None:
        print(
            f"margin: friction {d['smallest_friction_margin']:.2f} (smallest over the held samples), "
            f"centre of mass moved up to {d['largest_drift_m'] * 1e3:.2f} mm"
        )
    drivers = ", ".join(f"{n} (rho {r:+.2f})" if r == r else f"{n} (not ranked)" for n, r in res.drivers)
    print(f"what drives the set-points (rank correlation with their total): {drivers}")
    for i, (held, why) in enumerate(zip(res.held, res.reasons, strict=True)):
        if not held:
            vals = ", ".join(f"{k} = {v:.4g}" for k, v in res.samples[i].items())
            print(f"  not held: sample {i} ({vals}): {why}")
    print(
        f"wrote {out}/plan.json (robust set-points), robust.json, robust.png, robust/ (each stage's table), "
        f"history.csv, object.vtu, frames.npz, forces.png, force_penetration.png, grasp.png ({wall:.1f} s)"
    )
    if not res.achieved:
        print(
            f"softgrasp: error: no set-points found that hold {goal} within {res.rounds} checks; "
            "narrow the ranges or give --quantile",
            file=sys.stderr,
        )
        return 1
    return 0
