"""Reproduction step: one-finger indentation of the foam cube (paper Sec. 4.3.1, Fig. 11), and
its report section: the force-penetration curve, forces at a few depths next to Hertz's and the
paper's law's, and the fitted exponent of F ~ delta^n."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from softgrasp.experiments.indentation import default_steps, indentation_test
from softgrasp.physics.fingertip.laws import PAPER_PREFACTOR, contact_stiffness, effective_modulus
from softgrasp.report.context import Context, Progress, hertz_force, linear_solver, object_of, power_fit
from softgrasp.report.document import Block, figures, fmt, object_rows, params_table, status_line

#: Exponent of the paper's contact law F = K delta^n (Eq. 9-11).
MODEL_EXPONENT = 1.5


def run_indentation(ctx: Context, rec: dict[str, Any], progress: Progress) -> None:
    """Indent the foam cube with one fingertip; record parameters, results, curve and figure in ``rec``."""
    from softgrasp.physics.fingertip.params import ContactParams
    from softgrasp.viz.plots import plot_force_penetration

    s = ctx.settings
    body, obj = object_of("cube", s)
    rec["object"] = obj
    params = ContactParams()
    radius = 0.008
    depth = s.indentation_depth_m
    steps = default_steps(depth)
    rec["parameters"] = {
        "depth_m": depth,
        "steps": steps,
        "increment_m": depth / steps,
        "fingertip_radius_m": radius,
        "fingertip": "rigid sphere",
        "contact": params.describe(),
        "solver": f"quasi-static: a static Newton solve per increment after settling on the table; "
        f"linear solves: {linear_solver()}",
    }
    res = indentation_test(
        body, depth=depth, radius=radius, params=params, progress=lambda f: progress(0.9 * f)
    )
    d, F = res.penetration_m, res.force_N
    m = body.material
    paper_K = contact_stiffness(effective_modulus(math.inf, 0.0, m.E, m.nu), radius, PAPER_PREFACTOR)
    depths = np.array([q for q in (0.001, 0.002, 0.003, 0.005) if q <= depth + 1e-12])
    rec["parameters"].update(
        {
            "table_mu": res.table_mu,
            "speed_m_s": res.speed_m_s,
            "point_m": res.point_m.tolist(),
            "point_shift_m": res.point_shift_m,
            "K_N_m1_5": res.K_N_m1_5,
        }
    )
    rec["results"] = {
        "force_at_depth_N": float(F[-1]),
        "peak_force_N": res.peak_force_N,
        "exponent": power_fit(d, F),
        "model_exponent": MODEL_EXPONENT,
        "contact_depth_at_end_m": float(res.contact_depth_m[-1]),
        "settle_sag_m": res.settle_sag_m,
        "split_increments": res.halvings,
        "at_depths": [
            {
                "penetration_m": float(q),
                "force_N": float(np.interp(q, d, F)),
                "paper_law_force_N": float(paper_K * q**1.5),
                "hertz_half_space_force_N": float(hertz_force(m.E, m.nu, radius, q)),
            }
            for q in depths
        ],
        "paper": "Fig. 11 is a plot only; the text quotes a mean force error of 0.3 N, "
        "'15 % of typical contact forces' (about 2 N)",
    }
    rec["curve"] = {
        "penetration_m": d,
        "force_N": F,
        "normal_force_N": res.normal_force_N,
        "tangential_force_N": res.tangential_force_N,
        "contact_depth_m": res.contact_depth_m,
    }
    fig = "figures/indentation_cube.png"
    plot_force_penetration(
        ctx.out / fig,
        d,
        F,
        title=f"Indentation of the foam cube ({body.mesh.n_nodes} nodes), R = {radius * 1e3:g} mm",
    )
    rec["figures"] = {"force_penetration": fig}
    progress(1.0)


def indentation_section(st: dict[str, Any] | None) -> list[Block]:
    """The report section of the indentation: forces at a few depths, the exponent, the curve."""
    if st is None:
        return []
    blocks: list[Block] = [("h", 2, "2. One-finger indentation of the foam cube (paper Sec. 4.3.1, Fig. 11)")]
    blocks += status_line(st)
    p = st.get("parameters", {})
    if p:
        blocks.append(
            (
                "p",
                f"A rigid spherical fingertip (R = {fmt(p.get('fingertip_radius_m'), 'g', 1e3)} mm) presses "
                "straight down on the middle of the top of the foam cube resting on the table, "
                f"quasi-statically in {p.get('steps')} increments to "
                f"{fmt(p.get('depth_m'), 'g', 1e3)} mm beyond first contact. Penetration is the "
                "fingertip's travel since first contact (the abscissa of Fig. 11).",
            )
        )
    r = st.get("results")
    if r:
        rows = [
            [
                fmt(a["penetration_m"], "g", 1e3),
                fmt(a["force_N"], ".3g"),
                fmt(a["paper_law_force_N"], ".3g"),
                fmt(a["hertz_half_space_force_N"], ".3g"),
            ]
            for a in r["at_depths"]
        ]
        blocks.append(("p", "**Force at a few depths** (the paper gives Fig. 11 as a plot only):"))
        blocks.append(
            (
                "table",
                [
                    "penetration [mm]",
                    "softgrasp force [N]",
                    "the paper's law alone, 2 Ψ √R δ^1.5 [N]",
                    "Hertz, rigid sphere on a half-space [N]",
                ],
                rows,
                "rrrr",
            )
        )
        blocks.append(
            (
                "p",
                f"**Non-linearity**: fitted exponent of F ∝ δⁿ over the curve n = "
                f"{fmt(r['exponent'], '.3f')} (the contact model's exponent: {r['model_exponent']:g}; a "
                "linear spring: 1).",
            )
        )
        blocks.append(
            (
                "ul",
                [
                    "The fingertip's travel is the contact law's own depth "
                    f"({fmt(r['contact_depth_at_end_m'], '.3g', 1e3)} mm of the "
                    f"{fmt(p.get('depth_m'), 'g', 1e3)} mm at the end) plus the deformation of the meshed "
                    "cube under the finger. The default law supplies only the part of the cube's "
                    "compliance that its mesh does not resolve, so the force follows Hertz's half-space "
                    "(the cube, 50 mm, is deeper than the contact is wide; its finite size softens it "
                    "at depth); the paper's law, in series with the mesh, counts the cube's compliance "
                    "twice. Either way the curve is clearly non-linear, the paper's point against linear "
                    "models.",
                    "The paper's text quotes a mean force error of 0.3 N, '15 % of typical contact "
                    "forces', i.e. forces of about 2 N. With Table 1's E = 4.93 MPa softgrasp's cube "
                    "needs tens of newtons at a few millimetres, the same order as Hertz's half-space "
                    "with that E (last column): the paper's forces suggest its cube was softer or "
                    "smaller than Table 1 implies. Nothing here is tuned to match.",
                ],
            )
        )
    blocks += figures(
        st, {"force_penetration": "Force against penetration of the fingertip (cf. paper Fig. 11)."}
    )
    if st.get("object"):
        params = object_rows(st["object"])
        params.update(p)
        blocks += params_table("Parameters", params)
    return blocks
