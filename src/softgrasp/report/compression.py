"""Reproduction step: compression of the foam cube and of the rubber sphere between rigid plates
(paper Sec. 4.2, Figs. 8-9, Table 1), and its report section: stress-strain curves and the
identified E and nu next to Table 1's (and, for the sphere, Hertz's law fitted to its force)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from softgrasp.experiments.compression import CompressionResult, compression_test
from softgrasp.report.context import Context, Progress, hertz_force, linear_solver, object_of, power_fit, rel
from softgrasp.report.document import Block, figures, fmt, object_rows, params_table, pct, status_line

#: The paper's Table 1: identified Young's modulus [Pa] and Poisson's ratio of each object.
PAPER_TABLE1: dict[str, dict[str, float]] = {
    "cube": {"E_Pa": 4.9284e6, "nu": 0.39},
    "sphere": {"E_Pa": 0.0793e6, "nu": 0.45},
}
#: Strain range of the Hertz fit of the sphere's compression.
_HERTZ_FIT_STRAIN = 0.10
#: Plate friction of each compression: the cube lubricated (uniaxial stress, for E and nu), the
#: rubber sphere on steel platens (a lubricated sphere is held sideways by weak tethers only).
_PLATE_FRICTION = {"cube": 0.0, "sphere": 0.5}
#: Plate contact stiffness per node relative to the node's own stiffness (compression_test's).
_PLATE_PENALTY = 50.0


def _hertz_sphere_modulus(res: CompressionResult, nu: float, max_strain: float) -> float | None:
    """Young's modulus [Pa] of a sphere from its compression between plates by Hertz's law.

    Each plate is a Hertz contact of a sphere of radius R = H/2 with a rigid plane, taking half
    the plate travel d: F = (4/3) E/(1 - nu^2) sqrt(R) (d/2)^(3/2) (:func:`hertz_force`), linear in
    E. Fitted by least squares on the force over strains up to ``max_strain``.
    """
    sel = (res.strain > 0) & (res.strain <= max_strain + 1e-12)
    if not sel.any():
        return None
    R = 0.5 * res.height_m
    x = hertz_force(1.0, nu, R, 0.5 * res.displacement_m[sel])  # the force at E = 1 Pa
    return float(x @ res.force_N[sel] / (x @ x))


def run_compression(ctx: Context, rec: dict[str, Any], progress: Progress, name: str) -> None:
    """Compress object ``name`` between plates; record parameters, results, curve and figure in ``rec``."""
    from softgrasp.viz.plots import plot_stress_strain

    s = ctx.settings
    body, obj = object_of(name, s)
    rec["object"] = obj
    friction = _PLATE_FRICTION[name]
    rec["parameters"] = {
        "strain": s.compression_strain,
        "steps": s.compression_steps,
        "plate_friction": friction,
        "plate_penalty": _PLATE_PENALTY,
        "solver": f"static Newton per load increment (sparse Jacobian, energy line search); "
        f"linear solves: {linear_solver()}",
    }
    res = compression_test(
        body,
        strain=s.compression_strain,
        steps=s.compression_steps,
        plate_friction=friction,
        penalty=_PLATE_PENALTY,
        progress=lambda f: progress(0.9 * f),
    )
    paper = PAPER_TABLE1[name]
    m = body.material
    rec["parameters"].update({"height_m": res.height_m, "area_m2": res.area_m2, "fit_strain": res.fit_strain})
    out: dict[str, Any] = {
        "E_Pa": res.apparent_E_Pa,
        "nu": res.apparent_nu,
        "paper_E_Pa": paper["E_Pa"],
        "paper_nu": paper["nu"],
        "E_relative_difference": rel(res.apparent_E_Pa, paper["E_Pa"]),
        "nu_difference": res.apparent_nu - paper["nu"],
        "material_E_Pa": m.E,
        "material_nu": m.nu,
        "peak_force_N": float(res.force_N.max()),
        "peak_stress_Pa": float(res.stress_Pa.max()),
        "secant_modulus_at_peak_Pa": float(res.stress_Pa[-1] / res.strain[-1]),
        "newton_iterations": int(res.newton_iterations.sum()),
        "tether_force_N": res.tether_force_N,
    }
    if name == "sphere":
        E_h = _hertz_sphere_modulus(res, m.nu, _HERTZ_FIT_STRAIN)
        sel = (res.strain > 0) & (res.strain <= _HERTZ_FIT_STRAIN + 1e-12)
        out["hertz_fit_strain"] = _HERTZ_FIT_STRAIN
        out["hertz_E_Pa"] = E_h
        out["hertz_E_relative_difference"] = None if E_h is None else rel(E_h, paper["E_Pa"])
        out["force_exponent"] = power_fit(res.displacement_m[sel], res.force_N[sel])
    rec["results"] = out
    rec["curve"] = {
        "displacement_m": res.displacement_m,
        "force_N": res.force_N,
        "strain": res.strain,
        "stress_Pa": res.stress_Pa,
        "lateral_strain": res.lateral_strain,
    }
    fig = f"figures/compression_{name}.png"
    plot_stress_strain(
        ctx.out / fig,
        res.strain,
        res.stress_Pa,
        apparent_E_Pa=res.apparent_E_Pa,
        title=f"Compression of the {name} ({m.name}, {body.mesh.n_nodes} nodes)",
        linear_E_Pa=m.E,
    )
    rec["figures"] = {"stress_strain": fig}
    progress(1.0)


def compression_section(steps: Mapping[str, dict[str, Any]]) -> list[Block]:
    """The report section of both compressions: Table 1 side by side, the curves and the discussion."""
    cube, sphere = steps.get("compression_cube"), steps.get("compression_sphere")
    present = [s for s in (cube, sphere) if s is not None]
    if not present:
        return []
    blocks: list[Block] = [("h", 2, "1. Compression tests (paper Sec. 4.2, Figs. 8–9, Table 1)")]
    first = present[0]
    strain = first.get("parameters", {}).get("strain")
    blocks.append(
        (
            "p",
            "Each object settles under its own weight on a rigid bottom plate; a rigid top plate then "
            f"compresses it quasi-statically (one static Newton solve per increment) to "
            f"{fmt(strain, '.0f', 100)} % strain. Nominal stress is the plate force over the object's "
            "outline seen from above, strain the plate travel over the initial height. The identified E "
            "is the initial slope of stress against strain (up to 1 % strain, `apparent_E_Pa`), ν minus "
            "the lateral over the axial strain over the same range (`apparent_nu`). The models are built "
            "with Table 1's E and ν, so this checks that the calibrated mass-spring body gives back its "
            "input the way the paper identified Table 1 from its measured curves (Fig. 9); the paper's "
            "curves themselves are not given as numbers.",
        )
    )
    rows = []
    for name, st in (("cube", cube), ("sphere", sphere)):
        paper = PAPER_TABLE1[name]
        r = st.get("results") if st is not None else None
        if st is None:
            continue
        if r is None:
            rows.append(
                [
                    name,
                    fmt(paper["E_Pa"], ".4f", 1e-6),
                    st["status"],
                    "–",
                    fmt(paper["nu"], ".2f"),
                    "–",
                    "–",
                ]
            )
            continue
        rows.append(
            [
                name,
                fmt(paper["E_Pa"], ".4f", 1e-6),
                fmt(r["E_Pa"], ".4f", 1e-6),
                pct(r["E_relative_difference"]),
                fmt(paper["nu"], ".2f"),
                fmt(r["nu"], ".3f"),
                fmt(r["nu_difference"], "+.3f"),
            ]
        )
    blocks.append(("p", "**Table 1, side by side** (E in MPa):"))
    blocks.append(
        (
            "table",
            [
                "object",
                "paper E",
                "softgrasp E (initial slope)",
                "difference",
                "paper ν",
                "softgrasp ν",
                "difference",
            ],
            rows,
            "lrrrrrr",
        )
    )
    notes: list[str] = []
    if cube is not None and cube.get("results"):
        r = cube["results"]
        notes.append(
            f"**Cube**: lubricated plates, so the cube is in uniaxial stress and the initial slope is "
            f"its Young's modulus: the calibrated network gives back Table 1's E within "
            f"{pct(abs(r['E_relative_difference']), '.1f')} and ν within {abs(r['nu_difference']):.2g}. "
            "Although the foam's stress-strain law is linear, the curve stiffens at large strain (secant "
            f"modulus at {fmt(strain, '.0f', 100)} %: {fmt(r['secant_modulus_at_peak_Pa'], '.4g', 1e-6)} "
            f"MPa, {pct(rel(r['secant_modulus_at_peak_Pa'], r['E_Pa']))} over the initial slope): the "
            "model is geometrically non-linear (its springs and volume term follow the deformed "
            "configuration). The paper's measured curves (Fig. 9) are not "
            "given as numbers; a measured non-linear law can be given to softgrasp as a table."
        )
    if sphere is not None and sphere.get("results"):
        r = sphere["results"]
        notes.append(
            f"**Sphere**: the initial slope, {fmt(r['E_Pa'], '.4g', 1e-3)} kPa, is not the rubber's modulus "
            f"({pct(r['E_relative_difference'])}) and the lateral strain at the equator is not ν: "
            "between plates a sphere is a Hertz contact, σ = 4/(3π) E/(1−ν²) ε^1.5 at small strain, "
            "whose slope vanishes at zero strain. Fitting Hertz's law to the force up to "
            f"{fmt(r['hertz_fit_strain'], '.0f', 100)} % strain gives E = "
            f"{fmt(r['hertz_E_Pa'], '.4g', 1e-3)} kPa ({pct(r['hertz_E_relative_difference'])} from "
            f"Table 1), with a fitted force exponent of {fmt(r['force_exponent'], '.2f')} instead of "
            "Hertz's 1.5: the coarse mesh resolves the small contact patches at the poles with a few "
            "facets (a finer mesh brings both closer). The paper obtained its values from the curve "
            "'by applying the method indicated in [33]', which it does not describe, so softgrasp cannot "
            "repeat that identification; softgrasp's sphere has Table 1's E and ν by construction."
        )
    if notes:
        blocks.append(("ul", notes))
    for name, st in (("cube", cube), ("sphere", sphere)):
        if st is None:
            continue
        blocks.append(("h", 3, f"1.{1 if name == 'cube' else 2} {st['title']}"))
        blocks += status_line(st)
        blocks += figures(
            st,
            {
                "stress_strain": f"Nominal stress against strain of the {name} (cf. paper Fig. 9), with "
                "the initial-slope line and the material's E."
            },
        )
        if st.get("object"):
            params = object_rows(st["object"])
            params.update(st.get("parameters", {}))
            blocks += params_table("Parameters", params)
    return blocks
