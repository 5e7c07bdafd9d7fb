"""Robust set-points of a saved plan: the set-points that hold the object for every sampled value
of uncertain parameters (or a quantile of the samples), what ``softgrasp plan --uncertain`` adds.

:func:`uncertain_parameters` reads and checks the ranges (before the nominal plan runs);
:func:`robust_plan` samples them around a plan written by :meth:`Plan.save
<softgrasp.api.planning.Plan.save>`, writes ``robust.json``, ``robust.png`` and the stages'
tables under ``robust/``, and writes ``plan.json`` again with the robust set-points (the nominal
ones kept beside them).
"""

from __future__ import annotations

import copy
import shutil
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from softgrasp import __version__
from softgrasp.api.objects import SoftObject
from softgrasp.api.planning import Plan
from softgrasp.errors import ConfigError

__all__ = ["ROBUST_DEFAULTS", "uncertain_parameters", "robust_plan"]

#: Defaults of the robust options: samples, seed of their draw, local worker processes.
ROBUST_DEFAULTS = {"samples": 64, "seed": 0, "workers": 2}


def uncertain_parameters(
    obj: SoftObject,
    mu: float,
    ranges: Sequence[str],
    *,
    samples: int = 64,
    quantile: float | None = None,
    workers: int = 2,
) -> list[Any]:
    """The uncertain parameters ``ranges`` (``NAME=LOW..HIGH``, ``NAME=±P%``, ``NAME=±D``; names
    ``mu``, ``E``, ``nu``, ``density``, ``mass``, ``a2``, ``a3``) around the nominal values of
    ``obj`` and friction ``mu``, with the sampling options checked."""
    from softgrasp.sweep.robust import nominal_values, parse_uncertain

    nominal = nominal_values(obj.body, mu)
    found = [parse_uncertain(text, nominal) for text in ranges]
    names = [u.name for u in found]
    if len(set(names)) != len(names):
        raise ConfigError(f"--uncertain gives a parameter twice: {', '.join(names)}")
    if not 2 <= samples <= 100_000:
        raise ConfigError(f"--samples must be from 2 to 100000, got {samples}")
    if quantile is not None and not 0 < quantile < 1:
        raise ConfigError(f"--quantile must lie between 0 and 1 (e.g. 0.9), got {quantile}")
    if not 1 <= workers <= 256:
        raise ConfigError(f"--workers must be from 1 to 256, got {workers}")
    return found


def robust_plan(
    plan: Plan,
    uncertain: Sequence[Any],
    *,
    samples: int = 64,
    seed: int = 0,
    quantile: float | None = None,
    workers: int = 2,
    scheduler: str | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> Any:
    """Robust set-points around ``plan``, already saved (:meth:`Plan.save`): every sample closes
    from the contacts of its ``plan.json``; the stages' tables go to ``robust/``, with
    ``robust.json``, ``robust.png`` and the updated ``plan.json``: all of them replace the folder's
    earlier ones together once complete (:mod:`softgrasp.io.runfolder`), so a failed or
    interrupted run leaves the earlier robust set-points as they were.
    Returns the :class:`~softgrasp.sweep.robust.RobustResult` (its stages in ``robust/``)."""
    import numpy as np

    from softgrasp.io.atomic import write_json
    from softgrasp.io.runfolder import run_folder
    from softgrasp.sweep.robust import robust_setpoints
    from softgrasp.viz.plots import plot_robust

    if plan.directory is None:
        raise ConfigError("robust set-points start from a saved plan: call plan.save(DIR) first")
    out = plan.directory
    if not isinstance(plan.options["material"], str | None):
        raise ConfigError("robust set-points need the object and material named as text")
    options = {k: v for k, v in plan.options.items() if k not in ("out", "grasp")}
    for key in ("object", "material", "hand"):  # files named for the workers wherever they run
        if isinstance(options[key], str) and Path(options[key]).is_file():
            options[key] = str(Path(options[key]).resolve())
    with run_folder(out, "plan", complete=False) as folder:
        stage = folder.stage
        # The plan saved in this run (inside ``softgrasp plan``, not moved into place yet), else
        # the one in the folder.
        nominal = stage / "plan.json" if (stage / "plan.json").is_file() else out / "plan.json"
        work = stage / "robust"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        res = robust_setpoints(
            options,
            nominal.resolve(),
            [float(v) for v in plan.grasp.setpoints],
            list(uncertain),
            work,
            samples=samples,
            seed=seed,
            quantile=quantile,
            workers=workers,
            scheduler=scheduler,
            progress=progress,
            fingers=[str(f["name"]) for f in plan.document["fingers"]],
        )
        res = replace(res, stages={k: str(out / "robust" / Path(v).name) for k, v in res.stages.items()})
        summary = res.describe()
        summary["stages"] = {k: f"robust/{Path(v).name}" for k, v in res.stages.items()}  # from the folder
        per_sample = summary.pop("per_sample")
        doc = copy.deepcopy(plan.document)
        for j, f in enumerate(doc["fingers"]):
            f["nominal_setpoint_N"] = f["setpoint_N"]
            f["setpoint_N"] = doc["setpoints_N"][f["name"]] = float(res.setpoints[j])
        doc["setpoints"] = "robust" if res.achieved else "robust (goal not met)"
        doc["robust"] = {
            **summary,
            "note": "setpoints_N and each finger's setpoint_N are the robust set-points; the fingers' "
            "other fields (force, penetration, final position) and the equilibrium are the nominal "
            "plan's held state",
        }
        write_json(
            stage / "robust.json",
            {
                "schema": "softgrasp.robust/1",
                "softgrasp_version": __version__,
                **summary,
                "per_sample": per_sample,
            },
        )
        write_json(stage / "plan.json", doc)
        plot_robust(
            stage / "robust.png",
            {u.name: np.array([s[u.name] for s in res.samples]) for u in res.uncertain},
            res.required.sum(axis=1),
            res.nominal_held,
            robust_total=float(res.setpoints.sum()),
            nominal_total=float(res.nominal.sum()),
            title=f"Robust set-points over {len(res.samples)} samples"
            + ("" if res.quantile is None else f" ({res.quantile:.0%} to hold)"),
        )
    plan.document.clear()
    plan.document.update(doc)
    return res
