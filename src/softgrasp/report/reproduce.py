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
execute`` also reads). The files replace the folder's earlier ones whole, once every step has run
(:mod:`softgrasp.io.runfolder`): an interrupted run leaves them as they were.

A step that fails (``NotConverged``, ``InfeasibleGrasp``, any error) is recorded as failed with
its message and the run continues; the execution is *skipped*, with the reason, when MuJoCo
cannot be imported or there is no plan to execute. Nothing is tuned to match the paper: where
softgrasp's numbers differ from it, the report says so and why.
"""

from __future__ import annotations

import os
import platform
import time
import traceback
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from softgrasp import __version__
from softgrasp.errors import ConfigError, SoftgraspError
from softgrasp.io.atomic import write_json, write_text
from softgrasp.report.compression import PAPER_TABLE1, run_compression
from softgrasp.report.context import Context, Progress, Settings, Skipped, jsonable, linear_solver
from softgrasp.report.document import render_html, render_markdown
from softgrasp.report.execution import run_execution
from softgrasp.report.grasp import PAPER_TABLE2, run_grasp
from softgrasp.report.indentation import run_indentation
from softgrasp.report.summary import report_blocks

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
#: The reproduced paper.
PAPER_TITLE = "Model-based strategy for grasping 3D deformable objects using a multi-fingered robotic hand"
#: Schema of ``reproduce.json``.
SCHEMA = "softgrasp.reproduce/1"
#: Relative cost of each step (for the progress fraction).
_WEIGHTS = {
    "compression_cube": 1.5,
    "compression_sphere": 1.5,
    "indentation_cube": 1.5,
    "grasp_sphere": 3.0,
    "execution_sphere": 10.0,
    "report": 0.5,
}


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
        "linear solver": linear_solver(),
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
    from softgrasp.io.runfolder import run_folder

    names = _selection(experiments)
    with run_folder(out, "reproduce") as folder:
        return _reproduce(folder.stage, Path(out), quick, progress, names)


def _reproduce(
    out: Path,
    final: Path,
    quick: bool,
    progress: Callable[[float, str], None] | None,
    names: list[str],
) -> ReproductionResult:
    """:func:`reproduce` writing into ``out`` (a staging folder) what ends up in ``final``."""
    t_start = time.perf_counter()
    ctx = Context(out, Settings.of(quick))
    total = sum(_WEIGHTS[n] for n in names) + _WEIGHTS["report"]
    done = 0.0

    last = [0.0]  # the fraction never goes back, even when a step's own estimate does

    def report_progress(fraction: float, step: str) -> None:
        last[0] = min(1.0, max(last[0], fraction))
        if progress is not None:
            progress(last[0], step)

    runners: dict[str, Callable[[dict[str, Any], Progress], None]] = {
        "compression_cube": lambda rec, p: run_compression(ctx, rec, p, "cube"),
        "compression_sphere": lambda rec, p: run_compression(ctx, rec, p, "sphere"),
        "indentation_cube": lambda rec, p: run_indentation(ctx, rec, p),
        "grasp_sphere": lambda rec, p: run_grasp(ctx, rec, p),
        "execution_sphere": lambda rec, p: run_execution(ctx, rec, p),
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
        except Skipped as exc:
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
            StepRecord(
                name, EXPERIMENTS[name], status, wall, message, tuple(final / f for f in figs.values())
            )
        )
        done += w
        report_progress(done / total, name)

    report_progress(done / total, "report")
    t_report = time.perf_counter()
    doc: dict[str, Any] = {
        "schema": SCHEMA,
        "softgrasp_version": __version__,
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
    render_html(report_blocks(doc), out)
    doc["run"]["report_wall_time_s"] = time.perf_counter() - t_report
    doc["run"]["wall_time_s"] = time.perf_counter() - t_start
    blocks = report_blocks(doc)
    write_text(out / "report.md", render_markdown(blocks))
    write_text(out / "report.html", render_html(blocks, out))
    write_json(out / "reproduce.json", jsonable(doc))
    wall = time.perf_counter() - t_start
    report_progress(1.0, "report")
    return ReproductionResult(
        out=final,
        quick=bool(quick),
        steps=tuple(records),
        report_md=final / "report.md",
        report_html=final / "report.html",
        data_json=final / "reproduce.json",
        wall_time_s=wall,
        document=doc,
    )
