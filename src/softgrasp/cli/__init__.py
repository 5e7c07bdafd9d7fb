"""Command-line interface: parse, call the library, write files. No physics here.

Every deliberate error (:class:`softgrasp.errors.SoftgraspError`) becomes one line on stderr and
exit status 2; an interrupted run exits 130. Lengths are given in metres on the command line and
printed in millimetres for people.
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from softgrasp import __version__
from softgrasp.errors import ConfigError, SoftgraspError
from softgrasp.io.options import PLAN_DEFAULTS

if TYPE_CHECKING:
    from softgrasp.viz.worker import FigureWorker

__all__ = ["main"]


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one clear line instead of usage + error
        self.exit(2, f"softgrasp: error: {message} (see 'softgrasp {self.prog.split()[-1]} --help')\n")


def _positive(name: str):
    def conv(s: str) -> float:
        try:
            v = float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {s!r}") from None
        if not v > 0:
            raise argparse.ArgumentTypeError(f"{name} must be > 0, got {s}")
        return v

    return conv


def _progress(desc: str, total: int = 1000):
    from tqdm import tqdm

    bar = tqdm(
        total=total,
        desc=desc,
        unit="‰",
        leave=False,
        disable=None,
        file=sys.stderr,
        bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}",
    )

    def update(fraction: float) -> None:
        bar.n = int(round(fraction * total))
        bar.refresh()

    return bar, update


def _material_file(args: argparse.Namespace):
    """The --material FILE.toml of a command, read once (None when --material is not a file)."""
    from softgrasp.io.materialfile import is_material_file, read_material_file

    spec = getattr(args, "material", None)
    if spec is None or not is_material_file(spec):
        return None
    if getattr(args, "_material_file", None) is None:
        args._material_file = read_material_file(spec)
    return args._material_file


def _contact(args: argparse.Namespace, mu: float | None, **kw):
    """Contact parameters: the defaults, a material file's [contact] over them, then --mu if given."""
    from softgrasp.io.options import contact_params

    return contact_params(_material_file(args), mu, **kw)


def _plan_contact(args: argparse.Namespace, mu_given: float | None):
    """The plan's contact parameters; mu from --mu, else the material file, else --config or 0.8."""
    mf = _material_file(args)
    from_file = mf is not None and "mu" in mf.contact
    return _contact(args, mu_given if mu_given is not None or from_file else args.mu)


def _load(args: argparse.Namespace):
    from softgrasp.io.options import load_body

    return load_body(
        args.object, args.mesh_size, args.material, reorient=args.reorient, mfile=_material_file(args)
    )


def _cmd_compress(args: argparse.Namespace) -> int:
    from softgrasp.experiments.compression import compression_test
    from softgrasp.io.atomic import write_json, write_text
    from softgrasp.viz.plots import plot_stress_strain

    t0 = time.perf_counter()
    body = _load(args)
    out = Path(args.out or "softgrasp-out/compress")
    print(f"object   {body.mesh.summary()}, mass {body.total_mass * 1e3:.1f} g")
    m = body.material
    print(f"material {m.name}: E = {m.E / 1e3:.4g} kPa, nu = {m.nu:g}, density = {m.density:.4g} kg/m^3")
    bar, update = _progress("compress")
    try:
        res = compression_test(
            body, strain=args.strain, steps=args.steps, plate_friction=args.plate_friction, progress=update
        )
    finally:
        bar.close()
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["displacement_m", "force_N", "strain", "stress_Pa"])
    for row in zip(res.displacement_m, res.force_N, res.strain, res.stress_Pa, strict=True):
        w.writerow([f"{v:.9g}" for v in row])
    write_text(out / "compress.csv", buf.getvalue())
    write_json(
        out / "compress.json",
        {
            "schema": "softgrasp.compress/1",
            "object": {"name": args.object, **body.describe()},
            "parameters": {
                "strain": args.strain,
                "steps": args.steps,
                "plate_friction": args.plate_friction,
                "mesh_size_m": args.mesh_size,
                "height_m": res.height_m,
                "area_m2": res.area_m2,
                "fit_strain": res.fit_strain,
                "solver": "static Newton, sparse Jacobian, energy line search",
            },
            "apparent_E_Pa": res.apparent_E_Pa,
            "apparent_nu": res.apparent_nu,
            "peak_force_N": float(res.force_N.max()),
            "peak_stress_Pa": float(res.stress_Pa.max()),
            "newton_iterations": res.newton_iterations.tolist(),
            "wall_time_s": time.perf_counter() - t0,
        },
    )
    plot_stress_strain(
        out / "compress.png",
        res.strain,
        res.stress_Pa,
        apparent_E_Pa=res.apparent_E_Pa,
        title=f"Compression of the {args.object} ({m.name})",
        linear_E_Pa=m.E,
    )
    print(f"height {res.height_m * 1e3:.1f} mm, area {res.area_m2 * 1e6:.0f} mm^2, strain {args.strain:.0%}")
    print(
        f"apparent E {res.apparent_E_Pa / 1e3:.4g} kPa (initial slope), peak force {res.force_N.max():.3g} N"
    )
    print(f"wrote {out}/compress.csv, compress.json, compress.png ({time.perf_counter() - t0:.1f} s)")
    return 0


def _cmd_indent(args: argparse.Namespace) -> int:
    from softgrasp.experiments.indentation import (
        default_steps,
        indentation_test,
        mean_abs_force_error,
        read_force_curve,
    )
    from softgrasp.io.atomic import write_json, write_text
    from softgrasp.viz.plots import plot_force_penetration

    t0 = time.perf_counter()
    if args.mu is not None and not args.mu >= 0:
        raise ConfigError(f"--mu must be >= 0, got {args.mu}")
    if args.steps is not None and not 1 <= args.steps <= 100_000:
        raise ConfigError(f"--steps must be an integer from 1 to 100000, got {args.steps}")
    params = _contact(args, args.mu, rule=args.rule)
    measured = read_force_curve(args.data, max_penetration=args.depth) if args.data else None
    body = _load(args)
    out = Path(args.out or "softgrasp-out/indent")
    steps = args.steps if args.steps is not None else default_steps(args.depth)
    print(f"object   {body.mesh.summary()}, mass {body.total_mass * 1e3:.1f} g")
    m = body.material
    print(f"material {m.name}: E = {m.E / 1e3:.4g} kPa, nu = {m.nu:g}, density = {m.density:.4g} kg/m^3")
    print(
        f"finger   R = {args.radius * 1e3:.3g} mm, depth {args.depth * 1e3:.3g} mm in {steps} increments, "
        f"mu = {params.mu:g}, {args.rule} rule"
    )
    bar, update = _progress("indent")
    try:
        res = indentation_test(
            body,
            depth=args.depth,
            radius=args.radius,
            speed=args.speed,
            steps=steps,
            params=params,
            progress=update,
        )
    finally:
        bar.close()
    error = mean_abs_force_error(res, *measured) if measured is not None else None
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["time_s", "penetration_m", "force_N", "normal_force_N", "tangential_force_N", "contacts"])
    cols = (res.time_s, res.penetration_m, res.force_N, res.normal_force_N, res.tangential_force_N)
    for *vals, n in zip(*cols, res.contacts, strict=True):
        w.writerow([*(f"{v:.9g}" for v in vals), int(n)])
    write_text(out / "indent.csv", buf.getvalue())
    report = {
        "schema": "softgrasp.indent/1",
        "object": {"name": args.object, **body.describe()},
        "parameters": {
            "depth_m": res.depth_m,
            "radius_m": args.radius,
            "speed_m_s": res.speed_m_s,
            "steps": steps,
            "increment_m": res.depth_m / steps,
            "mesh_size_m": args.mesh_size,
            "table_mu": res.table_mu,
            "point_m": res.point_m.tolist(),
            "point_shift_m": res.point_shift_m,
            "surface_z_m": res.surface_z_m,
            "first_contact_travel_m": res.first_contact_travel_m,
            "penetration": "fingertip travel since first detected contact with the settled object",
            "solver": "quasi-static: a static Newton solve per increment, after settling on the table",
        },
        "contact": params.describe(),
        "fingertip": res.fingertip.describe(),
        "K_N_m1.5": res.K_N_m1_5,
        "peak_force_N": res.peak_force_N,
        "force_at_depth_N": float(res.force_N[-1]),
        "contact_depth_m": res.contact_depth_m.tolist(),
        "newton_iterations": res.newton_iterations.tolist(),
        "split_increments": res.halvings,
    }
    if measured is not None:
        report["data_file"] = str(args.data)
        report["measured_points"] = int(measured[0].size)
        report["mean_abs_error_N"] = error
    report["wall_time_s"] = time.perf_counter() - t0
    write_json(out / "indent.json", report)
    title = f"Indentation of the {args.object} ({m.name}), R = {args.radius * 1e3:.3g} mm"
    plot_force_penetration(
        out / "indent.png",
        res.penetration_m,
        res.force_N,
        title=title,
        measured=measured,
        mean_abs_error_N=error,
    )
    if res.point_shift_m > 0:
        print(
            f"note: press point moved {res.point_shift_m * 1e6:.3g} um off a mesh vertex/edge, where the "
            "facet contact test cannot see the fingertip"
        )
    print(
        f"force at {res.depth_m * 1e3:.3g} mm: {res.force_N[-1]:.4g} N (peak {res.peak_force_N:.4g} N), "
        f"K = {res.K_N_m1_5:.4g} N/m^1.5, contact depth {res.contact_depth_m[-1] * 1e3:.3g} mm"
    )
    if measured is not None and error is not None:
        print(f"mean absolute force error vs {measured[0].size} measured points: {error:.3g} N")
    print(f"wrote {out}/indent.csv, indent.json, indent.png ({time.perf_counter() - t0:.1f} s)")
    return 0


def _plan_options(args: argparse.Namespace) -> argparse.Namespace:
    """Merge command-line options over a --config TOML file over the defaults."""
    conf: dict[str, object] = {}
    if args.config is not None:
        from softgrasp.io.tomlfile import read_toml

        raw = read_toml(args.config, "config file")
        conf = {k.replace("-", "_"): v for k, v in raw.items()}
        unknown = sorted(set(conf) - set(PLAN_DEFAULTS))
        if unknown:
            raise ConfigError(
                f"config file {args.config}: unknown key(s) {', '.join(unknown)}; "
                f"known: {', '.join(sorted(PLAN_DEFAULTS))}"
            )
    merged = {}
    for key, default in PLAN_DEFAULTS.items():
        cli = getattr(args, key, None)
        given = cli is not None and cli is not False  # (0.0 == False: test identity, not equality)
        value = cli if given else conf.get(key, default)
        if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if default is not None and not isinstance(value, type(default)):
            raise ConfigError(f"option {key} must be a {type(default).__name__}, got {value!r}")
        merged[key] = value
    if merged["solver"] not in ("quasistatic", "dynamic"):
        raise ConfigError(f"solver must be quasistatic or dynamic, got {merged['solver']!r}")
    return argparse.Namespace(**{**vars(args), **merged})


def _fit_summary(fit) -> str:
    """The fitted values of a calibration, one per line, for the console and the figure."""
    units = {"E_Pa": ("E", 1e-3, "kPa"), "gamma_N_s_m2": ("gamma", 1.0, "N s/m^2")}
    rows = []
    for name, p in fit.parameters.items():
        label, scale, unit = units.get(name, (name, 1.0, ""))
        sd = "" if p.stderr != p.stderr else f" +- {p.stderr * scale:.3g}"
        rows.append(f"{label:<19} {p.value * scale:.5g}{sd} {unit} ({p.status})".replace("  (", " ("))
    rows.append(f"rms residual        {fit.residual_rms_N:.3g} N ({fit.relative_rms:.2%} of the peak)")
    rows.append(f"mean |error|        {fit.mean_abs_error_N:.3g} N")
    return "\n".join(rows)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from softgrasp.physics.body import build_body
    from softgrasp.experiments.calibration import (
        fit_compression,
        fit_indentation,
        read_compression_data,
        read_indentation_data,
        specimen_geometry,
    )
    from softgrasp.model.material import Material
    from softgrasp.io.materialfile import write_material_file
    from softgrasp.io.atomic import write_json
    from softgrasp.viz.plots import plot_calibration

    t0 = time.perf_counter()
    if args.compression is None and args.indentation is None:
        raise ConfigError("give measured data to fit: --compression DATA.csv and/or --indentation DATA.csv")
    if args.nu is not None and not -1.0 < args.nu < 0.5:
        raise ConfigError(f"--nu must lie in (-1, 0.5), got {args.nu}")
    # The indentation file needs no specimen: it is checked before any meshing.
    ind_data = read_indentation_data(args.indentation) if args.indentation else None
    body = _load(args)
    mesh, material, mass = body.mesh, body.material, body.total_mass
    # The density goes into material.toml only when the user gave one: otherwise a built-in
    # object planned with the file keeps its own mass.
    mf = _material_file(args)
    given_density = (mf is not None and mf.material is not None and mf.material.density is not None) or (
        mf is None and args.material is not None and "density" in args.material
    )
    density = material.density if given_density else None
    out = Path(args.out or "softgrasp-out/calibrate")
    comp_data = None
    if args.compression:
        comp_data = read_compression_data(args.compression, *specimen_geometry(mesh))
    print(f"specimen {mesh.summary()}, mass {mass * 1e3:.1f} g")
    fits = {}
    figures: list[tuple[str, object, dict]] = []

    def bar(desc: str):
        b = tqdm(desc=desc, unit=" simulations", leave=False, disable=None, file=sys.stderr)

        def update(k: int) -> None:
            b.n = k
            b.refresh()

        return b, update

    if comp_data is not None:
        top = float(comp_data.displacement_m.max())
        print(
            f"compression: {len(comp_data.force_N)} points from {args.compression}, up to "
            f"{top * 1e3:.3g} mm ({top / comp_data.height_m:.0%})"
        )
        b, update = bar("fit compression")
        try:
            fitted, fit = fit_compression(
                mesh,
                comp_data,
                nu=args.nu if args.nu is not None else material.nu,
                mass=mass,
                law=args.law,
                plate_friction=args.plate_friction,
                steps=args.steps,
                progress=update,
            )
        finally:
            b.close()
        material = Material(fitted.E, fitted.nu, density, fitted.law, name="calibrated")
        fits["compression"] = fit
        lateral = (fit.lateral_measured, fit.lateral_fitted) if fit.lateral_measured is not None else None
        figures.append(
            (
                "compression_fit.png",
                fit,
                dict(xlabel="displacement", lateral=lateral, title="Compression fit"),
            )
        )
        print(_fit_summary(fit))
    else:
        material = Material(material.E, material.nu, density, material.law, name=material.name)
    contact = None
    if ind_data is not None:
        print(f"indentation: {len(ind_data.force_N)} points from {args.indentation}")
        ibody = build_body(mesh, material, mass=mass)
        b, update = bar("fit indentation")
        try:
            contact, ifit = fit_indentation(
                ibody,
                ind_data,
                params=_contact(args, args.mu),
                radius=args.radius,
                speed=args.speed,
                progress=update,
            )
        finally:
            b.close()
        fits["indentation"] = ifit
        title = f"Indentation fit, R = {args.radius * 1e3:.3g} mm"
        figures.append(("indentation_fit.png", ifit, dict(xlabel="penetration", title=title)))
        print(_fit_summary(ifit))
    for fit in fits.values():
        for note in fit.notes:
            print(f"note: {note}")
    doc: dict[str, object] = {
        "schema": "softgrasp.calibration/1",
        "specimen": {"name": args.object, **body.describe()},
        "E_Pa": material.E,
        "nu": material.nu,
        "law": material.law.describe(),
        "residual": {k: {"rms_N": f.residual_rms_N, "relative_rms": f.relative_rms} for k, f in fits.items()},
    }
    if "indentation" in fits:
        doc["mean_abs_error_N"] = fits["indentation"].mean_abs_error_N
        assert contact is not None
        doc["contact"] = contact.describe()
    details = {
        k: {
            "data": str(getattr(args, k)),
            "points": len(f.x),
            "converged": f.converged,
            "parameters": {n: p.describe() for n, p in f.parameters.items()},
            "correlation": f.correlation,
            "residual_rms_N": f.residual_rms_N,
            "mean_abs_error_N": f.mean_abs_error_N,
            "relative_rms": f.relative_rms,
            "simulations": f.simulations,
            "wall_time_s": f.wall_time_s,
            "notes": list(f.notes),
        }
        for k, f in fits.items()
    }
    if comp_data is not None:
        details["compression"].update(
            {
                "plate_friction": args.plate_friction,
                "height_m": comp_data.height_m,
                "area_m2": comp_data.area_m2,
            }
        )
    if ind_data is not None:
        details["indentation"].update({"radius_m": args.radius, "speed_m_s": args.speed})
    doc["fits"] = details
    # Every output after every fit: a failed fit leaves the folder as it was.
    for name, fit, kw in figures:
        source = Path(str(getattr(args, fit.kind))).name
        plot_calibration(
            out / name,
            fit.x,
            fit.measured,
            fit.fitted,
            xlabel=kw["xlabel"],
            title=f"{kw['title']} ({source})",
            summary=_fit_summary(fit),
            lateral=kw.get("lateral"),
        )
    write_material_file(
        out / "material.toml",
        material,
        contact,
        comment=f"softgrasp calibrate: {', '.join(f'{k} {getattr(args, k)}' for k in fits)}\n"
        "use with --material FILE in plan, indent, compress and execute",
    )
    doc["wall_time_s"] = time.perf_counter() - t0
    write_json(out / "calibration.json", doc)
    figs = ", ".join(name for name, _, _ in figures)
    print(f"wrote {out}/calibration.json, material.toml, {figs} ({time.perf_counter() - t0:.1f} s)")
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    from softgrasp.viz.view import write_view

    path = write_view(args.run_dir, args.out)
    print(f"wrote {path} (open it in a browser; it needs no network)")
    return 0


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from softgrasp.report.reproduce import reproduce

    out = Path(args.out or "softgrasp-out/reproduce")
    bar, update = _progress("reproduce")

    def progress(fraction: float, step: str) -> None:
        bar.set_description(f"reproduce: {step}")
        update(fraction)

    try:
        res = reproduce(out, quick=args.quick, progress=progress)
    finally:
        bar.close()
    for st in res.steps:
        extra = f": {st.message}" if st.message and st.status != "ok" else ""
        print(f"{st.status:>7}  {st.title} ({st.wall_time_s:.1f} s){extra}")
    print(f"wrote {res.report_md}, {res.report_html.name}, {res.data_json.name} ({res.wall_time_s:.1f} s)")
    return 1 if res.failed else 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    from softgrasp.sweep.engine import run_sweep
    from softgrasp.sweep.report import sweep_figures
    from softgrasp.sweep.spec import read_sweep, sweep_cases

    spec = read_sweep(args.sweep)
    cases = sweep_cases(spec)
    out = Path(args.out or "softgrasp-out/sweep")
    where = args.scheduler or f"a local Dask cluster of {args.workers} worker process(es)"
    print(
        f"sweep {args.sweep}: {len(cases)} cases ({spec.mode} over {', '.join(spec.varied)}) on {where}"
        + (", executing each plan" if spec.execute else "")
    )
    from tqdm import tqdm

    bar = tqdm(total=len(cases), desc="sweep", unit=" cases", leave=False, disable=None, file=sys.stderr)

    def progress(done: int, total: int) -> None:
        bar.n = done
        bar.refresh()

    try:
        res = run_sweep(
            spec,
            cases,
            out,
            scheduler=args.scheduler,
            workers=args.workers,
            resume=args.resume,
            progress=progress,
        )
    finally:
        bar.close()
    figures = sweep_figures(spec, res.rows, out)
    per_min = 60.0 * res.ran / res.wall_time_s if res.wall_time_s > 0 else float("nan")
    print(
        f"{len(res.rows)} cases: {len(res.rows) - res.failed} planned, {res.failed} failed"
        + (f" ({res.resumed} from the earlier run)" if res.resumed else "")
        + f"; {res.ran} run in {res.wall_time_s:.1f} s ({per_min:.1f} cases/min on {res.workers} workers)"
    )
    for r in res.rows:
        if r["status"] == "failed":
            print(f"  case {r['case']} failed: {r['error']}")
    names = ", ".join(["results.csv", "results.parquet", "sweep.json", *(f.name for f in figures)])
    print(f"wrote {out}/{names}")
    return 0


def _write_frames(path: Path, plan, facets) -> None:
    """The closing increments and the held state, for ``softgrasp view`` (SI units)."""
    import numpy as np

    from softgrasp.io.atomic import atomic_write

    fr = plan.frames
    assert fr is not None

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                travel=fr.travel,
                positions=fr.positions,
                centres=fr.centres,
                forces=fr.forces,
                held_positions=plan.positions,
                held_centres=plan.centres,
                held_forces=np.array([f.force for f in plan.fingers]),
                facets=np.asarray(facets, dtype=np.int64),
                fingertip_radius=np.float64(plan.config.fingertip_radius),
                finger_names=np.array([f.name for f in plan.fingers]),
            )

    atomic_write(path, write)


def _cmd_plan(args: argparse.Namespace) -> int:
    from softgrasp.viz.worker import FigureWorker

    # Matplotlib loads in a child process meanwhile; it then draws the figures while the other
    # files are written.
    with FigureWorker() as figures:
        return _plan(args, figures)


def _plan(args: argparse.Namespace, figures: FigureWorker) -> int:
    from softgrasp.cli.warm import warm_up_in_background

    warm_up_in_background()  # the compiled kernels load while the object is meshed
    import numpy as np

    from softgrasp.io.options import plan_config
    from softgrasp.grasp.planner import plan_grasp
    from softgrasp.io.plan_document import HISTORY_HEADER, hand_polylines, history_rows, plan_document, plan_table
    from softgrasp.model.mesh.io import save_mesh
    from softgrasp.model.mesh.tetmesh import TetMesh
    from softgrasp.io.atomic import write_json, write_text

    t0 = time.perf_counter()
    mu_given = args.mu
    args = _plan_options(args)
    body = _load(args)
    out = Path(str(args.out))
    m = body.material
    print(f"object   {body.mesh.summary()}, mass {body.total_mass * 1e3:.1f} g")
    print(f"material {m.name}: E = {m.E / 1e3:.4g} kPa, nu = {m.nu:g}")
    config = plan_config(vars(args), _plan_contact(args, mu_given))
    uncertain = _uncertain(args, body, config.contact.mu)
    bar, update = _progress("plan")
    try:
        plan = plan_grasp(body, config, progress=update)
    finally:
        bar.close()
    doc = plan_document(
        plan, body, Path(str(args.object)).stem if "." in str(args.object) else str(args.object)
    )
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(HISTORY_HEADER)
    for row in history_rows(plan):
        w.writerow([f"{v:.9g}" if isinstance(v, float) else v for v in row])
    names = [f.name for f in plan.fingers]
    figures.draw(
        "plot_plan_forces",
        np.arange(1.0, plan.increments + 1.0),
        plan.force_norm,
        names,
        out / "forces.png",
        setpoints=[f.force_norm for f in plan.fingers],
    )
    figures.draw(
        "plot_plan_force_penetration", plan.penetration, plan.force_norm, names, out / "force_penetration.png"
    )
    figures.draw(
        "plot_grasp_3d",
        plan.positions,
        body.mesh.facets,
        plan.centres,
        np.full(3, config.fingertip_radius),
        np.array([f.force for f in plan.fingers]),
        plan.contact_points,
        names,
        out / "grasp.png",
        title=f"Held grasp of the {doc['object']['name']} ({m.name}), mu = {config.contact.mu:g}",
        weight=(plan.com, body.total_mass * float(abs(body.gravity[2]))),
        links=hand_polylines(plan),
    )
    write_text(out / "history.csv", buf.getvalue())
    _write_frames(out / "frames.npz", plan, body.mesh.facets)
    # The unloaded object as the plan placed it on the table: what `execute` rebuilds.
    save_mesh(TetMesh(plan.placed, body.mesh.tets, name=body.mesh.name), out / "object.vtu")
    doc["object"]["mesh_file"] = "object.vtu"
    doc["wall_time_s"] = time.perf_counter() - t0
    _remove_robust_outputs(out)  # an earlier robust run's, which no longer belong to this plan
    write_json(out / "plan.json", doc)
    figures.finish()
    print(plan_table(plan))
    eq = doc["equilibrium"]
    print(
        f"held: residual {eq['force_residual_N']:.2e} N, {eq['torque_residual_Nm']:.2e} N m; "
        f"friction margin {eq['friction_margin']:.2f}; centre of mass moved "
        f"{plan.com_drift * 1e3:.2f} mm in {plan.hold_time:g} s"
    )
    for travel, result in plan.hold_checks[:-1]:
        print(f"not held at {travel * 1e3:.2f} mm of travel: {result}; closed further")
    if uncertain:
        robust = _robust(args, config, plan, doc, uncertain, out)
        return _robust_summary(robust, out, time.perf_counter() - t0)
    if eq["friction_margin"] < 0.05:
        print(
            f"note: held at the friction limit (margin {eq['friction_margin']:.1%}): the least squeeze "
            "that holds; for a real hand, whose forces and friction vary, plan with --safety-factor 1.5 "
            "or more"
        )
    print(
        f"wrote {out}/plan.json, history.csv, object.vtu, frames.npz, forces.png, force_penetration.png, "
        "grasp.png "
        f"({plan.increments} increments, {time.perf_counter() - t0:.1f} s)"
    )
    return 0


#: What ``plan --uncertain`` writes besides the plan.
ROBUST_OUTPUTS = ("robust.json", "robust.png", "robust", ".robust-partial")


def _remove_robust_outputs(out: Path) -> None:
    import shutil

    for name in ROBUST_OUTPUTS:
        path = out / name
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        elif path.exists():
            path.unlink()


def _uncertain(args: argparse.Namespace, body, mu: float) -> list:
    """The --uncertain parameters of ``plan`` (checked before the nominal plan runs)."""
    if not args.uncertain:
        for flag in ("quantile", "scheduler", "samples", "seed", "workers"):
            if getattr(args, flag) is not None:
                raise ConfigError(f"--{flag} applies to robust set-points: give --uncertain NAME=RANGE too")
        return []
    args.samples = 64 if args.samples is None else args.samples
    args.seed = 0 if args.seed is None else args.seed
    args.workers = 2 if args.workers is None else args.workers
    from softgrasp.sweep.robust import nominal_values, parse_uncertain

    nominal = nominal_values(body, mu)
    found = [parse_uncertain(text, nominal) for text in args.uncertain]
    names = [u.name for u in found]
    if len(set(names)) != len(names):
        raise ConfigError(f"--uncertain gives a parameter twice: {', '.join(names)}")
    if not 2 <= args.samples <= 100_000:
        raise ConfigError(f"--samples must be from 2 to 100000, got {args.samples}")
    if args.quantile is not None and not 0 < args.quantile < 1:
        raise ConfigError(f"--quantile must lie between 0 and 1 (e.g. 0.9), got {args.quantile}")
    if not 1 <= args.workers <= 256:
        raise ConfigError(f"--workers must be from 1 to 256, got {args.workers}")
    return found


def _robust(args: argparse.Namespace, config, plan, doc: dict, uncertain: list, out: Path):
    """Robust set-points around the nominal ``plan`` (``--uncertain``), whose outputs are already
    written: every sample closes from the contacts of ``out/plan.json``; the stages' tables go to
    ``out/robust`` (built aside and moved there whole); then ``plan.json`` is written again with
    the robust set-points, the nominal ones kept beside them."""
    import shutil
    from dataclasses import replace

    from tqdm import tqdm

    from softgrasp.io.options import PLAN_DEFAULTS
    from softgrasp.sweep.robust import robust_setpoints
    from softgrasp.io.atomic import write_json

    options = {k: vars(args)[k] for k in PLAN_DEFAULTS if k not in ("out", "grasp")}
    options["mu"] = config.contact.mu
    for key in ("object", "material", "hand"):  # files named for the workers wherever they run
        if isinstance(options[key], str) and Path(options[key]).is_file():
            options[key] = str(Path(options[key]).resolve())
    work = out / ".robust-partial"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    bars: dict[str, object] = {}

    def progress(stage: str, done: int, total: int) -> None:
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
        res = robust_setpoints(
            options,
            (out / "plan.json").resolve(),
            [f.normal_force for f in plan.fingers],
            uncertain,
            work,
            samples=args.samples,
            seed=args.seed,
            quantile=args.quantile,
            workers=args.workers,
            scheduler=args.scheduler,
            progress=progress,
        )
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    finally:
        for b in bars.values():
            b.close()  # type: ignore[attr-defined]
    final = out / "robust"
    shutil.rmtree(final, ignore_errors=True)
    work.rename(final)
    res = replace(res, stages={k: str(final / Path(v).name) for k, v in res.stages.items()})
    summary = res.describe()
    per_sample = summary.pop("per_sample")
    for j, f in enumerate(doc["fingers"]):
        f["nominal_normal_force_N"] = f["normal_force_N"]
        f["normal_force_N"] = float(res.setpoints[j])
    doc["setpoints"] = "robust" if res.achieved else "robust (goal not met)"
    doc["robust"] = {
        **summary,
        "note": "each finger's normal_force_N is the robust set-point; its other fields (force, "
        "penetration, final position) and the equilibrium are the nominal plan's held state",
    }
    write_json(out / "robust.json", {"schema": "softgrasp.robust/1", **summary, "per_sample": per_sample})
    write_json(out / "plan.json", doc)
    return res


def _robust_summary(res, out: Path, wall: float) -> int:
    """Print the robust set-points, their check and the drivers; write robust.png."""
    import numpy as np

    from softgrasp.viz.plots import plot_robust

    fig = plot_robust(
        out / "robust.png",
        {u.name: np.array([s[u.name] for s in res.samples]) for u in res.uncertain},
        res.required.sum(axis=1),
        res.nominal_held,
        robust_total=float(res.setpoints.sum()),
        nominal_total=float(res.nominal.sum()),
        title=f"Robust set-points over {len(res.samples)} samples"
        + ("" if res.quantile is None else f" ({res.quantile:.0%} to hold)"),
    )
    print("finger    nominal N   robust N   samples need N (median..max)")
    for j, name in enumerate(("thumb", "first", "middle")):
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
        f"wrote {out}/plan.json (robust set-points), robust.json, {fig.name}, robust/ (each stage's table), "
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


def _execute_material(args: argparse.Namespace, plan):
    """The plan with the object's material and fingertip friction of --material FILE.toml over it
    (the hand then grasps an object that differs from the one planned for; mass as planned)."""
    from dataclasses import replace

    from softgrasp.io.materialfile import is_material_file

    if args.material is None:
        return plan
    if not is_material_file(args.material):
        raise ConfigError(f"execute --material takes a material file (.toml), got {args.material!r}")
    mf = _material_file(args)
    changes: dict[str, float] = {}
    if mf.material is not None:
        changes.update(E=mf.material.E, nu=mf.material.nu)
    if "mu" in mf.contact:
        changes["mu"] = float(mf.contact["mu"])  # type: ignore[arg-type]
    if changes:
        print("object as in " + args.material + ": " + ", ".join(f"{k} = {v:g}" for k, v in changes.items()))
    return replace(plan, **changes)


def _cmd_execute(args: argparse.Namespace) -> int:
    import numpy as np

    from softgrasp.execution.controller import PHASES, ExecuteConfig, closing_lines, execute_plan
    from softgrasp.io.planfile import load_plan_file
    from softgrasp.model.mesh.io import load_mesh
    from softgrasp.io.atomic import write_json, write_text
    from softgrasp.viz.plots import EXECUTION_FRAME_TITLES, plot_execution_forces, plot_execution_frame

    t0 = time.perf_counter()
    if not (np.isfinite(args.scale) and args.scale > 0):
        raise ConfigError(f"--scale must be a number > 0, got {args.scale}")
    if not (np.isfinite(args.lift) and args.lift > 0):
        raise ConfigError(f"--lift must be a height > 0 m, got {args.lift}")
    plan = load_plan_file(args.plan)
    plan = _execute_material(args, plan)
    out = Path(str(args.out))
    from softgrasp.execution.mujoco.hand import MujocoHand

    hand = MujocoHand.from_plan(plan)
    facets = load_mesh(plan.mesh_file).facets
    lines = closing_lines(plan, args.scale)
    cfg = ExecuteConfig(lift=float(args.lift))
    names = [f.name for f in plan.fingers]
    print(
        f"executing {args.plan} on {args.backend}: set-points "
        + ", ".join(f"{n} {lines[n].setpoint:.3f} N" for n in names)
        + (f" (x {args.scale:g})" if args.scale != 1 else "")
    )
    frames: dict[str, tuple] = {}

    def snapshot(event: str) -> None:
        frames[event] = hand.snapshot(names)

    bar, update = _progress("execute")
    try:
        res = execute_plan(
            hand, lines, cfg, palm_to_world=hand.palm_to_world, progress=update, on_event=snapshot
        )
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    ser = res.series
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    head = ["t_s", "phase", "base_rise_m", "com_x_m", "com_y_m", "com_z_m"]
    head += [f"{n}_normal_force_N" for n in names] + [f"{n}_travel_m" for n in names]
    w.writerow(head)
    for k in range(len(ser["t"])):
        row = [ser["t"][k], PHASES[int(ser["phase"][k])], ser["base_z"][k], *ser["com"][k]]
        row += list(ser["force"][k]) + list(ser["travel"][k])
        w.writerow([f"{v:.9g}" if isinstance(v, float | np.floating) else v for v in row])
    phases = [(p, res.events[p]) for p in PHASES if p in res.events]
    plot_execution_forces(
        ser["t"],
        ser["force"],
        [lines[n].setpoint for n in names],
        names,
        out / "execute_forces.png",
        phases=phases,
        tolerance=cfg.tolerance,
    )
    pictures = []
    for event in EXECUTION_FRAME_TITLES:
        if event in frames:
            name = f"frame_{event}.png"
            plot_execution_frame(out / name, frames[event], facets, names, plan.fingertip_radius, event)
            pictures.append(name)
    sim = float(ser["t"][-1]) if len(ser["t"]) else 0.0
    doc = {
        "schema": "softgrasp.execute/1",
        "plan": str(Path(args.plan).resolve()),
        "backend": args.backend,
        "scale": args.scale,
        "object_material": {
            "file": args.material,
            "E_Pa": plan.E,
            "nu": plan.nu,
            "mu": plan.mu,
        },
        "parameters": {**cfg.describe(), "mujoco_timestep_s": float(hand.scene.model.opt.timestep)},
        **res.describe(),
        "simulated_time_s": sim,
        "wall_time_s": wall,
        "realtime_factor": sim / wall if wall > 0 else None,
    }
    write_text(out / "execute.csv", buf.getvalue())
    write_json(out / "execute.json", doc)
    print("finger    set-point N  measured N  error %   held N")
    for fd in doc["fingers"]:
        print(
            f"{fd['name']:<9}{fd['setpoint_N']:>12.3f}{fd['measured_N']:>12.3f}"
            f"{100 * fd['error_N'] / fd['setpoint_N']:>9.1f}{fd['held_N']:>9.3f}"
        )
    state = "DROPPED" if res.dropped else "lifted"
    print(
        f"{state}: object rose {res.rise * 1e3:.1f} mm of {cfg.lift * 1e3:.0f} mm; slip "
        f"{res.slip * 1e3:.2f} mm; set-points {'reached' if res.reached else 'NOT reached'} within "
        f"{cfg.tolerance:.0%}; {sim:.2f} s simulated in {wall:.1f} s"
    )
    print(f"wrote {out}/execute.json, execute.csv, execute_forces.png, {', '.join(pictures)}")
    if res.dropped:
        print(
            "softgrasp: the object dropped: raise the set-points (plan with --safety-factor)", file=sys.stderr
        )
        return 1
    return 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--object",
        default="sphere",
        help="built-in object (cube, sphere), a shape (box:WxDxH, cylinder:DxH, ball:R; metres) "
        "or a mesh file (.msh .vtk .vtu .stl .obj ..., metres)",
    )
    p.add_argument(
        "--material",
        default=None,
        help="preset (foam, rubber) or E=..,nu=..,density=.. [Pa, -, kg/m^3]; default: the object's",
    )
    p.add_argument(
        "--mesh-size",
        type=_positive("--mesh-size"),
        default=None,
        metavar="M",
        help="target element size [m]",
    )
    p.add_argument(
        "--reorient", action="store_true", help="flip inverted tets of a mesh file instead of refusing it"
    )
    p.add_argument("--out", default=None, metavar="DIR", help="output folder")


def build_parser() -> argparse.ArgumentParser:
    """The ``softgrasp`` argument parser."""
    p = _Parser(prog="softgrasp", description="Grasp planning for soft objects (SI units; lengths in m).")
    p.add_argument("--version", action="version", version=f"softgrasp {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks of internal errors")
    p.add_argument(
        "--verbose",
        action="store_true",
        help="print the static solver's progress to stderr (every Newton iteration, friction pass "
        "and split load increment)",
    )
    sub = p.add_subparsers(dest="command", parser_class=_Parser)
    c = sub.add_parser("compress", help="compression test between rigid plates (paper Fig. 8-9)")
    _common(c)
    c.add_argument(
        "--strain", type=_positive("--strain"), default=0.3, help="final compressive strain (default 0.3)"
    )
    c.add_argument("--steps", type=int, default=30, help="load increments (default 30)")
    c.add_argument(
        "--plate-friction",
        type=float,
        default=0.5,
        help="plate friction coefficient (default 0.5, rubber on steel platens; faces stick at rest). "
        "0 is a lubricated test, whose free sliding and rolling only weak tethers hold",
    )
    c.set_defaults(func=_cmd_compress)
    i = sub.add_parser("indent", help="one fingertip pressed into the object (paper Fig. 10-11)")
    _common(i)
    i.set_defaults(object="cube", func=_cmd_indent)
    for action in i._actions:  # the shared options, with this command's defaults
        if action.dest == "object":
            action.help = f"{action.help} (default: cube, the paper's foam cube)"
        elif action.dest == "out":
            action.help = f"{action.help} (default: softgrasp-out/indent)"
    i.add_argument(
        "--depth",
        type=_positive("--depth"),
        default=0.005,
        help="penetration beyond first contact [m] (default 0.005)",
    )
    i.add_argument(
        "--radius", type=_positive("--radius"), default=0.008, help="fingertip radius [m] (default 0.008)"
    )
    i.add_argument(
        "--speed", type=_positive("--speed"), default=0.005, help="fingertip speed [m/s] (default 0.005)"
    )
    i.add_argument(
        "--steps", type=int, default=None, metavar="N", help="load increments (default: ~0.25 mm each, >= 10)"
    )
    i.add_argument(
        "--mu",
        type=float,
        default=None,
        help="fingertip friction coefficient (default 0.8, or the material file's)",
    )
    i.add_argument(
        "--rule",
        choices=("patch", "facet"),
        default="patch",
        help="force rule over touched facets (default patch; facet is the paper's literal rule, "
        "whose force jumps as facets enter contact, so static solves may fail)",
    )
    i.add_argument(
        "--data",
        default=None,
        metavar="FILE",
        help="measured CSV with a header: penetration_m (or penetration_mm) and force_N; "
        "penetrations must lie within 0..--depth; overlaid and compared (mean absolute error)",
    )
    pl = sub.add_parser("plan", help="plan a three-finger grasp and its force set-points (paper Sec. 2, 4.3)")
    _common(pl)
    pl.set_defaults(object=None, func=_cmd_plan)
    for action in pl._actions:
        if action.dest == "object":
            action.help = f"{action.help} (default: sphere, the paper's rubber sphere)"
        elif action.dest == "out":
            action.help = f"{action.help} (default: softgrasp-out/plan)"
    pl.add_argument(
        "--mu",
        type=float,
        default=None,
        help="fingertip friction coefficient (default 0.8); wins over a --material file's, which wins "
        "over --config's",
    )
    pl.add_argument(
        "--fingertip-radius",
        type=_positive("--fingertip-radius"),
        default=None,
        help="fingertip radius [m] (default 0.008)",
    )
    pl.add_argument(
        "--step", type=_positive("--step"), default=None, help="closing increment [m] (default 0.0005)"
    )
    pl.add_argument(
        "--solver",
        choices=("quasistatic", "dynamic"),
        default=None,
        help="rest per increment by static Newton (default) or the paper's explicit Runge-Kutta",
    )
    pl.add_argument(
        "--safety-factor",
        type=float,
        default=None,
        help="the grasp test must hold this multiple of the weight (default 1)",
    )
    pl.add_argument(
        "--hold-time", type=float, default=None, help="simulated holding time of the check [s] (default 1)"
    )
    pl.add_argument(
        "--max-squeeze",
        type=float,
        default=None,
        help="largest finger travel past first contact, fraction of its reach (default 0.5)",
    )
    pl.add_argument(
        "--refine",
        type=int,
        default=None,
        help="bisections of the last step for the smallest holding squeeze (default 3: step / 8)",
    )
    pl.add_argument(
        "--hand",
        default=None,
        metavar="URDF",
        help="the hand: a URDF file (fingertip links th_tip, ff_tip, mf_tip), 'shadow_like' (default, "
        "packaged) or 'none' (free fingertips, no reachability check)",
    )
    pl.add_argument(
        "--grasp",
        default=None,
        metavar="PLAN.json",
        help="close from the initial grasp of an earlier plan (same object and mesh) instead of searching "
        "for one: the same contacts and closing lines for another material or friction",
    )
    pl.add_argument("--config", default=None, metavar="FILE.toml", help="TOML file with any of these options")
    rb = pl.add_argument_group(
        "robust set-points",
        "plan for uncertain parameters: the set-points that hold the object for every sampled parameter set",
    )
    rb.add_argument(
        "--uncertain",
        action="append",
        default=[],
        metavar="NAME=RANGE",
        help="an uncertain parameter (mu, E, nu, density, mass, a2, a3) and its range: LOW..HIGH (SI), "
        "±P%% of the nominal value, or ±D; repeat for several "
        "(e.g. --uncertain mu=0.4..0.8 --uncertain E=±20%%)",
    )
    rb.add_argument(
        "--samples", type=int, default=None, help="parameter sets sampled over the ranges (default 64)"
    )
    rb.add_argument(
        "--quantile",
        type=float,
        default=None,
        help="hold this share of the samples (e.g. 0.9) instead of every one",
    )
    rb.add_argument("--seed", type=int, default=None, help="seed of the samples' draw (default 0)")
    rb.add_argument("--workers", type=int, default=None, help="local Dask worker processes (default 2)")
    rb.add_argument(
        "--scheduler", default=None, metavar="ADDRESS", help="a running Dask scheduler (tcp://host:port)"
    )

    ca = sub.add_parser(
        "calibrate", help="fit the material (compression) and contact law (indentation) to measurements"
    )
    _common(ca)
    ca.set_defaults(object="cube")
    ca.add_argument(
        "--compression",
        default=None,
        metavar="DATA.csv",
        help="compression curve: displacement_m|displacement_mm,force_N or strain,stress_Pa|_kPa|_MPa; "
        "optional lateral_strain (then nu is fitted too)",
    )
    ca.add_argument(
        "--indentation",
        default=None,
        metavar="DATA.csv",
        help="force-penetration curve: penetration_m|penetration_mm,force_N (optional tangential_force_N)",
    )
    ca.add_argument(
        "--nu", type=float, default=None, help="Poisson's ratio when not fitted (default: the material's)"
    )
    ca.add_argument(
        "--law",
        choices=("polynomial", "linear"),
        default="polynomial",
        help="spring law to fit (default polynomial)",
    )
    ca.add_argument(
        "--plate-friction", type=float, default=0.5, help="friction of the compression platens (default 0.5)"
    )
    ca.add_argument(
        "--steps", type=int, default=16, help="increments of each simulated compression (default 16)"
    )
    ca.add_argument(
        "--radius", type=_positive("--radius"), default=0.008, help="fingertip radius [m] (default 0.008)"
    )
    ca.add_argument(
        "--speed", type=_positive("--speed"), default=0.005, help="indentation speed [m/s] (default 0.005)"
    )
    ca.add_argument(
        "--mu",
        type=float,
        default=None,
        help="fingertip friction coefficient (default 0.8, or the material file's); fitted instead when "
        "the indentation data have tangential_force_N",
    )
    ca.set_defaults(func=_cmd_calibrate)

    vw = sub.add_parser(
        "view", help="write an interactive 3-D page of a plan run (closing increments, forces)"
    )
    vw.add_argument("run_dir", metavar="RUN_DIR", help="a folder written by softgrasp plan --out")
    vw.add_argument("--out", default=None, metavar="FILE.html", help="the page (default RUN_DIR/view.html)")
    vw.set_defaults(func=_cmd_view)
    rp = sub.add_parser("reproduce", help="run the paper's experiments end to end and write a report")
    rp.add_argument(
        "--out", default=None, metavar="DIR", help="output folder (default softgrasp-out/reproduce)"
    )
    rp.add_argument(
        "--quick", action="store_true", help="coarse meshes: the whole run in well under 2 minutes"
    )
    rp.set_defaults(func=_cmd_reproduce)

    sw = sub.add_parser("sweep", help="plan many cases (grid or random over any plan option) on Dask")
    sw.add_argument("sweep", metavar="SWEEP.toml", help="the sweep: [sweep], [base], [grid] or [random]")
    sw.add_argument(
        "--scheduler", default=None, metavar="ADDRESS", help="a running Dask scheduler (tcp://host:port)"
    )
    sw.add_argument("--workers", type=int, default=2, help="local worker processes (default 2)")
    sw.add_argument("--out", default=None, metavar="DIR", help="output folder (default softgrasp-out/sweep)")
    sw.add_argument("--resume", action="store_true", help="keep the finished rows in DIR, run the rest")
    sw.set_defaults(func=_cmd_sweep)

    ex = sub.add_parser("execute", help="execute a plan under force control on a simulated hand and lift")
    ex.add_argument("plan", metavar="PLAN.json", help="a plan written by softgrasp plan")
    ex.add_argument("--backend", choices=("mujoco",), default="mujoco", help="the hand (default: mujoco)")
    ex.add_argument("--lift", type=float, default=0.10, help="lift height [m] (default 0.10)")
    ex.add_argument("--scale", type=float, default=1.0, help="multiply the set-points (default 1)")
    ex.add_argument(
        "--material",
        default=None,
        metavar="FILE.toml",
        help="grasp an object of this material (and fingertip mu) instead of the planned one",
    )
    ex.add_argument(
        "--out", default="softgrasp-out/execute", help="output directory (default softgrasp-out/execute)"
    )
    ex.add_argument("--debug", action="store_true", help="show tracebacks of internal errors")
    ex.set_defaults(func=_cmd_execute)
    return p


def _log_progress() -> None:
    """The solvers' DEBUG records (:mod:`softgrasp.sim.static`) to stderr, one line each."""
    import logging

    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("softgrasp: %(message)s"))
    log = logging.getLogger("softgrasp")
    log.addHandler(handler)
    log.setLevel(logging.DEBUG)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``softgrasp`` command."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    if getattr(args, "verbose", False):
        _log_progress()
    try:
        if getattr(args, "plate_friction", 0.0) < 0:
            raise ConfigError(f"--plate-friction must be >= 0, got {args.plate_friction}")
        return int(args.func(args))
    except SoftgraspError as exc:
        print(f"softgrasp: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("softgrasp: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug: keep it to one line unless asked
        if args.debug:
            raise
        print(
            f"softgrasp: internal error: {type(exc).__name__}: {exc} (rerun with --debug for details)",
            file=sys.stderr,
        )
        return 3

