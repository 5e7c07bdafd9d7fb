"""The report's structure: title, key numbers (one line per step), the steps and their wall
times, one section per experiment and the environment, as blocks of
:mod:`softgrasp.report.document`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from softgrasp.report.compression import compression_section
from softgrasp.report.document import Block, fmt, pct
from softgrasp.report.execution import execution_section
from softgrasp.report.grasp import grasp_section
from softgrasp.report.indentation import indentation_section


def key_numbers(steps: Mapping[str, dict[str, Any]]) -> list[str]:
    """One line per step with its headline numbers, or why it has none."""
    items: list[str] = []
    for name, st in steps.items():
        r = st.get("results")
        if st["status"] != "ok" or not r:
            items.append(f"{st['title']}: **{st['status']}** ({st['message']}).")
            continue
        if name.startswith("compression_"):
            obj = name.split("_")[1]
            line = (
                f"Table 1, {obj}: E {r['E_Pa'] / 1e6:.4g} MPa vs the paper's {r['paper_E_Pa'] / 1e6:.4g} MPa "
                f"({pct(r['E_relative_difference'])}), ν {r['nu']:.3f} vs {r['paper_nu']:g}"
            )
            if obj == "sphere":
                line += (
                    f" — a sphere's initial slope is not its modulus; Hertz's law fitted to its force "
                    f"gives {fmt(r['hertz_E_Pa'], '.4g', 1e-6)} MPa "
                    f"({pct(r['hertz_E_relative_difference'])})"
                )
            items.append(line + " (§1).")
        elif name == "indentation_cube":
            last = r["at_depths"][-1] if r["at_depths"] else None
            at = f"{last['force_N']:.3g} N at {last['penetration_m'] * 1e3:g} mm; " if last else ""
            items.append(
                f"Fig. 11, foam cube: {at}F ∝ δ^{fmt(r['exponent'], '.2f')} over the curve (contact law: "
                f"δ^{r['model_exponent']:g}) (§2)."
            )
        elif name == "grasp_sphere":
            fs = r["fingers"]
            ratios = [1 / f["force_ratio_to_paper"] for f in fs if f["force_ratio_to_paper"]]
            spread = f"{min(ratios):.1f}–{max(ratios):.1f} times smaller" if ratios else "not comparable"
            items.append(
                "Table 2, rubber sphere: "
                + " / ".join(f"{f['force_N']:.2f}" for f in fs)
                + " N at "
                + " / ".join(f"{f['penetration_m'] * 1e3:.2f}" for f in fs)
                + " mm (thumb / first / middle) vs the paper's "
                + " / ".join(fmt(f["paper_force_N"], ".1f") for f in fs)
                + " N at "
                + " / ".join(fmt(f["paper_penetration_m"], "g", 1e3) for f in fs)
                + f" mm: forces {spread}, close to the least that holds the "
                + f"{r['weight_N']:.2f} N sphere (§3)."
            )
        elif name == "execution_sphere":
            err = max(abs(f["relative_error"]) for f in r["fingers"])
            verdict = (
                "**dropped**"
                if r["dropped"]
                else f"lifted {r['rise_m'] * 1e3:.1f} of {r['lift_m'] * 1e3:.0f} mm"
            )
            items.append(
                f"Execution in MuJoCo: set-points {'reached' if r['reached'] else '**not reached**'} "
                f"(largest error {pct(err, '.1f')}), {verdict}, slip {r['slip_m'] * 1e3:.2f} mm (§4)."
            )
    return items


def report_blocks(doc: dict[str, Any]) -> list[Block]:
    steps = {s["name"]: s for s in doc["steps"]}
    run = doc["run"]
    blocks: list[Block] = [
        ("h", 1, "softgrasp: reproduction of the paper's experiments"),
        (
            "p",
            f"*{doc['paper']}* — Sec. 4, Tables 1–2. softgrasp {run['softgrasp_version']}, "
            f"{'quick (coarse meshes)' if run['quick'] else 'full'} run, {run['date_utc']}, "
            f"{run['wall_time_s']:.1f} s in all. SI units inside softgrasp; millimetres and MPa/kPa in "
            "these tables for people. Every number is also in `reproduce.json`.",
        ),
    ]
    failed = [s for s in doc["steps"] if s["status"] == "failed"]
    if failed:
        blocks.append(
            ("quote", "**Failed steps**: " + "; ".join(f"{s['name']}: {s['message']}" for s in failed))
        )
    if steps:
        blocks += [("h", 2, "Key numbers"), ("ul", key_numbers(steps))]
    rows = [[s["title"], s["status"], f"{s['wall_time_s']:.2f}", s["message"] or "–"] for s in doc["steps"]]
    rows.append(["report (md, html, json)", "ok", f"{run['report_wall_time_s']:.2f}", "–"])
    rows.append(["**total**", "", f"**{run['wall_time_s']:.2f}**", ""])
    blocks += [
        ("h", 2, "Steps and wall times"),
        ("table", ["step", "status", "wall time [s]", "note"], rows, "llrl"),
    ]
    blocks += compression_section(steps)
    blocks += indentation_section(steps.get("indentation_cube"))
    blocks += grasp_section(steps.get("grasp_sphere"))
    blocks += execution_section(steps.get("execution_sphere"))
    env = doc["environment"]
    blocks += [
        ("h", 2, "Environment"),
        ("table", ["component", "version or setting"], [[k, str(v)] for k, v in env.items()], "ll"),
    ]
    return blocks
