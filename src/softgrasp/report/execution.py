"""Reproduction step: the grasp plan executed under force control on the simulated hand in MuJoCo,
with the lift (paper Sec. 4.3.3), and its report section: set-points reached, lift height, slip.
Skipped, with the reason, when MuJoCo cannot be imported or there is no plan to execute."""

from __future__ import annotations

import time
from typing import Any

from softgrasp.report.context import Context, Progress, Skipped, rel
from softgrasp.report.document import Block, figures, params_table, pct, status_line


def _mujoco_version() -> str:
    """MuJoCo's version; raises :class:`Skipped` with the reason when it cannot be imported.
    Imported for the first time here, MuJoCo renders offscreen (``MUJOCO_GL``,
    softgrasp.offscreen.prefer_headless_gl)."""
    from softgrasp.offscreen import prefer_headless_gl

    prefer_headless_gl()
    try:
        import mujoco
    except Exception as exc:  # ImportError, or a broken installation
        raise Skipped(f"MuJoCo is not importable ({type(exc).__name__}: {exc}); pip install mujoco") from None
    return str(getattr(mujoco, "__version__", "unknown"))


def run_execution(ctx: Context, rec: dict[str, Any], progress: Progress) -> None:
    """Execute this run's grasp plan in MuJoCo and lift; record results and figures in ``rec``."""
    if ctx.plan_file is None:
        raise Skipped(f"there is no grasp plan to execute (the grasp step {ctx.plan_status})")
    version = _mujoco_version()
    from softgrasp.execution.controller import PHASES, ExecuteConfig, closing_lines, execute_plan
    from softgrasp.execution.mujoco.hand import MujocoHand
    from softgrasp.execution.mujoco.render import event_pictures
    from softgrasp.io.planfile import load_plan_file
    from softgrasp.model.mesh.io import load_mesh
    from softgrasp.viz.plots import plot_execution_forces, write_execution_pictures

    plan = load_plan_file(ctx.plan_file)
    hand = MujocoHand.from_plan(plan)
    facets = load_mesh(plan.mesh_file).facets
    lines = closing_lines(plan)
    cfg = ExecuteConfig()
    names = [f.name for f in plan.fingers]
    rec["parameters"] = {
        **cfg.describe(),
        "backend": f"MuJoCo {version}",
        "mujoco_timestep_s": float(hand.scene.model.opt.timestep),
        "object": "3-D flex from the plan's mesh (linear-tetrahedron elasticity with the plan's E, nu)",
        "fingertip_radius_m": plan.fingertip_radius,
        "mu": plan.mu,
        "table_mu": plan.table_mu,
        "plan": "grasp/plan.json",
    }
    largest = max(line.setpoint for line in lines.values())
    pictures = event_pictures(hand, plan.fingertip_radius, cfg.lift, largest)
    rendered = pictures.renderer is not None
    rec["parameters"]["pictures"] = (
        "MuJoCo's offscreen renderer" if rendered else "matplotlib (MuJoCo cannot render here)"
    )
    t0 = time.perf_counter()
    try:
        res = execute_plan(
            hand,
            lines,
            cfg,
            palm_to_world=hand.palm_to_world,
            progress=lambda f: progress(0.75 * f),
            on_event=pictures,
        )
    finally:
        pictures.close()
    sim_wall = time.perf_counter() - t0
    ser = res.series
    simulated = float(ser["t"][-1]) if len(ser["t"]) else 0.0
    outcome = res.describe()
    for f in outcome["fingers"]:
        f["relative_error"] = rel(f["measured_N"], f["setpoint_N"])
    rec["results"] = {
        **outcome,
        "lift_m": cfg.lift,
        "simulated_time_s": simulated,
        "simulation_wall_time_s": sim_wall,
        "realtime_factor": simulated / sim_wall if sim_wall > 0 else None,
        "paper": "the real hand closed under force control and lifted the sphere 'without any "
        "slipping' (Sec. 5; no numbers given)",
    }
    figs = {"forces": "figures/execution_forces.png"}
    plot_execution_forces(
        ser["t"],
        ser["force"],
        [lines[n].setpoint for n in names],
        names,
        ctx.out / figs["forces"],
        phases=[(p, res.events[p]) for p in PHASES if p in res.events],
        tolerance=cfg.tolerance,
    )
    written = write_execution_pictures(
        ctx.out / "figures",
        "execution_frame_",
        images=pictures.images,
        snapshots=pictures.snapshots,
        times=pictures.times,
        facets=facets,
        names=names,
        radius=plan.fingertip_radius,
        reached=bool(res.reached),
        lifted=bool(res.lifted),
        rise_m=float(res.rise),
        lift_m=cfg.lift,
    )
    for name in written:  # execution_frame_<event>.png
        figs[name[len("execution_") : -len(".png")]] = f"figures/{name}"
    rec["figures"] = figs
    progress(1.0)


def execution_section(st: dict[str, Any] | None) -> list[Block]:
    """The report section of the execution: set-points reached, lift, slip and pictures."""
    if st is None:
        return []
    blocks: list[Block] = [
        ("h", 2, "4. Execution on the simulated hand and lift (paper Sec. 4.3.3, Figs. 14–15)")
    ]
    blocks += status_line(st)
    blocks.append(
        (
            "p",
            "The plan is executed on a simulated hand in MuJoCo (physics softgrasp did not write): the "
            "sphere as a 3-D flex from the plan's mesh with its E and ν, the hand from the plan's URDF. "
            "Each fingertip closes along its planned line under force control on its tactile normal "
            "force, approaching its set-point without pressing past it, until every finger has stayed "
            "within the tolerance of its set-point; the arm "
            "then lifts and holds with the fingers keeping that posture.",
        )
    )
    r = st.get("results")
    if r:
        rows = [
            [
                f["name"],
                f"{f['setpoint_N']:.3f}",
                f"{f['measured_N']:.3f}",
                pct(f["relative_error"]),
                f"{f['held_N']:.3f}",
            ]
            for f in r["fingers"]
        ]
        blocks.append(("p", "**Set-points reached** (normal forces):"))
        blocks.append(
            (
                "table",
                [
                    "finger",
                    "set-point [N]",
                    "measured at the end of closing [N]",
                    "error",
                    "held (mean, last half of the hold) [N]",
                ],
                rows,
                "lrrrr",
            )
        )
        verdict = "dropped" if r["dropped"] else "lifted"
        blocks.append(("p", "**Lift, side by side with the paper**:"))
        blocks.append(
            (
                "table",
                ["", "paper (real Shadow hand)", "softgrasp (MuJoCo)"],
                [
                    [
                        "set-points reached",
                        "yes (force control on BioTac readings)",
                        "yes" if r["reached"] else "no",
                    ],
                    ["result", "lifted", verdict],
                    ["lift height [mm]", "not given", f"{r['rise_m'] * 1e3:.1f} of {r['lift_m'] * 1e3:.0f}"],
                    ["slip [mm]", "'without any slipping' (no number)", f"{r['slip_m'] * 1e3:.2f}"],
                    [
                        "simulated / wall time [s]",
                        "–",
                        f"{r['simulated_time_s']:.2f} / {r['simulation_wall_time_s']:.1f}",
                    ],
                ],
                "lll",
            )
        )
        blocks.append(
            (
                "quote",
                "The plan holds the sphere close to the least squeeze that holds (safety factor "
                "1), so the margin is small. During the lift and the hold the fingers keep their posture "
                "and the measured forces rise above the set-points (held/set-point: "
                + ", ".join(f"{f['name']} ×{f['held_N'] / f['setpoint_N']:.2f}" for f in r["fingers"])
                + ") as the weight passes from the table to the fingers and the sphere settles into "
                "them. The slip is MuJoCo's: its friction is soft (a constraint that slips in proportion "
                "to the force it carries), so the object creeps down a little through the fingers.",
            )
        )
    blocks += figures(
        st,
        {
            "forces": "Measured normal force of each finger against time with its set-point and "
            "tolerance band (cf. paper Fig. 15).",
            "frame_start": "Initial pose (cf. paper Fig. 14 a–b).",
            "frame_contact": "First contact (cf. Fig. 14 c–d).",
            "frame_closed": "Final deformation under the set-points (cf. Fig. 14 e–f).",
            "frame_end": "After the lift and the hold (lifted, or dropped).",
        },
    )
    if st.get("parameters"):
        blocks += params_table("Parameters", st["parameters"])
    return blocks
