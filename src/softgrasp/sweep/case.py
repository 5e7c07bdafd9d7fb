"""One case of a sweep: a plan (and optionally its execution) turned into one table row.

:func:`run_case` never raises for a case's own failure (a bad material, an unreachable grasp, a
solve that does not converge, a crash): the row says ``failed`` with the error message, so that
one bad case never stops a sweep.
"""

from __future__ import annotations

import math
import tempfile
import time
import traceback
from collections.abc import Mapping, Sequence
from pathlib import Path

from softgrasp.errors import ConfigError, SoftgraspError
from softgrasp.hand.reach import GRASP_FINGERS

__all__ = [
    "FINGERS",
    "OUTPUTS",
    "EXECUTE_OUTPUTS",
    "HOLD_OUTPUTS",
    "run_case",
    "output_columns",
    "plan_outputs",
    "hold_outputs",
]

#: The default hand's fingers (thumb, first, middle); a sweep's rows name its own hand's fingers
#: (:attr:`softgrasp.sweep.spec.SweepSpec.fingers`: ``left`` and ``right`` for a gripper).
FINGERS: tuple[str, ...] = GRASP_FINGERS[0]

#: The first output columns of every case: its outcome and its object.
_CASE: tuple[str, ...] = ("status", "error", "error_type", "wall_time_s", "nodes", "mass_kg")


def plan_outputs(fingers: Sequence[str] = FINGERS) -> tuple[str, ...]:
    """Output columns of a planned case (SI units in the names), per finger of ``fingers``."""
    return (
        *_CASE,
        "travel_m",
        "increments",
        *(f"setpoint_{f}_N" for f in fingers),
        *(f"force_{f}_N" for f in fingers),
        *(f"penetration_{f}_m" for f in fingers),
        "setpoint_sum_N",
        "friction_margin",
        "rigid_utilisation",
        "force_residual_N",
        "hold_drift_m",
    )


def hold_outputs(fingers: Sequence[str] = FINGERS) -> tuple[str, ...]:
    """Output columns of a case that checks given set-points (force-controlled closing and
    hold), per finger of ``fingers``."""
    return (
        *_CASE,
        "held",
        "hold_reason",
        "increments",
        *(f"reached_{f}_N" for f in fingers),
        *(f"travel_{f}_m" for f in fingers),
        *(f"penetration_{f}_m" for f in fingers),
        *(f"held_{f}_N" for f in fingers),
        "friction_margin",
        "hold_drift_m",
    )


#: Output columns of every case of the default hand.
OUTPUTS: tuple[str, ...] = plan_outputs()

#: Extra columns when the sweep executes each plan on the simulated hand.
EXECUTE_OUTPUTS: tuple[str, ...] = ("reached", "lifted", "slip_m", "rise_m", "execute_wall_time_s")

#: Output columns of a case of the default hand that checks given set-points.
HOLD_OUTPUTS: tuple[str, ...] = hold_outputs()


def output_columns(execute: bool, hold: bool = False, fingers: Sequence[str] = FINGERS) -> tuple[str, ...]:
    """The output columns of a sweep's rows (a plan's, with its execution's; or a hold check's)
    for a hand with the fingers ``fingers``."""
    if hold:
        return hold_outputs(fingers)
    return plan_outputs(fingers) + (EXECUTE_OUTPUTS if execute else ())


def _failed(row: dict[str, object], exc: BaseException, t0: float) -> dict[str, object]:
    msg = str(exc) if isinstance(exc, SoftgraspError) else f"{type(exc).__name__}: {exc}"
    if not isinstance(exc, SoftgraspError):
        tb = traceback.format_exception(type(exc), exc, exc.__traceback__)
        msg += " | " + tb[-2].strip().replace("\n", " ") if len(tb) > 1 else ""
    row.update(status="failed", error=msg, error_type=type(exc).__name__)
    row["wall_time_s"] = time.perf_counter() - t0
    return row


def run_case(
    options: Mapping[str, object],
    execute: bool = False,
    hold: Sequence[float] | None = None,
    fingers: Sequence[str] = FINGERS,
) -> dict[str, object]:
    """Plan one case (and execute it when asked), or check set-points on it, and return its
    outputs as a row.

    Parameters
    ----------
    options: the case's options (:mod:`softgrasp.sweep.spec`): plan options over the defaults and
        material parameters over the object's material.
    execute: also execute the plan on the simulated MuJoCo hand (lift and hold).
    hold: normal-force set-points [N], one per finger: instead of planning, close the fingers to
        them under force control and check the hold
        (:func:`softgrasp.grasp.force_control.hold_setpoints`).
    fingers: the fingers the row's columns name (the sweep's hand's, opposing finger first); a
        case whose hand plans with other fingers fails with a ConfigError saying so.

    Returns
    -------
    The output columns (:func:`output_columns`): ``status`` ``ok`` or ``failed``, ``error`` (empty
    or the message), ``error_type`` (the exception's class: ``InfeasibleGrasp``, ``NotConverged``
    ...), and the figures (NaN where a failed case has none).
    """
    from softgrasp.grasp.planner import plan_grasp
    from softgrasp.io.options import contact_params, load_body, material_file, plan_config
    from softgrasp.model.ranges import check_units
    from softgrasp.sweep.spec import split_options

    t0 = time.perf_counter()
    fingers = tuple(fingers)
    row: dict[str, object] = {c: math.nan for c in output_columns(execute, hold is not None, fingers)}
    row.update(status="ok", error="", error_type="")
    try:
        plan_opts, material = split_options(options)
        mf = material_file(plan_opts["material"])  # type: ignore[arg-type]
        body = load_body(
            str(plan_opts["object"]),
            plan_opts["mesh_size"],  # type: ignore[arg-type]
            plan_opts["material"],  # type: ignore[arg-type]
            reorient=bool(plan_opts.get("reorient", False)),
            mfile=mf,
            overrides=material,
            scale=check_units(plan_opts.get("units", "m")),
            volume=str(plan_opts.get("volume_term", "element")),
        )
        mu = plan_opts["mu"] if "mu" in options or mf is None or "mu" not in mf.contact else None
        law = str(plan_opts.get("contact_law", "resolved"))
        config = plan_config(plan_opts, contact_params(mf, mu, law=law))  # type: ignore[arg-type]
        if tuple(config.fingers) != fingers:
            raise ConfigError(
                f"the case's hand plans with the fingers {', '.join(config.fingers)}, the sweep's columns "
                f"name {', '.join(fingers)}: sweep hands with other fingers apart"
            )
        if hold is not None:
            row.update(_hold(body, config, hold))
            row["wall_time_s"] = time.perf_counter() - t0
            return row
        plan = plan_grasp(body, config)
        row.update(
            nodes=int(body.n_nodes),
            mass_kg=float(body.total_mass),
            travel_m=float(plan.travel[-1]) if len(plan.travel) else math.nan,
            increments=int(plan.increments),
            friction_margin=float(plan.friction_margin),
            rigid_utilisation=float(plan.rigid_utilisation),
            force_residual_N=float(plan.force_residual),
            hold_drift_m=float(plan.com_drift),
        )
        for name, f, sp in zip(fingers, plan.fingers, plan.setpoints, strict=True):
            row[f"setpoint_{name}_N"] = float(sp)
            row[f"force_{name}_N"] = float(math.sqrt(float(f.force @ f.force)))
            row[f"penetration_{name}_m"] = float(f.penetration)
        row["setpoint_sum_N"] = float(plan.setpoints.sum())
        if execute:
            te = time.perf_counter()
            row.update(_execute(plan, body))
            row["execute_wall_time_s"] = time.perf_counter() - te
    except Exception as exc:  # noqa: BLE001 - a case's failure is data, never the sweep's end
        return _failed(row, exc, t0)
    row["wall_time_s"] = time.perf_counter() - t0
    return row


def _hold(body, config, setpoints: Sequence[float]) -> dict[str, object]:
    """The hold check of ``setpoints`` as row values."""
    from softgrasp.grasp.force_control import hold_setpoints

    res = hold_setpoints(body, config, tuple(float(v) for v in setpoints))
    row: dict[str, object] = {
        "nodes": int(body.n_nodes),
        "mass_kg": float(body.total_mass),
        "held": bool(res.held),
        "hold_reason": res.reason,
        "increments": int(res.increments),
        "friction_margin": float(res.friction_margin),
        "hold_drift_m": float(res.drift),
    }
    for j, name in enumerate(config.fingers):
        row[f"reached_{name}_N"] = float(res.reached[j])
        row[f"travel_{name}_m"] = float(res.travel[j])
        row[f"penetration_{name}_m"] = float(res.penetration[j])
        row[f"held_{name}_N"] = float(res.held_normal[j])
    return row


def _execute(plan, body) -> dict[str, object]:
    """Execute a plan on the simulated hand: through a plan file, as ``softgrasp execute`` does."""
    from softgrasp.execution.controller import ExecuteConfig, closing_lines, execute_plan
    from softgrasp.execution.mujoco.hand import MujocoHand
    from softgrasp.io.atomic import write_json
    from softgrasp.io.plan_document import plan_document
    from softgrasp.io.planfile import load_plan_file
    from softgrasp.model.mesh.io import save_mesh
    from softgrasp.model.mesh.tetmesh import TetMesh

    with tempfile.TemporaryDirectory(prefix="softgrasp-case-") as tmp:
        d = Path(tmp)
        save_mesh(TetMesh(plan.placed, body.mesh.tets, name=body.mesh.name), d / "object.vtu")
        doc = plan_document(plan, body, body.mesh.name)
        doc["object"]["mesh_file"] = "object.vtu"
        write_json(d / "plan.json", doc)
        pf = load_plan_file(d / "plan.json")
        hand = MujocoHand.from_plan(pf)
        res = execute_plan(hand, closing_lines(pf), ExecuteConfig(), palm_to_world=hand.palm_to_world)
    return {"reached": bool(res.reached), "lifted": bool(res.lifted), "slip_m": res.slip, "rise_m": res.rise}
