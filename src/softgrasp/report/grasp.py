"""Reproduction step: the three-finger grasp plan of the rubber sphere (paper Sec. 4.3.2, Table 2,
Figs. 12-13, 15), and its report section: set-points and penetrations next to Table 2. The plan is
written to ``grasp/plan.json`` + ``grasp/object.vtu`` for the execution step (and ``softgrasp
execute``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from softgrasp.grasp.planner import PlanConfig, plan_grasp
from softgrasp.io.atomic import write_json
from softgrasp.report.context import Context, Progress, jsonable, linear_solver, object_of
from softgrasp.report.document import Block, figures, fmt, object_rows, params_table, pct, status_line

#: The paper's Table 2: penetration depth [m] and force [N] of each finger.
PAPER_TABLE2: dict[str, dict[str, float]] = {
    "thumb": {"penetration_m": 0.020, "force_N": 2.2},
    "first": {"penetration_m": 0.015, "force_N": 1.6},
    "middle": {"penetration_m": 0.012, "force_N": 1.3},
}


def run_grasp(ctx: Context, rec: dict[str, Any], progress: Progress) -> None:
    """Plan the grasp of the rubber sphere, write it to ``grasp/``; record results and figures in ``rec``."""
    from softgrasp.io.plan_document import hand_polylines, plan_document
    from softgrasp.model.mesh.io import save_mesh
    from softgrasp.model.mesh.tetmesh import TetMesh
    from softgrasp.viz.plots import plot_grasp_3d, plot_plan_force_penetration, plot_plan_forces

    body, obj = object_of("sphere", ctx.settings)
    rec["object"] = obj
    config = PlanConfig()
    rec["parameters"] = {
        **config.describe(),
        "solver_detail": "closing in increments, each brought to rest by a static Newton solve; hold check "
        f"by backward Euler; linear solves: {linear_solver()}",
    }
    plan = plan_grasp(body, config, progress=lambda f: progress(0.8 * f))
    doc = plan_document(plan, body, "sphere")
    grasp_dir = ctx.out / "grasp"
    grasp_dir.mkdir(parents=True, exist_ok=True)
    save_mesh(TetMesh(plan.placed, body.mesh.tets, name=body.mesh.name), grasp_dir / "object.vtu")
    doc["object"]["mesh_file"] = "object.vtu"
    write_json(grasp_dir / "plan.json", jsonable(doc))
    ctx.plan_file = grasp_dir / "plan.json"
    weight = float(body.total_mass * np.linalg.norm(body.gravity))
    fingers = []
    for j, f in enumerate(plan.fingers):
        p = PAPER_TABLE2.get(f.name, {})
        fingers.append(
            {
                "name": f.name,
                "penetration_m": f.penetration,
                "force_N": f.force_norm,
                "normal_force_N": f.normal_force,
                "tangential_force_N": f.tangential_force,
                "rigid_minimum_normal_force_N": float(plan.rigid_normal_forces[j]),
                "paper_penetration_m": p.get("penetration_m"),
                "paper_force_N": p.get("force_N"),
                "force_ratio_to_paper": f.force_norm / p["force_N"] if p else None,
            }
        )
    forces = [f.force_norm for f in plan.fingers]
    rec["results"] = {
        "fingers": fingers,
        "weight_N": weight,
        "total_force_N": float(sum(forces)),
        "total_normal_force_N": float(sum(f.normal_force for f in plan.fingers)),
        "rigid_minimum_total_normal_force_N": float(np.sum(plan.rigid_normal_forces)),
        "paper_total_force_N": float(sum(p["force_N"] for p in PAPER_TABLE2.values())),
        "thumb_largest": bool(plan.fingers[0].name == "thumb" and forces[0] == max(forces)),
        "equilibrium": doc["equilibrium"],
        "hold": {"com_drift_m": plan.com_drift, "duration_s": plan.hold_time},
        "initial_grasp": doc["initial_grasp"],
        "increments": plan.increments,
        "plan_file": "grasp/plan.json",
    }
    from softgrasp.model.objects import SPHERE_RADIUS
    from softgrasp.report.table2 import consistent_runs

    rec["results"]["table2_consistent"] = consistent_runs(body, plan, PAPER_TABLE2, SPHERE_RADIUS)
    progress(0.8)
    rec["curve"] = {
        "travel_m": plan.travel,
        "penetration_m": plan.penetration,
        "force_norm_N": plan.force_norm,
    }
    names = [f.name for f in plan.fingers]
    figs = {
        "forces": "figures/grasp_forces.png",
        "force_penetration": "figures/grasp_force_penetration.png",
        "grasp_3d": "figures/grasp_3d.png",
    }
    plot_plan_forces(
        np.arange(1.0, plan.increments + 1.0),
        plan.force_norm,
        names,
        ctx.out / figs["forces"],
        setpoints=[f.force_norm for f in plan.fingers],
        held_at=plan.held_increment,
        title="Grasping forces per closing increment (cf. paper Fig. 13)",
    )
    progress(0.85)
    plot_plan_force_penetration(
        plan.penetration,
        plan.force_norm,
        names,
        ctx.out / figs["force_penetration"],
        title="Force against penetration of each finger (cf. paper Fig. 15)",
    )
    progress(0.9)
    plot_grasp_3d(
        plan.positions,
        body.mesh.facets,
        plan.centres,
        np.full(len(names), config.fingertip_radius),
        np.array([f.force for f in plan.fingers]),
        plan.contact_points,
        names,
        ctx.out / figs["grasp_3d"],
        title=f"Held grasp of the rubber sphere, mu = {config.contact.mu:g} (cf. paper Fig. 12)",
        weight=(plan.com, weight),
        links=hand_polylines(plan),
    )
    rec["figures"] = figs
    progress(1.0)


def grasp_section(st: dict[str, Any] | None) -> list[Block]:
    """The report section of the grasp plan: Table 2 side by side, equilibrium and figures."""
    if st is None:
        return []
    blocks: list[Block] = [
        ("h", 2, "3. Three-finger grasp of the rubber sphere (paper Sec. 4.3.2, Table 2, Figs. 12–13, 15)")
    ]
    blocks += status_line(st)
    blocks.append(
        (
            "p",
            "The planner picks a force-closure initial grasp the Shadow-like hand reaches (thumb opposite "
            "the first and middle fingers in the horizontal plane through the centre of mass), closes "
            "the three fingertips together towards the centroid of the contact triangle in small "
            "increments, each brought to rest on the table, until the grasp test (Eq. 21–22 with friction "
            "cones) passes and the object, the table taken away, stays held; those held-state forces are "
            "the set-points. Penetration is measured from each finger's first contact, as in Table 2.",
        )
    )
    r = st.get("results")
    if r:
        rows = []
        for f in r["fingers"]:
            rows.append(
                [
                    f["name"],
                    fmt(f["paper_penetration_m"], "g", 1e3),
                    fmt(f["paper_force_N"], ".1f"),
                    fmt(f["penetration_m"], ".2f", 1e3),
                    f"{f['force_N']:.3f} ({f['normal_force_N']:.3f} + {f['tangential_force_N']:.3f})",
                    fmt(f["force_ratio_to_paper"], ".2f"),
                    fmt(f["rigid_minimum_normal_force_N"], ".3f"),
                ]
            )
        blocks.append(("p", "**Table 2, side by side**:"))
        blocks.append(
            (
                "table",
                [
                    "finger",
                    "paper: penetration [mm]",
                    "paper: force [N]",
                    "softgrasp: penetration [mm]",
                    "softgrasp: force [N] (normal + friction)",
                    "force ratio softgrasp / paper",
                    "rigid-object minimum normal force [N]",
                ],
                rows,
                "lrrrrrr",
            )
        )
        eq, hold, ig = r["equilibrium"], r["hold"], r["initial_grasp"]
        blocks.append(
            (
                "ul",
                [
                    f"Held state: force residual {eq['force_residual_N']:.2e} N, torque residual "
                    f"{eq['torque_residual_Nm']:.2e} N m (weight {r['weight_N']:.3f} N); friction margin "
                    f"{pct(eq['friction_margin'], '.0f')}; equilibrium satisfied: "
                    f"{'yes' if eq['satisfied'] else 'no'}; centre of mass drift "
                    f"{hold['com_drift_m'] * 1e3:.3f} mm over {hold['duration_s']:g} s of holding.",
                    f"Initial grasp: Ferrari–Canny ε = {ig['epsilon']:.3g}, finger half-spread "
                    f"{ig['finger_half_spread_deg']:.0f}°; {r['increments']} closing increments.",
                    f"The plan is written to `{r['plan_file']}` (with `grasp/object.vtu`); "
                    "`softgrasp execute` reads it.",
                ],
            )
        )
        order = "agrees with the paper's" if r["thumb_largest"] else "differs from the paper's"
        blocks.append(
            (
                "quote",
                f"**Why softgrasp's forces are smaller.** The ordering {order} (the thumb, balancing two "
                "fingers, pushes hardest); the magnitudes do not. The sphere weighs "
                f"{r['weight_N']:.2f} N; with μ = {st['parameters']['contact']['mu']:g} a rigid sphere "
                f"at these contacts needs only {r['rigid_minimum_total_normal_force_N']:.2f} N of normal "
                "force in all, and softgrasp stops at the least squeeze whose grasp holds, holding it with "
                f"{r['total_normal_force_N']:.2f} N of normal force ({r['total_force_N']:.2f} N with "
                f"friction). The paper's {r['paper_total_force_N']:.1f} N is "
                f"{r['paper_total_force_N'] / r['weight_N']:.0f} times the weight: its stopping test "
                "('equilibrium conditions are satisfied') is not specified further, its friction "
                "coefficient and fingertip size are not given, and its BioTac fingertips are soft. "
                "The penetrations are much smaller also because softgrasp's fingertips are rigid and its "
                "contact law counts the sphere's compliance once. A lower μ or a larger "
                "`safety_factor` gives larger forces; nothing here is tuned to match.",
            )
        )
        blocks += _consistent_blocks(r.get("table2_consistent"))
    blocks += figures(
        st,
        {
            "forces": "Force on each finger against the closing increment (cf. paper Fig. 13): the "
            "closing with the sphere on the table, the bisected last step's increments sorted in by "
            "travel. The set-points of Table 2 are the forces once the table is taken away and the "
            "fingers carry the weight.",
            "force_penetration": "Force against penetration of each finger (cf. paper Fig. 15).",
            "grasp_3d": "The held, deformed sphere with the fingertips, their forces on it, the weight and "
            "the hand (cf. paper Fig. 12).",
        },
    )
    if st.get("object"):
        params = object_rows(st["object"])
        params.update(st.get("parameters", {}))
        blocks += params_table("Parameters", params)
    return blocks


def _consistent_blocks(t: dict[str, Any] | None) -> list[Block]:
    """Table 2 with the parameters that make it consistent (:mod:`softgrasp.report.table2`)."""
    if not t:
        return []
    E = t["implied_E_Pa"]
    blocks: list[Block] = [
        (
            "p",
            "**What would make Table 2 consistent.** Hertz's rigid 8 mm sphere on the 64 mm sphere needs "
            + ", ".join(f"{n} {v / 1e3:.1f} kPa" for n, v in E.items())
            + f" (mean {t['implied_E_mean_Pa'] / 1e3:.1f} kPa, {79.3e3 / t['implied_E_mean_Pa']:.0f} times "
            "softer than Table 1's 79.3 kPa) to press the paper's penetrations with its forces, and three "
            f"fingers need {t['paper_total_force_N']:.1f} N in all at these contacts only with μ = "
            f"{t['implied_mu']:.2f}. The sphere planned again on the same contacts with those values:",
        )
    ]
    rows = []
    for run in t["runs"]:
        if "fingers" in run:
            cells = [f"{f['penetration_m'] * 1e3:.1f} mm, {f['force_N']:.2f} N" for f in run["fingers"]]
        else:
            cells = [f"no plan: {run['failed']}", "", ""]
        rows.append([f"{run['label']} (E = {run['E_Pa'] / 1e3:.1f} kPa, μ = {run['mu']:.2f})", *cells])
    rows.append(["the paper (Table 2)", "20 mm, 2.2 N", "15 mm, 1.6 N", "12 mm, 1.3 N"])
    blocks.append(("table", ["run", "thumb", "first", "middle"], rows, "llll"))
    return blocks
