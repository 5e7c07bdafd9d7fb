"""Executing a plan on a simulated hand: :func:`execute` and its result :class:`Execution`, whose
:meth:`Execution.save` writes the files of ``softgrasp execute``.

The hand closes its fingertips under force control to the plan's set-points, lifts the object and
holds it (MuJoCo; :mod:`softgrasp.execution`).
"""

from __future__ import annotations

import csv
import io
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from softgrasp import __version__
from softgrasp.api.planning import Plan
from softgrasp.errors import ConfigError

if TYPE_CHECKING:
    from softgrasp.execution.controller import ClosingLine, ExecuteConfig, ExecutionResult
    from softgrasp.io.planfile import PlanFile

__all__ = ["Execution", "execute", "check_options", "with_material_file", "EXECUTE_SCHEMA"]

EXECUTE_SCHEMA = "softgrasp.execute/1"


def with_material_file(plan: PlanFile, path: str) -> tuple[PlanFile, dict[str, float]]:
    """``plan`` with the object's material (E, nu) and fingertip friction of the material file
    ``path`` over it (the hand then grasps an object that differs from the one planned for; mass
    as planned), and the values changed."""
    from softgrasp.io.materialfile import is_material_file, read_material_file

    if not is_material_file(path):
        raise ConfigError(f"execute --material takes a material file (.toml), got {path!r}")
    from softgrasp.io.limits import PLAN_RANGES

    mf = read_material_file(path)
    changes: dict[str, float] = {}
    if mf.material is not None:
        changes.update(E=mf.material.E, nu=mf.material.nu)
    if "mu" in mf.contact:
        changes["mu"] = mf.contact["mu"]  # type: ignore[assignment]
    where = {"E": "object.material.E_Pa", "nu": "object.material.nu", "mu": "parameters.contact.mu"}
    for key, value in changes.items():
        changes[key] = PLAN_RANGES[where[key]].check(value, key, f"execute --material {path}: ")
    return replace(plan, **changes), changes


def check_options(plan: PlanFile, lift_m: float, scale: float, backend: str) -> None:
    """Refuse an option of :func:`execute` outside its physical range
    (:data:`~softgrasp.io.limits.EXECUTE_RANGES`), or a scaled set-point above
    :data:`~softgrasp.io.limits.MAX_SETPOINT_N`, naming the option."""
    from softgrasp.io.limits import EXECUTE_RANGES, MAX_SETPOINT_N

    EXECUTE_RANGES["--lift"].check(lift_m, "--lift")
    EXECUTE_RANGES["--scale"].check(scale, "--scale")
    if backend != "mujoco":
        raise ConfigError(f"backend must be mujoco, got {backend!r}")
    for f in plan.fingers:
        if scale * f.normal_force > MAX_SETPOINT_N:
            raise ConfigError(
                f"--scale {scale:g} asks the {f.name} to press {scale * f.normal_force:.3g} N, more than "
                f"the {MAX_SETPOINT_N:g} N a fingertip is driven to: lower --scale"
            )


@dataclass(eq=False)
class Execution:
    """An executed plan.

    Attributes
    ----------
    plan: the plan file executed (its object material possibly replaced).
    result: the controller's record (:class:`~softgrasp.execution.controller.ExecutionResult`).
    config: the controller settings.  lines: per finger its set-point and closing line.
    frames: where MuJoCo could not render, snapshots of the hand and object at the events
        ``start``, ``contact``, ``closed``, ``end`` (drawn by matplotlib); else empty.
    facets: the object's surface triangles (for the snapshots' pictures).
    document: the ``execute.json`` document.
    scene_xml: the MJCF of the simulated scene (table, object as a flex with its points and tets
        inline, hand on its arm; keyframe ``initial`` the start): self-contained, no other file.
    images: MuJoCo's renderings of the scene at the events (RGB, (480, 640, 3) uint8), all from
        one camera; empty where MuJoCo could not render.
    event_times: the hand's time [s] at each event.
    """

    plan: PlanFile
    result: ExecutionResult
    config: ExecuteConfig
    lines: dict[str, ClosingLine]
    frames: dict[str, tuple]
    facets: Any
    document: dict[str, Any]
    scene_xml: str = ""
    images: dict[str, Any] = field(default_factory=dict)
    event_times: dict[str, float] = field(default_factory=dict)

    def save_scene(self, path: str | Path) -> Path:
        """Write the MJCF of the executed scene (:attr:`scene_xml`) to ``path`` atomically; it loads
        with ``mujoco.MjModel.from_xml_path(path)``."""
        from softgrasp.io.atomic import write_text
        from softgrasp.io.runfolder import check_out_file

        return write_text(check_out_file(path, "--save-scene"), self.scene_xml)

    @property
    def lifted(self) -> bool:
        """Whether the object rose with the hand."""
        return bool(self.result.lifted)

    @property
    def dropped(self) -> bool:
        """Whether the object fell (rose less than half the lift)."""
        return bool(self.result.dropped)

    @property
    def reached(self) -> bool:
        """Whether the closing brought every finger within the tolerance of its set-point."""
        return bool(self.result.reached)

    @property
    def slip_m(self) -> float:
        """The object's largest displacement relative to the fingertips in lift and hold [m]."""
        return float(self.result.slip)

    @property
    def rise_m(self) -> float:
        """The object's final rise [m]."""
        return float(self.result.rise)

    @property
    def setpoints_N(self) -> dict[str, float]:
        """Each finger's set-point [N] (the plan's, times the scale)."""
        return {n: float(v) for n, v in self.result.setpoints.items()}

    @property
    def measured_N(self) -> dict[str, float]:
        """Each finger's tactile normal force when the closing ended [N]."""
        return {n: float(v) for n, v in self.result.measured.items()}

    @property
    def held_N(self) -> dict[str, float]:
        """Each finger's mean tactile normal force over the last half of the hold [N]."""
        return {n: float(v) for n, v in self.result.held.items()}

    @property
    def simulated_time_s(self) -> float:
        """Simulated time of the whole execution [s]."""
        return float(self.document["simulated_time_s"])

    def to_dict(self) -> dict[str, Any]:
        """The ``execute.json`` document."""
        return dict(self.document)

    def save(self, out: str | Path) -> list[str]:
        """Write ``execute.json``, ``execute.csv``, ``execute_forces.png`` and a picture per event
        (``frame_start.png`` ..., :meth:`write_pictures`) into ``out``, replacing the folder's
        earlier ones whole (:mod:`softgrasp.io.runfolder`); return the pictures' names."""
        from softgrasp.io.portable import portable_path
        from softgrasp.io.runfolder import run_folder

        with run_folder(out, "execute") as folder:
            doc, material = self.document, self.document.get("object_material") or {}
            if isinstance(doc.get("plan"), str):  # named from the folder, not by this machine's path
                doc["plan"] = portable_path(doc["plan"], folder.path)
            if isinstance(material.get("file"), str):
                material["file"] = portable_path(material["file"], folder.path)
            return self._write(folder.stage)

    def _write(self, out: Path) -> list[str]:
        import numpy as np

        from softgrasp.execution.controller import PHASES
        from softgrasp.io.atomic import write_json, write_text
        from softgrasp.viz.plots import plot_execution_forces

        res, names = self.result, [f.name for f in self.plan.fingers]
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
            [self.lines[n].setpoint for n in names],
            names,
            out / "execute_forces.png",
            phases=phases,
            tolerance=self.config.tolerance,
        )
        pictures = self.write_pictures(out)
        write_text(out / "execute.csv", buf.getvalue())
        write_json(out / "execute.json", self.document)
        return pictures

    def write_pictures(self, out: Path, prefix: str = "frame_") -> list[str]:
        """Write the picture of each event into ``out`` as ``<prefix><event>.png``, titled by the
        event and the run's outcome: MuJoCo's rendering (:attr:`images`), or matplotlib's drawing
        of the snapshot (:attr:`frames`) where MuJoCo could not render; return their names
        (:func:`~softgrasp.viz.execution_plots.write_execution_pictures`)."""
        from softgrasp.viz.plots import write_execution_pictures

        res = self.result
        return write_execution_pictures(
            out,
            prefix,
            images=self.images,
            snapshots=self.frames,
            times=self.event_times,
            facets=self.facets,
            names=[f.name for f in self.plan.fingers],
            radius=self.plan.fingertip_radius,
            reached=bool(res.reached),
            lifted=bool(res.lifted),
            rise_m=float(res.rise),
            lift_m=self.config.lift,
        )


def execute(
    plan: Plan | PlanFile | str | Path,
    *,
    lift_m: float = 0.10,
    hold_s: float = 2.0,
    scale: float = 1.0,
    material: str | None = None,
    backend: str = "mujoco",
    progress: Callable[[float], None] | None = None,
    renderer: Callable[[Any, int, int], Any] | None = None,
) -> Execution:
    """Execute ``plan`` (a :class:`Plan`, a ``plan.json`` written by ``softgrasp plan`` or its
    :class:`~softgrasp.io.planfile.PlanFile`) under
    force control on a simulated hand, lift the object ``lift_m`` [m] and hold it ``hold_s`` [s].

    Parameters
    ----------
    scale:
        Multiplies the set-points.
    material:
        A material file (``.toml``): grasp an object of its material and fingertip friction
        instead of the planned one.
    backend:
        The simulated hand: ``mujoco``.
    progress:
        Called with the fraction of the planned duration done.
    renderer:
        Makes MuJoCo's offscreen renderer of the pictures from (model, height, width); default
        ``mujoco.Renderer``. Where it raises (no OpenGL), the pictures are drawn by matplotlib
        instead, with a :class:`~softgrasp.errors.SoftgraspWarning`
        (:mod:`softgrasp.execution.mujoco.render`).

    A :class:`Plan` not saved yet is executed from a temporary copy of its ``plan.json`` and
    ``object.vtu`` (the run's document then names no plan file).
    """
    from softgrasp.io.limits import EXECUTE_RANGES
    from softgrasp.io.planfile import load_plan_file

    EXECUTE_RANGES["--lift"].check(lift_m, "--lift")
    EXECUTE_RANGES["--hold"].check(hold_s, "--hold")
    EXECUTE_RANGES["--scale"].check(scale, "--scale")
    if isinstance(plan, Plan):
        if plan.directory is not None:
            return execute(
                plan.directory / "plan.json",
                lift_m=lift_m,
                hold_s=hold_s,
                scale=scale,
                material=material,
                backend=backend,
                progress=progress,
                renderer=renderer,
            )
        with tempfile.TemporaryDirectory(prefix="softgrasp-plan-") as tmp:
            planned = load_plan_file(plan.write_plan_file(tmp))
            run = _execute(planned, lift_m, scale, material, backend, progress, renderer, hold_s)
        run.document["plan"] = None
        return run
    if isinstance(plan, str | Path):
        plan = load_plan_file(plan)
    return _execute(plan, lift_m, scale, material, backend, progress, renderer, hold_s)


def _execute(
    plan: PlanFile,
    lift_m: float,
    scale: float,
    material: str | None,
    backend: str,
    progress: Callable[[float], None] | None,
    renderer: Callable[[Any, int, int], Any] | None = None,
    hold_s: float = 2.0,
) -> Execution:
    from softgrasp.execution.controller import ExecuteConfig, closing_lines, execute_plan
    from softgrasp.execution.mujoco.hand import MujocoHand
    from softgrasp.execution.mujoco.mjcf import build_mjcf
    from softgrasp.execution.mujoco.render import event_pictures
    from softgrasp.model.mesh.io import load_mesh

    t0 = time.perf_counter()
    check_options(plan, lift_m, scale, backend)
    if material is not None:
        plan, _ = with_material_file(plan, material)
    hand = MujocoHand.from_plan(plan)  # the plan's parts checked to agree first
    facets = load_mesh(plan.mesh_file).facets
    lines = closing_lines(plan, scale)
    cfg = ExecuteConfig(lift=float(lift_m), hold_time=float(hold_s))
    largest = max(line.setpoint for line in lines.values())
    pictures = event_pictures(hand, plan.fingertip_radius, cfg.lift, largest, make=renderer)
    try:
        res = execute_plan(
            hand, lines, cfg, palm_to_world=hand.palm_to_world, progress=progress, on_event=pictures
        )
    finally:
        pictures.close()
    wall = time.perf_counter() - t0
    ser = res.series
    sim = float(ser["t"][-1]) if len(ser["t"]) else 0.0
    doc = {
        "schema": EXECUTE_SCHEMA,
        "softgrasp_version": __version__,
        "plan": str(Path(plan.path).resolve()),
        "backend": backend,
        "scale": scale,
        "object_material": {"file": material, "E_Pa": plan.E, "nu": plan.nu, "mu": plan.mu},
        "parameters": {**cfg.describe(), "mujoco_timestep_s": float(hand.scene.model.opt.timestep)},
        **res.describe(),
        "simulated_time_s": sim,
        "wall_time_s": wall,
        "realtime_factor": sim / wall if wall > 0 else None,
        "mujoco_solver_capped_share": hand.scene.solver_capped_share,
        "mujoco_newton_share": hand.scene.newton_share,
    }
    return Execution(
        plan,
        res,
        cfg,
        lines,
        pictures.snapshots,
        facets,
        doc,
        build_mjcf(hand.scene.spec),
        images=pictures.images,
        event_times=pictures.times,
    )
