"""Robust set-points: forces that hold the object for every sampled value of its uncertain
parameters (friction, stiffness, mass ...), not only for the nominal ones.

Given the nominal plan (its contacts and closing lines) and the uncertain parameters' ranges:

1. **samples**: ``samples`` parameter sets drawn uniformly from the ranges (seeded), each planned
   from the nominal plan's initial grasp (same contacts and closing lines): the set-points that
   sample needs (:func:`softgrasp.grasp.planner.plan_grasp`);
2. **robust set-points**: per finger, the largest of the samples' set-points (or their
   ``quantile``, taken as the next sample up: a value some sample needed, so that ``quantile``
   0.9 of 10 samples is their largest); a sample the fingers cannot hold at all (no hold before
   the crushing limit) needs infinite force;
3. **check**: on every sample, the fingers close under force control to the robust set-points
   and the table is taken away (:func:`softgrasp.grasp.force_control.hold_setpoints`). A plan's
   set-points are the normal forces of its *held* state, while a force-controlled hand reaches
   them on the table, where the same squeeze reads higher (on the default sphere 0.48 N on the
   table for 0.34 N held): closing to the held-state forces stops short of the plan's travel.
   That is how ``execute`` uses set-points too, and the check is what decides: until the
   object is held on every sample (or the quantile's share of them), the set-points are raised
   by ``RAISE`` and checked again: at most ``MAX_ROUNDS`` checks in all;
4. the nominal plan's set-points are checked on every sample the same way (how often they fail);
5. **drivers**: Spearman's rank correlation of each uncertain parameter with the samples' total
   set-point: which parameter the force depends on, and which way.

Every stage runs on the sweep engine (:func:`softgrasp.sweep.engine.run_sweep`, Dask), so that
each stage's table (``results.csv`` / ``.parquet``) is written as it runs.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError, InfeasibleGrasp
from softgrasp.hand.reach import GRASP_FINGERS
from softgrasp.model.ranges import RANGES

__all__ = [
    "UNCERTAIN",
    "Uncertain",
    "RobustPlan",
    "parse_uncertain",
    "nominal_values",
    "robust_setpoints",
    "sample_requirements",
    "MAX_ROUNDS",
    "RAISE",
]

#: Parameters that may be uncertain: fingertip friction and the material parameters.
UNCERTAIN = ("mu", "E", "nu", "density", "mass", "a2", "a3")
#: Factor by which the set-points are raised after a check in which too few samples were held.
RAISE = 1.25
#: Checks of the set-points (the first and the raised ones) before giving up.
MAX_ROUNDS = 4
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


@dataclass(frozen=True)
class Uncertain:
    """One uncertain parameter: sampled uniformly in [low, high] (SI units)."""

    name: str
    low: float
    high: float
    text: str = ""

    def describe(self) -> dict[str, object]:
        return {"name": self.name, "low": self.low, "high": self.high, "given": self.text}


def parse_uncertain(text: str, nominal: Mapping[str, float]) -> Uncertain:
    """Parse ``NAME=LOW..HIGH``, ``NAME=±P%`` (or ``+-P%``: relative to the nominal value) or
    ``NAME=±D`` (the nominal value ± D) for a parameter of :data:`UNCERTAIN`.

    Raises ConfigError naming what is wrong: an unknown parameter, a malformed range, low >= high,
    or a range outside the parameter's physical bounds (nu < 0.5, E > 0 ...)."""
    if "=" not in text:
        raise ConfigError(f"--uncertain {text!r}: give NAME=LOW..HIGH or NAME=±P% (e.g. mu=0.4..0.8, E=±20%)")
    name, spec = (part.strip() for part in text.split("=", 1))
    if name not in UNCERTAIN:
        raise ConfigError(
            f"--uncertain {text!r}: {name!r} is not an uncertain parameter; use one of {', '.join(UNCERTAIN)}"
        )
    spec = spec.replace(" ", "")
    rng = re.fullmatch(rf"({_NUMBER})\.\.({_NUMBER})", spec)
    rel = re.fullmatch(rf"(?:±|\+-|\+/-)({_NUMBER})(%?)", spec)
    if rng:
        low, high = float(rng.group(1)), float(rng.group(2))
    elif rel:
        d = float(rel.group(1))
        base = float(nominal[name])
        if rel.group(2):
            if not 0 < d < 100:
                raise ConfigError(f"--uncertain {text!r}: the percentage must lie between 0 and 100")
            d = abs(base) * d / 100.0
        low, high = base - d, base + d
    else:
        raise ConfigError(
            f"--uncertain {text!r}: {spec!r} is not a range; give LOW..HIGH, ±P% or ±D "
            "(e.g. mu=0.4..0.8, E=±20%)"
        )
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise ConfigError(f"--uncertain {text!r}: the range needs LOW < HIGH, got {low:g}..{high:g}")
    bounds = RANGES[name]  # the parameter's physical range
    if not (bounds.contains(low) and bounds.contains(high)):
        raise ConfigError(
            f"--uncertain {text!r}: {name} must stay in {bounds.text}; the range is {low:g}..{high:g}"
        )
    return Uncertain(name, low, high, text)


def nominal_values(body, mu: float) -> dict[str, float]:
    """The nominal value of each parameter of :data:`UNCERTAIN` for ``body`` and friction ``mu``."""
    m = body.material
    law = m.law.describe()
    return {
        "mu": float(mu),
        "E": float(m.E),
        "nu": float(m.nu),
        "density": float(m.density) if m.density is not None else float(body.density),
        "mass": float(body.total_mass),
        "a2": float(law.get("a2", 0.0)),
        "a3": float(law.get("a3", 0.0)),
    }


@dataclass(frozen=True)
class RobustPlan:
    """Robust set-points and how they were found.

    Attributes
    ----------
    uncertain: the uncertain parameters.  quantile: None (hold every sample) or the share to hold.
    fingers: the plan's fingers (F of them, opposing finger first), the columns' order below.
    samples: each sample's parameter values, (S,) dicts.
    required: each sample's planned set-points [N], (S, F) (inf where the sample cannot be held at
        all; ``sample_errors`` says why).
    sample_errors: per sample, "" or why its plan failed.
    nominal: the nominal plan's set-points [N], (F,).
    setpoints: the robust set-points [N], (F,).
    scale: the factor of the last check over the samples' largest (or quantile) set-points (1, or
        raised by :data:`RAISE` per failed check).
    held: per sample, whether the robust set-points held it, (S,).
    reasons: per sample, "held" or why not.
    drift: per sample, the centre of mass's motion in the hold [m] (nan where not held).
    friction_margin: per sample, the friction margin of the held state (nan where not held).
    nominal_held, nominal_reasons: the nominal set-points' check on every sample.
    drivers: (parameter, Spearman rho with the samples' total set-point), by decreasing |rho|
        (nan when the samples do not vary it enough to rank).
    rounds: checks of the robust set-points.  achieved: the goal (every sample or the quantile's
        share held) was met.  wall_time: seconds.
    stages: the folder of each stage's table (``samples``, ``nominal``, ``robust-1`` ...).
    """

    uncertain: tuple[Uncertain, ...]
    quantile: float | None
    fingers: tuple[str, ...]
    samples: list[dict[str, float]]
    required: NDArray[np.float64]
    sample_errors: list[str]
    nominal: NDArray[np.float64]
    setpoints: NDArray[np.float64]
    scale: float
    held: NDArray[np.bool_]
    reasons: list[str]
    drift: NDArray[np.float64]
    friction_margin: NDArray[np.float64]
    nominal_held: NDArray[np.bool_]
    nominal_reasons: list[str]
    drivers: list[tuple[str, float]]
    rounds: int
    achieved: bool
    wall_time: float
    stages: dict[str, str] = field(default_factory=dict)

    @property
    def held_fraction(self) -> float:
        return float(self.held.mean())

    @property
    def nominal_failure_fraction(self) -> float:
        return float(1.0 - self.nominal_held.mean())

    @property
    def goal(self) -> float:
        """Share of the samples that must be held."""
        return 1.0 if self.quantile is None else self.quantile

    def describe(self) -> dict[str, object]:
        """JSON-ready summary (SI units)."""
        finite = np.isfinite(self.required).all(axis=1)
        ratio = self.setpoints[None, :] / np.where(finite[:, None], self.required, np.nan)
        return {
            "uncertain": [u.describe() for u in self.uncertain],
            "samples": len(self.samples),
            "quantile": self.quantile,
            "goal_held_fraction": self.goal,
            "achieved": self.achieved,
            "fingers": list(self.fingers),
            "setpoints_N": dict(zip(self.fingers, map(float, self.setpoints), strict=True)),
            "nominal_setpoints_N": dict(zip(self.fingers, map(float, self.nominal), strict=True)),
            "scale_over_samples": self.scale,
            "rounds": self.rounds,
            "held_fraction": self.held_fraction,
            "nominal_failure_fraction": self.nominal_failure_fraction,
            "smallest_friction_margin": _nanmin(self.friction_margin),
            "largest_drift_m": _nanmax(self.drift),
            "smallest_force_ratio": _nanmin(ratio.min(axis=1)) if finite.any() else None,
            "drivers": [{"parameter": n, "spearman_rho": _finite_or_none(r)} for n, r in self.drivers],
            "per_sample": [
                {
                    **s,
                    "required_N": [_finite_or_none(v) for v in self.required[i]],
                    "plan_error": self.sample_errors[i],
                    "robust_held": bool(self.held[i]),
                    "robust_result": self.reasons[i],
                    "robust_drift_m": _finite_or_none(self.drift[i]),
                    "robust_friction_margin": _finite_or_none(self.friction_margin[i]),
                    "nominal_held": bool(self.nominal_held[i]),
                    "nominal_result": self.nominal_reasons[i],
                }
                for i, s in enumerate(self.samples)
            ],
            "stages": self.stages,
            "wall_time_s": self.wall_time,
        }


def _finite_or_none(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _nanmin(a: NDArray[np.float64]) -> float | None:
    a = a[np.isfinite(a)]
    return float(a.min()) if len(a) else None


def _nanmax(a: NDArray[np.float64]) -> float | None:
    a = a[np.isfinite(a)]
    return float(a.max()) if len(a) else None


def _spearman(x: NDArray[np.float64], y: NDArray[np.float64]) -> float:
    """Spearman's rank correlation of x and y over the finite pairs (nan for fewer than 3 or no
    spread)."""
    from scipy.stats import spearmanr

    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
        return math.nan
    return float(spearmanr(x[ok], y[ok]).statistic)


def _quantile(required: NDArray[np.float64], q: float | None) -> NDArray[np.float64]:
    """Per finger, the largest required set-point or its q-quantile (the next sample up: a
    set-point some sample actually needed), (F,)."""
    if q is None:
        return required.max(axis=0)
    return np.quantile(required, q, axis=0, method="higher")


def sample_requirements(
    rows: Sequence[Mapping[str, object]],
    options: Sequence[Mapping[str, object]],
    names: Sequence[str],
    fingers: Sequence[str] = GRASP_FINGERS[0],
) -> tuple[NDArray[np.float64], list[str]]:
    """The set-points each sample needs, (S, F) for the F ``fingers`` (inf for a sample the
    fingers cannot hold at all: its plan failed with ``InfeasibleGrasp``), and each sample's error
    ("" when planned).

    Raises NotConverged when a sample's plan failed for another reason (a solve that did not
    converge, a lost worker, a missing file): that is no verdict on the grasp, and a robust
    set-point cannot skip the sample."""
    from softgrasp.errors import NotConverged

    required = np.full((len(rows), len(fingers)), math.inf)
    errors = []
    for i, r in enumerate(rows):
        if r["status"] == "ok":
            required[i] = [float(r[f"setpoint_{f}_N"]) for f in fingers]  # type: ignore[arg-type]
            errors.append("")
        elif r.get("error_type") == "InfeasibleGrasp":
            errors.append(str(r["error"]))
        else:
            where = ", ".join(f"{n} = {float(options[i][n]):.4g}" for n in names)  # type: ignore[arg-type]
            raise NotConverged(
                f"sample {i} ({where}) could not be planned, for a reason other than grip: {r['error']}; "
                "its set-points are unknown (a finer --step or --refine may let the solve converge)"
            )
    return required, errors


def _unholdable(
    required: NDArray[np.float64],
    errors: Sequence[str],
    options: Sequence[Mapping[str, object]],
    names: Sequence[str],
    quantile: float | None,
) -> str:
    """Why no robust set-points exist: the samples no set-point holds, and the largest quantile
    that would leave them out."""
    n = len(required)
    bad = [i for i in range(n) if not np.isfinite(required[i]).all()]
    where = "; ".join(
        f"sample {i} ({', '.join(f'{k} = {float(options[i][k]):.4g}' for k in names)}): {errors[i]}"  # type: ignore[arg-type]
        for i in bad[:3]
    )
    text = f"{len(bad)} of {n} samples cannot be held by any set-points on these contacts ({where}); "
    ok = n - len(bad)
    if ok == 0:
        return text + "narrow the ranges of the uncertain parameters"
    # np.quantile(..., method="higher") picks a finite value only up to the share (ok - 1) / (n - 1).
    q_max = math.floor(1000 * (ok - 1) / (n - 1)) / 1000  # rounded down: printed, it must still do
    if q_max <= 0:
        return text + "narrow the ranges of the uncertain parameters"
    return text + f"narrow the ranges, or hold a share of the samples with --quantile {q_max:g} or less"


def _plan_fingers(path: str | Path) -> tuple[str, ...]:
    """The fingers of the plan file ``path`` (its ``fingers[*].name``), in its order."""
    import json

    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
        names = tuple(str(f["name"]) for f in doc["fingers"])
    except (OSError, ValueError, KeyError, TypeError):
        raise ConfigError(f"plan file {path}: field 'fingers' must list the plan's fingers by name") from None
    if not names:
        raise ConfigError(f"plan file {path}: field 'fingers' lists no finger")
    return names


def robust_setpoints(
    options: Mapping[str, object],
    grasp_file: str | Path,
    nominal: Sequence[float],
    uncertain: Sequence[Uncertain],
    out: str | Path,
    *,
    samples: int = 64,
    seed: int = 0,
    quantile: float | None = None,
    workers: int = 2,
    scheduler: str | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    fingers: Sequence[str] | None = None,
) -> RobustPlan:
    """Robust set-points over ``uncertain`` parameters (module docstring).

    Parameters
    ----------
    options: the nominal plan's options (:mod:`softgrasp.sweep.spec` options: object, material,
        mesh size, mu, planner settings); each sample sets its uncertain parameters over them.
    grasp_file: the nominal ``plan.json`` (its initial grasp: every sample closes on the same
        contacts along the same lines).
    nominal: the nominal plan's set-points [N], one per finger.
    uncertain: the uncertain parameters (:func:`parse_uncertain`), each at most once.
    out: folder of the stages' tables.
    samples, seed: number of parameter sets and the seed of their draw.
    quantile: None to hold every sample, or the share of samples to hold, in (0, 1).
    workers, scheduler: the Dask cluster (:func:`softgrasp.sweep.engine.run_sweep`).
    progress: called with (stage, finished cases, cases).
    fingers: the nominal plan's fingers, in the order of ``nominal`` (default: those of
        ``grasp_file``).

    Raises
    ------
    ConfigError: no or repeated uncertain parameters, fewer than 2 samples, a bad quantile.
    InfeasibleGrasp: samples (more than the quantile allows) that no set-points can hold: the
        fingers reach the crushing limit before the object is held.
    NotConverged: a sample that could not be planned for another reason
        (:func:`sample_requirements`).
    """
    from softgrasp.sweep.engine import dask_client, run_sweep
    from softgrasp.sweep.spec import SweepSpec, sweep_cases

    t0 = time.perf_counter()
    names = [u.name for u in uncertain]
    if not names:
        raise ConfigError("robust set-points need at least one --uncertain parameter")
    if len(set(names)) != len(names):
        raise ConfigError(f"--uncertain gives a parameter twice: {', '.join(names)}")
    if not 2 <= samples <= 100_000:
        raise ConfigError(f"--samples must be from 2 to 100000, got {samples}")
    if quantile is not None and not 0 < quantile < 1:
        raise ConfigError(f"--quantile must lie between 0 and 1 (e.g. 0.9), got {quantile}")
    nominal = np.asarray(nominal, dtype=np.float64)
    fingers = _plan_fingers(grasp_file) if fingers is None else tuple(fingers)
    if nominal.shape != (len(fingers),):
        raise ConfigError(
            f"the nominal set-points {nominal.tolist()} must be one per finger ({', '.join(fingers)})"
        )
    out = Path(out)
    base = {k: v for k, v in options.items() if k not in names}
    base["grasp"] = str(Path(grasp_file).resolve())
    spec = SweepSpec(
        mode="random",
        samples=samples,
        seed=seed,
        execute=False,
        base=base,
        random={u.name: (u.low, u.high, False) for u in uncertain},
        source="softgrasp plan --uncertain",
        fingers=fingers,
    )
    cases = sweep_cases(spec)
    stages: dict[str, str] = {}

    def stage(client, name: str, hold: NDArray[np.float64] | None) -> list[dict[str, object]]:
        s = replace(spec, hold=None if hold is None else tuple(float(v) for v in hold))
        cb = None if progress is None else (lambda done, total: progress(name, done, total))
        res = run_sweep(s, cases, out / name, progress=cb, client=client)
        stages[name] = str(out / name)
        return res.rows

    def held_of(rows: list[dict[str, object]]) -> tuple[NDArray[np.bool_], list[str], NDArray, NDArray]:
        held = np.array([r["status"] == "ok" and r["held"] is True for r in rows])
        reasons = [str(r["hold_reason"]) if r["status"] == "ok" else f"failed: {r['error']}" for r in rows]
        drift = np.array([float(r["hold_drift_m"]) for r in rows])  # type: ignore[arg-type]
        margin = np.array([float(r["friction_margin"]) for r in rows])  # type: ignore[arg-type]
        return held, reasons, drift, margin

    with dask_client(scheduler, workers) as client:
        rows = stage(client, "samples", None)
        required, errors = sample_requirements(rows, [c.options for c in cases], names, fingers)
        goal = 1.0 if quantile is None else quantile
        base_points = _quantile(required, quantile)
        if not np.isfinite(base_points).all():
            raise InfeasibleGrasp(_unholdable(required, errors, [c.options for c in cases], names, quantile))
        nominal_rows = stage(client, "nominal", nominal)
        nominal_held, nominal_reasons, _, _ = held_of(nominal_rows)
        scale = 1.0
        for rounds in range(1, MAX_ROUNDS + 1):
            setpoints = scale * base_points
            held, reasons, drift, margin = held_of(stage(client, f"robust-{rounds}", setpoints))
            if held.mean() >= goal - 1e-12:
                break
            if rounds < MAX_ROUNDS:
                scale *= RAISE
    params = [{n: float(c.options[n]) for n in names} for c in cases]  # type: ignore[arg-type]
    total = required.sum(axis=1)
    drivers = [(n, _spearman(np.array([p[n] for p in params]), total)) for n in names]
    drivers.sort(key=lambda d: -abs(d[1]) if math.isfinite(d[1]) else 0.0)
    return RobustPlan(
        uncertain=tuple(uncertain),
        quantile=quantile,
        fingers=fingers,
        samples=params,
        required=required,
        sample_errors=errors,
        nominal=nominal,
        setpoints=setpoints,
        scale=scale,
        held=held,
        reasons=reasons,
        drift=drift,
        friction_margin=margin,
        nominal_held=nominal_held,
        nominal_reasons=nominal_reasons,
        drivers=drivers,
        rounds=rounds,
        achieved=bool(held.mean() >= goal - 1e-12),
        wall_time=time.perf_counter() - t0,
        stages=stages,
    )
