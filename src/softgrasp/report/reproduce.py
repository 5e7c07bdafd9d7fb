"""The paper's experiments end to end, in one report (``softgrasp reproduce``).

:func:`reproduce` runs, through softgrasp's own library functions:

1. the compression of the foam cube and of the rubber sphere between rigid plates (paper Sec. 4.2,
   Figs. 8-9, Table 1): stress-strain curves and the identified E and nu next to Table 1's;
2. the one-finger indentation of the foam cube (Sec. 4.3.1, Fig. 11): the force-penetration curve,
   forces at a few depths and the fitted exponent of F ~ delta^n;
3. the three-finger grasp plan of the rubber sphere (Sec. 4.3.2, Table 2, Figs. 12-13, 15):
   set-points and penetrations next to Table 2;
4. that plan executed under force control on the simulated hand in MuJoCo, with the lift
   (Sec. 4.3.3): set-points reached, lift height, slip.

It writes into the output folder ``report.md`` (figures referenced by relative path from
``figures/``), ``report.html`` (the same report, self-contained: CSS inline, figures embedded as
base64 data URIs, nothing fetched from the network), ``reproduce.json`` (every number, keys with
their SI units) and ``grasp/plan.json`` + ``grasp/object.vtu`` (the plan, which ``softgrasp
execute`` also reads). Every file is written atomically.

A step that fails (``NotConverged``, ``InfeasibleGrasp``, any error) is recorded as failed with
its message and the run continues; the execution is *skipped*, with the reason, when MuJoCo
cannot be imported or there is no plan to execute. Nothing is tuned to match the paper: where
softgrasp's numbers differ from it, the report says so and why.
"""

from __future__ import annotations

import base64
import html
import math
import os
import platform
import re
import time
import traceback
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from softgrasp import __version__
from softgrasp.physics.body import build_body
from softgrasp.errors import ConfigError, SoftgraspError
from softgrasp.experiments.compression import CompressionResult, compression_test
from softgrasp.experiments.indentation import default_steps, indentation_test
from softgrasp.grasp.planner import PlanConfig, plan_grasp
from softgrasp.model.objects import OBJECTS, make_object
from softgrasp.io.atomic import write_json, write_text

__all__ = [
    "EXPERIMENTS",
    "PAPER_TABLE1",
    "PAPER_TABLE2",
    "ReproductionResult",
    "StepRecord",
    "reproduce",
]

#: The steps of a reproduction, in the order they run, with their titles.
EXPERIMENTS: dict[str, str] = {
    "compression_cube": "Compression of the foam cube",
    "compression_sphere": "Compression of the rubber sphere",
    "indentation_cube": "One-finger indentation of the foam cube",
    "grasp_sphere": "Three-finger grasp plan of the rubber sphere",
    "execution_sphere": "Execution of the grasp on the simulated hand (MuJoCo) and lift",
}

#: The paper's Table 1: identified Young's modulus [Pa] and Poisson's ratio of each object.
PAPER_TABLE1: dict[str, dict[str, float]] = {
    "cube": {"E_Pa": 4.9284e6, "nu": 0.39},
    "sphere": {"E_Pa": 0.0793e6, "nu": 0.45},
}

#: The paper's Table 2: penetration depth [m] and force [N] of each finger.
PAPER_TABLE2: dict[str, dict[str, float]] = {
    "thumb": {"penetration_m": 0.020, "force_N": 2.2},
    "first": {"penetration_m": 0.015, "force_N": 1.6},
    "middle": {"penetration_m": 0.012, "force_N": 1.3},
}

#: The reproduced paper.
PAPER_TITLE = "Model-based strategy for grasping 3D deformable objects using a multi-fingered robotic hand"
#: Exponent of the paper's contact law F = K delta^n (Eq. 9-11).
MODEL_EXPONENT = 1.5
#: Schema of ``reproduce.json``.
SCHEMA = "softgrasp.reproduce/1"
#: Relative cost of each step (for the progress fraction), measured on a 2-core machine.
_WEIGHTS = {
    "compression_cube": 1.5,
    "compression_sphere": 1.5,
    "indentation_cube": 1.5,
    "grasp_sphere": 3.0,
    "execution_sphere": 10.0,
    "report": 0.5,
}
#: Strain range of the Hertz fit of the sphere's compression.
_HERTZ_FIT_STRAIN = 0.10
#: Plate friction of each compression: the cube lubricated (uniaxial stress, for E and nu), the
#: rubber sphere on steel platens (a lubricated sphere is held sideways by weak tethers only).
_PLATE_FRICTION = {"cube": 0.0, "sphere": 0.5}
#: Plate contact stiffness per node relative to the node's own stiffness (compression_test's).
_PLATE_PENALTY = 50.0


@dataclass(frozen=True)
class _Settings:
    """Meshes and load schedules of one run (``quick`` or full)."""

    mesh_size_m: Mapping[str, float]
    compression_strain: float
    compression_steps: int
    indentation_depth_m: float

    @classmethod
    def of(cls, quick: bool) -> _Settings:
        if quick:
            # Coarse: 4 BCC cells per cube edge (285 nodes), a ~210-node sphere.
            return cls({"cube": 0.0125, "sphere": 0.025}, 0.3, 10, 0.003)
        return cls({k: OBJECTS[k].mesh_size for k in ("cube", "sphere")}, 0.3, 30, 0.005)


@dataclass(frozen=True)
class StepRecord:
    """What happened to one step.

    Attributes
    ----------
    name: key in :data:`EXPERIMENTS`.  title: its title in the report.
    status: ``"ok"``, ``"failed"`` or ``"skipped"``.
    wall_time_s: wall time of the step, its figures included [s].
    message: why it failed or was skipped (``""`` when it ran).
    figures: the PNG files it wrote (absolute paths).
    """

    name: str
    title: str
    status: str
    wall_time_s: float
    message: str = ""
    figures: tuple[Path, ...] = ()


@dataclass(frozen=True)
class ReproductionResult:
    """The outcome of :func:`reproduce`.

    Attributes
    ----------
    out: the output folder.  quick: whether the coarse settings were used.
    steps: one record per step that was asked for, in run order.
    report_md, report_html, data_json: the files written.
    wall_time_s: total wall time [s].
    document: the content of ``reproduce.json``.
    """

    out: Path
    quick: bool
    steps: tuple[StepRecord, ...]
    report_md: Path
    report_html: Path
    data_json: Path
    wall_time_s: float
    document: dict[str, Any] = field(repr=False)

    @property
    def failed(self) -> tuple[str, ...]:
        """Names of the steps that failed."""
        return tuple(s.name for s in self.steps if s.status == "failed")

    @property
    def skipped(self) -> tuple[str, ...]:
        """Names of the steps that were skipped."""
        return tuple(s.name for s in self.steps if s.status == "skipped")

    @property
    def ok(self) -> bool:
        """Whether no step failed (skipped steps do not count as failures)."""
        return not self.failed

    def step(self, name: str) -> StepRecord:
        """The record of step ``name``."""
        for s in self.steps:
            if s.name == name:
                return s
        raise KeyError(name)


class _Skipped(Exception):
    """A step that cannot run here (not an error of the step)."""


@dataclass
class _Context:
    out: Path
    settings: _Settings
    plan_file: Path | None = None
    plan_status: str = "was not run"


_Progress = Callable[[float], None]


# ---------------------------------------------------------------------- small helpers


def _finite(x: Any) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _jsonable(v: Any) -> Any:
    """``v`` with NumPy values, paths and non-finite floats made JSON-safe (NaN, inf -> None)."""
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, bool | np.bool_):
        return bool(v)
    if isinstance(v, int | np.integer):
        return int(v)
    if isinstance(v, float | np.floating):
        return _finite(v)
    if isinstance(v, Path):
        return str(v)
    return v


def _rel(a: float, b: float) -> float:
    """Relative difference of ``a`` from the reference ``b``."""
    return (a - b) / b


def _linear_solver() -> str:
    from softgrasp.linalg import pardiso
    method = os.environ.get("SOFTGRASP_LINSOLVE", "auto")
    if method != "auto":
        return f"SOFTGRASP_LINSOLVE={method}"
    return "MKL PARDISO" if pardiso.available() else "sparse LU / multigrid-preconditioned CG"


def _mesh_info(body, mesh_size: float) -> dict[str, Any]:
    return {
        "mesh_size_m": mesh_size,
        "nodes": body.mesh.n_nodes,
        "tets": body.mesh.n_tets,
        "facets": int(len(body.mesh.facets)),
        "extent_m": np.ptp(body.mesh.points, axis=0).tolist(),
        "mass_kg": body.total_mass,
    }


def _object(name: str, settings: _Settings):
    mesh, material, mass = make_object(name, settings.mesh_size_m[name])
    body = build_body(mesh, material, mass=mass)
    return body, {
        "name": name,
        "description": OBJECTS[name].description,
        **_mesh_info(body, settings.mesh_size_m[name]),
        "material": body.material.describe(),
        "network": body.calibration.describe(),
    }


def _power_fit(x: NDArray[np.float64], y: NDArray[np.float64]) -> float | None:
    """Exponent n of ``y ~ x^n``: the slope of a least-squares line in log-log (x, y > 0)."""
    sel = (x > 0) & (y > 0)
    if sel.sum() < 2:
        return None
    return float(np.polyfit(np.log(x[sel]), np.log(y[sel]), 1)[0])


def _hertz_sphere_modulus(res: CompressionResult, nu: float, max_strain: float) -> float | None:
    """Young's modulus [Pa] of a sphere from its compression between plates by Hertz's law.

    Each plate is a Hertz contact of a sphere of radius R = H/2 with a rigid plane, taking half
    the plate travel d: F = (4/3) E/(1 - nu^2) sqrt(R) (d/2)^(3/2). Fitted by least squares on
    the force over strains up to ``max_strain``.
    """
    sel = (res.strain > 0) & (res.strain <= max_strain + 1e-12)
    if not sel.any():
        return None
    R = 0.5 * res.height_m
    x = (4.0 / 3.0) * math.sqrt(R) * (0.5 * res.displacement_m[sel]) ** 1.5
    E_star = float(x @ res.force_N[sel] / (x @ x))
    return E_star * (1.0 - nu**2)


def _hertz_force(E: float, nu: float, R: float, delta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Hertz: force [N] of a rigid sphere of radius R pressed delta into an elastic half-space."""
    return (4.0 / 3.0) * E / (1.0 - nu**2) * math.sqrt(R) * np.asarray(delta) ** 1.5


# ---------------------------------------------------------------------- the experiments


def _exp_compression(ctx: _Context, rec: dict[str, Any], progress: _Progress, name: str) -> None:
    from softgrasp.viz.plots import plot_stress_strain

    s = ctx.settings
    body, obj = _object(name, s)
    rec["object"] = obj
    friction = _PLATE_FRICTION[name]
    rec["parameters"] = {
        "strain": s.compression_strain,
        "steps": s.compression_steps,
        "plate_friction": friction,
        "plate_penalty": _PLATE_PENALTY,
        "solver": f"static Newton per load increment (sparse Jacobian, energy line search); "
        f"linear solves: {_linear_solver()}",
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
        "E_relative_difference": _rel(res.apparent_E_Pa, paper["E_Pa"]),
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
        out["hertz_E_relative_difference"] = None if E_h is None else _rel(E_h, paper["E_Pa"])
        out["force_exponent"] = _power_fit(res.displacement_m[sel], res.force_N[sel])
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


def _exp_indentation(ctx: _Context, rec: dict[str, Any], progress: _Progress) -> None:
    from softgrasp.physics.fingertip.params import ContactParams
    from softgrasp.viz.plots import plot_force_penetration

    s = ctx.settings
    body, obj = _object("cube", s)
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
        f"linear solves: {_linear_solver()}",
    }
    res = indentation_test(
        body, depth=depth, radius=radius, params=params, progress=lambda f: progress(0.9 * f)
    )
    d, F = res.penetration_m, res.force_N
    m = body.material
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
        "exponent": _power_fit(d, F),
        "model_exponent": MODEL_EXPONENT,
        "contact_depth_at_end_m": float(res.contact_depth_m[-1]),
        "settle_sag_m": res.settle_sag_m,
        "split_increments": res.halvings,
        "at_depths": [
            {
                "penetration_m": float(q),
                "force_N": float(np.interp(q, d, F)),
                "contact_law_force_N": float(res.K_N_m1_5 * q**params.exponent),
                "hertz_half_space_force_N": float(_hertz_force(m.E, m.nu, radius, q)),
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


def _exp_grasp(ctx: _Context, rec: dict[str, Any], progress: _Progress) -> None:
    from softgrasp.io.plan_document import hand_polylines, plan_document
    from softgrasp.model.mesh.io import save_mesh
    from softgrasp.model.mesh.tetmesh import TetMesh
    from softgrasp.viz.plots import plot_grasp_3d, plot_plan_force_penetration, plot_plan_forces

    body, obj = _object("sphere", ctx.settings)
    rec["object"] = obj
    config = PlanConfig()
    rec["parameters"] = {
        **config.describe(),
        "solver_detail": "closing in increments, each brought to rest by a static Newton solve; hold check "
        f"by backward Euler; linear solves: {_linear_solver()}",
    }
    plan = plan_grasp(body, config, progress=lambda f: progress(0.8 * f))
    doc = plan_document(plan, body, "sphere")
    grasp_dir = ctx.out / "grasp"
    grasp_dir.mkdir(parents=True, exist_ok=True)
    save_mesh(TetMesh(plan.placed, body.mesh.tets, name=body.mesh.name), grasp_dir / "object.vtu")
    doc["object"]["mesh_file"] = "object.vtu"
    write_json(grasp_dir / "plan.json", _jsonable(doc))
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


def _mujoco_version() -> str:
    """MuJoCo's version; raises :class:`_Skipped` with the reason when it cannot be imported."""
    try:
        import mujoco
    except Exception as exc:  # ImportError, or a broken installation
        raise _Skipped(
            f"MuJoCo is not importable ({type(exc).__name__}: {exc}); pip install mujoco"
        ) from None
    return str(getattr(mujoco, "__version__", "unknown"))


def _exp_execution(ctx: _Context, rec: dict[str, Any], progress: _Progress) -> None:
    if ctx.plan_file is None:
        raise _Skipped(f"there is no grasp plan to execute (the grasp step {ctx.plan_status})")
    version = _mujoco_version()
    from softgrasp.execution.controller import PHASES, ExecuteConfig, closing_lines, execute_plan
    from softgrasp.execution.mujoco.hand import MujocoHand
    from softgrasp.io.planfile import load_plan_file
    from softgrasp.model.mesh.io import load_mesh
    from softgrasp.viz.plots import EXECUTION_FRAME_TITLES, plot_execution_forces, plot_execution_frame

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
    frames: dict[str, tuple] = {}

    def snapshot(event: str) -> None:
        frames[event] = hand.snapshot(names)

    t0 = time.perf_counter()
    res = execute_plan(
        hand,
        lines,
        cfg,
        palm_to_world=hand.palm_to_world,
        progress=lambda f: progress(0.75 * f),
        on_event=snapshot,
    )
    sim_wall = time.perf_counter() - t0
    ser = res.series
    simulated = float(ser["t"][-1]) if len(ser["t"]) else 0.0
    outcome = res.describe()
    for f in outcome["fingers"]:
        f["relative_error"] = _rel(f["measured_N"], f["setpoint_N"])
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
    for done, event in enumerate(EXECUTION_FRAME_TITLES, start=1):
        if event in frames:
            key = f"frame_{event}"
            figs[key] = f"figures/execution_{key}.png"
            radius = plan.fingertip_radius
            plot_execution_frame(ctx.out / figs[key], frames[event], facets, names, radius, event)
        progress(0.75 + 0.25 * done / len(EXECUTION_FRAME_TITLES))
    rec["figures"] = figs
    progress(1.0)


# ---------------------------------------------------------------------- the report: a tiny document model
# Blocks: ("h", level, text), ("p", text), ("ul", [items]), ("table", header, rows, align),
# ("fig", relative path, caption), ("quote", text). Text may hold `code` and **bold**.

Block = tuple[Any, ...]


def _fmt(x: Any, spec: str = ".4g", scale: float = 1.0, none: str = "–") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    return format(float(x) * scale, spec)


def _pct(x: Any, spec: str = "+.1f") -> str:
    return "–" if x is None else f"{format(100 * float(x), spec)} %"


def _flatten(d: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    """Parameter rows ``(dotted.key, value)`` of a nested dict, lists shortened for people."""
    rows: list[tuple[str, str]] = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            rows += _flatten(v, key + ".")
        elif isinstance(v, list | tuple):
            vals = [
                _fmt(x, ".4g") if isinstance(x, int | float) and not isinstance(x, bool) else str(x)
                for x in v
            ]
            rows.append((key, "[" + ", ".join(vals) + "]"))
        elif isinstance(v, float):
            rows.append((key, _fmt(v, ".6g")))
        else:
            rows.append((key, "–" if v is None else str(v)))
    return rows


def _params_table(title: str, params: Mapping[str, Any]) -> list[Block]:
    return [("p", f"**{title}**"), ("table", ["parameter", "value"], _flatten(params), "ll")]


def _object_rows(obj: Mapping[str, Any]) -> dict[str, Any]:
    m = obj["material"]
    return {
        "object": obj["description"],
        "material": f"{m['name']}: E = {m['E_Pa']:.6g} Pa, nu = {m['nu']:g}, density "
        f"{m['density_kg_m3']:.4g} kg/m^3, law {m['law']['kind']}",
        "mesh": f"mesh size {obj['mesh_size_m'] * 1e3:.3g} mm: {obj['nodes']} nodes, {obj['tets']} tets, "
        f"{obj['facets']} boundary facets",
        "mass_kg": obj["mass_kg"],
        "network": obj["network"],
    }


def _status_line(step: Mapping[str, Any]) -> list[Block]:
    if step["status"] == "failed":
        return [("quote", f"**FAILED** after {step['wall_time_s']:.1f} s: {step['message']}")]
    if step["status"] == "skipped":
        return [("quote", f"**SKIPPED**: {step['message']}")]
    return []


def _figures(step: Mapping[str, Any], captions: Mapping[str, str]) -> list[Block]:
    figs = step.get("figures", {})
    return [("fig", figs[k], cap) for k, cap in captions.items() if k in figs]


def _section_compression(steps: Mapping[str, dict[str, Any]]) -> list[Block]:
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
            f"{_fmt(strain, '.0f', 100)} % strain. Nominal stress is the plate force over the object's "
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
                    _fmt(paper["E_Pa"], ".4f", 1e-6),
                    st["status"],
                    "–",
                    _fmt(paper["nu"], ".2f"),
                    "–",
                    "–",
                ]
            )
            continue
        rows.append(
            [
                name,
                _fmt(paper["E_Pa"], ".4f", 1e-6),
                _fmt(r["E_Pa"], ".4f", 1e-6),
                _pct(r["E_relative_difference"]),
                _fmt(paper["nu"], ".2f"),
                _fmt(r["nu"], ".3f"),
                _fmt(r["nu_difference"], "+.3f"),
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
            f"{_pct(abs(r['E_relative_difference']), '.1f')} and ν within {abs(r['nu_difference']):.2g}. "
            "Although the foam's stress-strain law is linear, the curve stiffens at large strain (secant "
            f"modulus at {_fmt(strain, '.0f', 100)} %: {_fmt(r['secant_modulus_at_peak_Pa'], '.4g', 1e-6)} "
            f"MPa, {_pct(_rel(r['secant_modulus_at_peak_Pa'], r['E_Pa']))} over the initial slope): the "
            "model is geometrically non-linear (its springs and volume term follow the deformed "
            "configuration). The paper's measured curves (Fig. 9) are not "
            "given as numbers; a measured non-linear law can be given to softgrasp as a table."
        )
    if sphere is not None and sphere.get("results"):
        r = sphere["results"]
        notes.append(
            f"**Sphere**: the initial slope, {_fmt(r['E_Pa'], '.4g', 1e-3)} kPa, is not the rubber's modulus "
            f"({_pct(r['E_relative_difference'])}) and the lateral strain at the equator is not ν: "
            "between plates a sphere is a Hertz contact, σ = 4/(3π) E/(1−ν²) ε^1.5 at small strain, "
            "whose slope vanishes at zero strain. Fitting Hertz's law to the force up to "
            f"{_fmt(r['hertz_fit_strain'], '.0f', 100)} % strain gives E = "
            f"{_fmt(r['hertz_E_Pa'], '.4g', 1e-3)} kPa ({_pct(r['hertz_E_relative_difference'])} from "
            f"Table 1), with a fitted force exponent of {_fmt(r['force_exponent'], '.2f')} instead of "
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
        blocks.append(("h", 3, f"1.{1 if name == 'cube' else 2} {EXPERIMENTS[st['name']]}"))
        blocks += _status_line(st)
        blocks += _figures(
            st,
            {
                "stress_strain": f"Nominal stress against strain of the {name} (cf. paper Fig. 9), with "
                "the initial-slope line and the material's E."
            },
        )
        if st.get("object"):
            params = _object_rows(st["object"])
            params.update(st.get("parameters", {}))
            blocks += _params_table("Parameters", params)
    return blocks


def _section_indentation(st: dict[str, Any] | None) -> list[Block]:
    if st is None:
        return []
    blocks: list[Block] = [("h", 2, "2. One-finger indentation of the foam cube (paper Sec. 4.3.1, Fig. 11)")]
    blocks += _status_line(st)
    p = st.get("parameters", {})
    if p:
        blocks.append(
            (
                "p",
                f"A rigid spherical fingertip (R = {_fmt(p.get('fingertip_radius_m'), 'g', 1e3)} mm) presses "
                "straight down on the middle of the top of the foam cube resting on the table, "
                f"quasi-statically in {p.get('steps')} increments to "
                f"{_fmt(p.get('depth_m'), 'g', 1e3)} mm beyond first contact. Penetration is the "
                "fingertip's travel since first contact (the abscissa of Fig. 11).",
            )
        )
    r = st.get("results")
    if r:
        rows = [
            [
                _fmt(a["penetration_m"], "g", 1e3),
                _fmt(a["force_N"], ".3g"),
                _fmt(a["contact_law_force_N"], ".3g"),
                _fmt(a["hertz_half_space_force_N"], ".3g"),
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
                    "contact law alone, K δ^1.5 [N]",
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
                f"{_fmt(r['exponent'], '.3f')} (the contact model's exponent: {r['model_exponent']:g}; a "
                "linear spring: 1).",
            )
        )
        blocks.append(
            (
                "ul",
                [
                    "The fingertip's travel is the contact law's own depth "
                    f"({_fmt(r['contact_depth_at_end_m'], '.3g', 1e3)} mm of the "
                    f"{_fmt(p.get('depth_m'), 'g', 1e3)} mm at the end) plus the deformation of the meshed "
                    "cube under the finger, which is nearly linear in the force: in series they grow with "
                    "an exponent between 1 and 1.5 — clearly non-linear, the paper's point against linear "
                    "models.",
                    "The paper's text quotes a mean force error of 0.3 N, '15 % of typical contact "
                    "forces', i.e. forces of about 2 N. With Table 1's E = 4.93 MPa softgrasp's cube "
                    "needs tens of newtons at a few millimetres, the same order as Hertz's half-space "
                    "with that E (last column): the paper's forces suggest its cube was softer or "
                    "smaller than Table 1 implies. Nothing here is tuned to match.",
                ],
            )
        )
    blocks += _figures(
        st, {"force_penetration": "Force against penetration of the fingertip (cf. paper Fig. 11)."}
    )
    if st.get("object"):
        params = _object_rows(st["object"])
        params.update(p)
        blocks += _params_table("Parameters", params)
    return blocks


def _section_grasp(st: dict[str, Any] | None) -> list[Block]:
    if st is None:
        return []
    blocks: list[Block] = [
        ("h", 2, "3. Three-finger grasp of the rubber sphere (paper Sec. 4.3.2, Table 2, Figs. 12–13, 15)")
    ]
    blocks += _status_line(st)
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
                    _fmt(f["paper_penetration_m"], "g", 1e3),
                    _fmt(f["paper_force_N"], ".1f"),
                    _fmt(f["penetration_m"], ".2f", 1e3),
                    f"{f['force_N']:.3f} ({f['normal_force_N']:.3f} + {f['tangential_force_N']:.3f})",
                    _fmt(f["force_ratio_to_paper"], ".2f"),
                    _fmt(f["rigid_minimum_normal_force_N"], ".3f"),
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
                    f"{_pct(eq['friction_margin'], '.0f')}; equilibrium satisfied: "
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
                "The penetrations are much smaller also because softgrasp's contact law is Hertz's with "
                "the object's own E in series with the meshed body. A lower μ or a larger "
                "`safety_factor` gives larger forces; nothing here is tuned to match.",
            )
        )
    blocks += _figures(
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
        params = _object_rows(st["object"])
        params.update(st.get("parameters", {}))
        blocks += _params_table("Parameters", params)
    return blocks


def _section_execution(st: dict[str, Any] | None) -> list[Block]:
    if st is None:
        return []
    blocks: list[Block] = [
        ("h", 2, "4. Execution on the simulated hand and lift (paper Sec. 4.3.3, Figs. 14–15)")
    ]
    blocks += _status_line(st)
    blocks.append(
        (
            "p",
            "The plan is executed on a simulated hand in MuJoCo (physics softgrasp did not write): the "
            "sphere as a 3-D flex from the plan's mesh with its E and ν, the hand from the plan's URDF. "
            "Each fingertip closes along its planned line under an integral force loop on its tactile "
            "normal force until every finger has stayed within the tolerance of its set-point; the arm "
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
                _pct(f["relative_error"]),
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
    blocks += _figures(
        st,
        {
            "forces": "Measured normal force of each finger against time with its set-point and "
            "tolerance band (cf. paper Fig. 15).",
            "frame_start": "Initial pose (cf. paper Fig. 14 a–b).",
            "frame_contact": "First contact (cf. Fig. 14 c–d).",
            "frame_closed": "Final deformation under the set-points (cf. Fig. 14 e–f).",
            "frame_end": "Lifted, after the hold.",
        },
    )
    if st.get("parameters"):
        blocks += _params_table("Parameters", st["parameters"])
    return blocks


def _key_numbers(steps: Mapping[str, dict[str, Any]]) -> list[str]:
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
                f"({_pct(r['E_relative_difference'])}), ν {r['nu']:.3f} vs {r['paper_nu']:g}"
            )
            if obj == "sphere":
                line += (
                    f" — a sphere's initial slope is not its modulus; Hertz's law fitted to its force "
                    f"gives {_fmt(r['hertz_E_Pa'], '.4g', 1e-6)} MPa "
                    f"({_pct(r['hertz_E_relative_difference'])})"
                )
            items.append(line + " (§1).")
        elif name == "indentation_cube":
            last = r["at_depths"][-1] if r["at_depths"] else None
            at = f"{last['force_N']:.3g} N at {last['penetration_m'] * 1e3:g} mm; " if last else ""
            items.append(
                f"Fig. 11, foam cube: {at}F ∝ δ^{_fmt(r['exponent'], '.2f')} over the curve (contact law: "
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
                + " / ".join(_fmt(f["paper_force_N"], ".1f") for f in fs)
                + " N at "
                + " / ".join(_fmt(f["paper_penetration_m"], "g", 1e3) for f in fs)
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
                f"(largest error {_pct(err, '.1f')}), {verdict}, slip {r['slip_m'] * 1e3:.2f} mm (§4)."
            )
    return items


def _report_blocks(doc: dict[str, Any]) -> list[Block]:
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
        blocks += [("h", 2, "Key numbers"), ("ul", _key_numbers(steps))]
    rows = [[s["title"], s["status"], f"{s['wall_time_s']:.2f}", s["message"] or "–"] for s in doc["steps"]]
    rows.append(["report (md, html, json)", "ok", f"{run['report_wall_time_s']:.2f}", "–"])
    rows.append(["**total**", "", f"**{run['wall_time_s']:.2f}**", ""])
    blocks += [
        ("h", 2, "Steps and wall times"),
        ("table", ["step", "status", "wall time [s]", "note"], rows, "llrl"),
    ]
    blocks += _section_compression(steps)
    blocks += _section_indentation(steps.get("indentation_cube"))
    blocks += _section_grasp(steps.get("grasp_sphere"))
    blocks += _section_execution(steps.get("execution_sphere"))
    env = doc["environment"]
    blocks += [
        ("h", 2, "Environment"),
        ("table", ["component", "version or setting"], [[k, str(v)] for k, v in env.items()], "ll"),
    ]
    return blocks


_INLINE_CODE = re.compile(r"`([^`]+)`")
_BOLD = re.compile(r"\*\*(.+?)\*\*")
_ITALIC = re.compile(r"(?<![\w*])\*([^*\n]+)\*(?![\w*])")


def _inline_html(text: str) -> str:
    """Escape ``text`` for HTML and turn `code`, **bold** and *italic* into tags."""
    parts = _INLINE_CODE.split(text)
    out = []
    for i, part in enumerate(parts):
        if i % 2:
            out.append(f"<code>{html.escape(part)}</code>")
        else:
            s = html.escape(part, quote=False)
            s = _BOLD.sub(r"<strong>\1</strong>", s)
            out.append(_ITALIC.sub(r"<em>\1</em>", s))
    return "".join(out)


def _md_cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _render_markdown(blocks: Sequence[Block]) -> str:
    """The report as Markdown (figures by relative path)."""
    out: list[str] = []
    n_fig = 0
    for b in blocks:
        kind = b[0]
        if kind == "h":
            out.append(f"{'#' * b[1]} {b[2]}")
        elif kind == "p":
            out.append(b[1])
        elif kind == "quote":
            out.append(f"> {b[1]}")
        elif kind == "ul":
            out.append("\n".join(f"- {item}" for item in b[1]))
        elif kind == "table":
            header, rows, align = b[1], b[2], b[3]
            lines = ["| " + " | ".join(_md_cell(h) for h in header) + " |"]
            lines.append("|" + "|".join("---:" if a == "r" else ":---" for a in align) + "|")
            lines += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in rows]
            out.append("\n".join(lines))
        elif kind == "fig":
            n_fig += 1
            out.append(f"![Figure {n_fig}]({b[1]})\n\n*Figure {n_fig}. {b[2]}*")
    return "\n\n".join(out) + "\n"


_CSS = """
body{font-family:-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;max-width:60rem;margin:2rem auto;
padding:0 1rem;color:#222;line-height:1.5}
h1{font-size:1.7rem;border-bottom:2px solid #ddd;padding-bottom:.3rem}
h2{font-size:1.35rem;margin-top:2.2rem;border-bottom:1px solid #e4e4e4;padding-bottom:.2rem}
h3{font-size:1.1rem;margin-top:1.6rem}
table{border-collapse:collapse;margin:.6rem 0 1rem;font-size:.9rem}
th,td{border:1px solid #d8d8d8;padding:.25rem .55rem;vertical-align:top}
th{background:#f3f3f3}
td.r,th.r{text-align:right}
code{background:#f4f4f4;padding:0 .2rem;border-radius:3px;font-size:.88em}
blockquote{margin:1rem 0;padding:.5rem 1rem;border-left:4px solid #c9a227;background:#fcf8e8}
figure{margin:1.2rem 0;text-align:center}
figure img{max-width:100%;height:auto;border:1px solid #eee}
figcaption{font-size:.9rem;color:#555;margin-top:.3rem}
"""


def _render_html(blocks: Sequence[Block], base: Path) -> str:
    """The report as one self-contained HTML page: CSS inline, each figure read from ``base`` and
    embedded as a base64 PNG data URI (nothing is fetched)."""
    out: list[str] = []
    title = next((b[2] for b in blocks if b[0] == "h" and b[1] == 1), "softgrasp report")
    n_fig = 0
    for b in blocks:
        kind = b[0]
        if kind == "h":
            out.append(f"<h{b[1]}>{_inline_html(b[2])}</h{b[1]}>")
        elif kind == "p":
            out.append(f"<p>{_inline_html(b[1])}</p>")
        elif kind == "quote":
            out.append(f"<blockquote>{_inline_html(b[1])}</blockquote>")
        elif kind == "ul":
            out.append("<ul>" + "".join(f"<li>{_inline_html(i)}</li>" for i in b[1]) + "</ul>")
        elif kind == "table":
            header, rows, align = b[1], b[2], b[3]
            cls = [' class="r"' if a == "r" else "" for a in align]
            head = "".join(f"<th{c}>{_inline_html(str(h))}</th>" for h, c in zip(header, cls, strict=True))
            body = "".join(
                "<tr>"
                + "".join(f"<td{c}>{_inline_html(str(v))}</td>" for v, c in zip(row, cls, strict=True))
                + "</tr>"
                for row in rows
            )
            out.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
        elif kind == "fig":
            n_fig += 1
            data = base64.b64encode((base / b[1]).read_bytes()).decode("ascii")
            out.append(
                f'<figure><img alt="Figure {n_fig}" src="data:image/png;base64,{data}">'
                f"<figcaption>Figure {n_fig}. {_inline_html(b[2])}</figcaption></figure>"
            )
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
        + "\n".join(out)
        + "\n</body>\n</html>\n"
    )


# ---------------------------------------------------------------------- the run


def _environment() -> dict[str, str]:
    import matplotlib
    import numba
    import scipy

    try:
        import mujoco

        mj = str(getattr(mujoco, "__version__", "unknown"))
    except Exception as exc:
        mj = f"not importable ({type(exc).__name__})"
    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpus": str(os.cpu_count()),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "matplotlib": matplotlib.__version__,
        "mujoco": mj,
        "numba": numba.__version__,
        "linear solver": _linear_solver(),
    }


def _selection(experiments: Collection[str] | None) -> list[str]:
    if experiments is None:
        return list(EXPERIMENTS)
    wanted = [str(e) for e in experiments]
    unknown = sorted(set(wanted) - set(EXPERIMENTS))
    if unknown:
        raise ConfigError(f"unknown experiment(s) {', '.join(unknown)}; choose from {', '.join(EXPERIMENTS)}")
    if not wanted:
        raise ConfigError(f"no experiment selected; choose from {', '.join(EXPERIMENTS)}")
    return [e for e in EXPERIMENTS if e in wanted]


def reproduce(
    out: str | Path,
    *,
    quick: bool = False,
    progress: Callable[[float, str], None] | None = None,
    experiments: Collection[str] | None = None,
) -> ReproductionResult:
    """Run the paper's experiments and write ``report.md``, ``report.html`` and ``reproduce.json``.

    Parameters
    ----------
    out: output folder (created if needed). Figures go to ``out/figures/``, the grasp plan to
        ``out/grasp/``.
    quick: coarse meshes (285-node cube, ~210-node sphere), 10 compression increments and a 3 mm
        indentation instead of the objects' default meshes, 30 increments and 5 mm; well under a
        minute on two cores once softgrasp's compiled kernels are cached.
    progress: called as ``progress(fraction, step)`` with the completed fraction of the whole run
        (0..1, non-decreasing, 1 at the end) and the name of the running step (a key of
        :data:`EXPERIMENTS`, or ``"report"``).
    experiments: run only these steps (keys of :data:`EXPERIMENTS`; default all). The execution
        needs the grasp plan of the same run and is skipped without it.

    Returns
    -------
    ReproductionResult: per step its status (``ok``, ``failed``, ``skipped``), message and wall
    time; the files written; the JSON document.

    Raises
    ------
    ConfigError: an unknown experiment name. A failing experiment does not raise: it is recorded
    as failed (with its message) in the result and the report, and the run continues.
    """
    t_start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    names = _selection(experiments)
    ctx = _Context(out, _Settings.of(quick))
    total = sum(_WEIGHTS[n] for n in names) + _WEIGHTS["report"]
    done = 0.0

    last = [0.0]  # the fraction never goes back, even when a step's own estimate does

    def report_progress(fraction: float, step: str) -> None:
        last[0] = min(1.0, max(last[0], fraction))
        if progress is not None:
            progress(last[0], step)

    runners: dict[str, Callable[[dict[str, Any], _Progress], None]] = {
        "compression_cube": lambda rec, p: _exp_compression(ctx, rec, p, "cube"),
        "compression_sphere": lambda rec, p: _exp_compression(ctx, rec, p, "sphere"),
        "indentation_cube": lambda rec, p: _exp_indentation(ctx, rec, p),
        "grasp_sphere": lambda rec, p: _exp_grasp(ctx, rec, p),
        "execution_sphere": lambda rec, p: _exp_execution(ctx, rec, p),
    }
    step_docs: list[dict[str, Any]] = []
    records: list[StepRecord] = []
    for name in names:
        w = _WEIGHTS[name]
        start = done

        def sub(f: float, start: float = start, w: float = w, name: str = name) -> None:
            report_progress((start + w * min(1.0, max(0.0, f))) / total, name)

        sub(0.0)
        rec: dict[str, Any] = {}
        t0 = time.perf_counter()
        status, message, tb = "ok", "", None
        try:
            runners[name](rec, sub)
        except _Skipped as exc:
            status, message = "skipped", str(exc)
        except Exception as exc:  # any failure of one experiment is reported, not raised
            status, message = "failed", f"{type(exc).__name__}: {exc}"
            if not isinstance(exc, SoftgraspError):  # not a deliberate error: keep where it happened
                tb = traceback.format_exc(limit=8)
        wall = time.perf_counter() - t0
        if name == "grasp_sphere":
            ctx.plan_status = {"ok": "ran", "failed": "failed", "skipped": "was skipped"}[status]
        figs = rec.pop("figures", {})
        step_doc: dict[str, Any] = {
            "name": name,
            "title": EXPERIMENTS[name],
            "status": status,
            "message": message,
            "wall_time_s": wall,
            **rec,
            "figures": figs,
        }
        if tb is not None:
            step_doc["traceback"] = tb
        step_docs.append(step_doc)
        records.append(
            StepRecord(name, EXPERIMENTS[name], status, wall, message, tuple(out / f for f in figs.values()))
        )
        done += w
        report_progress(done / total, name)

    report_progress(done / total, "report")
    t_report = time.perf_counter()
    doc: dict[str, Any] = {
        "schema": SCHEMA,
        "paper": PAPER_TITLE,
        "run": {
            "softgrasp_version": __version__,
            "quick": bool(quick),
            "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M:%S UTC"),
            "experiments": names,
            "failed": [s["name"] for s in step_docs if s["status"] == "failed"],
            "skipped": [s["name"] for s in step_docs if s["status"] == "skipped"],
            "wall_time_s": 0.0,
            "report_wall_time_s": 0.0,
        },
        "paper_values": {"table1": PAPER_TABLE1, "table2": PAPER_TABLE2},
        "environment": _environment(),
        "steps": step_docs,
    }
    # The report states its own wall time and the total: time a first rendering (the figures read
    # and encoded), then render again with the times in (milliseconds).
    _render_html(_report_blocks(doc), out)
    doc["run"]["report_wall_time_s"] = time.perf_counter() - t_report
    doc["run"]["wall_time_s"] = time.perf_counter() - t_start
    blocks = _report_blocks(doc)
    md_path = write_text(out / "report.md", _render_markdown(blocks))
    html_path = write_text(out / "report.html", _render_html(blocks, out))
    json_path = write_json(out / "reproduce.json", _jsonable(doc))
    wall = time.perf_counter() - t_start
    report_progress(1.0, "report")
    return ReproductionResult(
        out=out,
        quick=bool(quick),
        steps=tuple(records),
        report_md=md_path,
        report_html=html_path,
        data_json=json_path,
        wall_time_s=wall,
        document=doc,
    )
