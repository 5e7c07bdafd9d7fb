"""Sweep files: which plan options vary, over what, and the cases they make.

A sweep file is TOML::

    [sweep]
    mode = "grid"          # "grid": every combination of [grid]; "random": samples of [random]
    samples = 32           # random: number of cases
    seed = 1               # random: seed of the generator (the same file gives the same cases)
    execute = false        # also execute each plan on the simulated hand (MuJoCo) and lift

    [base]                 # options of every case: any plan option or material parameter
    object = "sphere"
    mesh_size = 0.024

    [grid]                 # grid: a list of values per option
    mu = [0.4, 0.6, 0.8]
    E = [60e3, 80e3, 100e3]

    [random]               # random: [low, high] uniform, or {low = .., high = .., log = true}
    mu = [0.3, 0.9]
    E = { low = 40e3, high = 160e3, log = true }

Options are those of ``softgrasp plan`` (:data:`softgrasp.io.options.PLAN_DEFAULTS`: ``object``,
``material``, ``mesh_size``, ``units``, ``mu``, ``fingertip_radius``, ``step``, ``solver``,
``safety_factor``, ``hold_time``, ``max_squeeze``, ``refine``, ``hand``, ``grasp``) and the
material parameters ``E``
[Pa], ``nu``, ``density`` [kg/m^3], ``mass`` [kg], ``a2``, ``a3`` set over the object's material. SI
units; each value, and each end of a random range, lies in the option's physical range
(:data:`softgrasp.model.ranges.RANGES`). ``grasp`` names a ``plan.json``: every case closes from
its initial grasp.

The results' per-finger columns (``setpoint_<finger>_N`` ...) name the fingers the sweep's hand
plans with: ``thumb``, ``first``, ``middle`` for a three-finger hand, ``left``, ``right`` for a
gripper (``hand = "parallel_jaw"``). The hands of one sweep must plan with the same fingers.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from softgrasp.errors import ConfigError
from softgrasp.hand.reach import GRASP_FINGERS
from softgrasp.io.options import MATERIAL_OVERRIDES, PLAN_DEFAULTS, TEXT_OPTIONS, check_option
from softgrasp.io.tomlfile import read_toml

__all__ = [
    "SweepSpec",
    "Case",
    "OPTIONS",
    "read_sweep",
    "sweep_cases",
    "case_id",
    "split_options",
    "describe_spec",
    "spec_digest",
    "sweep_fingers",
    "MAX_CASES",
]

#: The most cases a sweep may have (grid or random).
MAX_CASES = 1_000_000

#: Options a sweep may set (plan options and material parameters).
OPTIONS: tuple[str, ...] = (
    tuple(k for k in PLAN_DEFAULTS if k not in ("out", "reorient", *MATERIAL_OVERRIDES)) + MATERIAL_OVERRIDES
)
_TEXT = TEXT_OPTIONS


@dataclass(frozen=True)
class Case:
    """One case of a sweep: its index, a stable id (a hash of its options) and its options."""

    index: int
    id: str
    options: dict[str, object]


@dataclass(frozen=True)
class SweepSpec:
    """A parsed sweep file.

    Attributes
    ----------
    mode: ``grid`` or ``random``.  samples, seed: of a random sweep.
    execute: also execute each plan on the simulated hand.
    base: options common to every case.
    grid: per option, its values (grid mode).
    random: per option, (low, high, log) (random mode).
    source: the file.
    hold: normal-force set-points [N], one per finger of ``fingers``: each case then closes its
        fingers to them under force control and checks the hold
        (:func:`softgrasp.grasp.force_control.hold_setpoints`) instead of planning (robust
        set-points are checked so).
    fingers: the fingers the hand plans with, opposing finger first (:func:`sweep_fingers`): the
        names of the results' per-finger columns.
    """

    mode: str
    samples: int
    seed: int
    execute: bool
    base: dict[str, object] = field(default_factory=dict)
    grid: dict[str, list[object]] = field(default_factory=dict)
    random: dict[str, tuple[float, float, bool]] = field(default_factory=dict)
    source: str = "<sweep>"
    hold: tuple[float, ...] | None = None
    fingers: tuple[str, ...] = GRASP_FINGERS[0]

    def __post_init__(self) -> None:
        if self.hold is not None and len(self.hold) != len(self.fingers):
            raise ConfigError(
                f"hold set-points {list(self.hold)} must be one per finger ({', '.join(self.fingers)})"
            )

    @property
    def varied(self) -> tuple[str, ...]:
        """The options that vary between cases, in file order."""
        return tuple(self.grid) if self.mode == "grid" else tuple(self.random)

    @property
    def inputs(self) -> tuple[str, ...]:
        """Every option a case sets: the base ones, then the varied ones."""
        return tuple(k for k in self.base if k not in self.varied) + self.varied


def case_id(options: Mapping[str, object]) -> str:
    """A stable id of a case's options (the key of ``--resume``): 12 hex digits of a SHA-256."""
    text = json.dumps({k: options[k] for k in sorted(options)}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def _check_name(source: str, table: str, name: str) -> None:
    if name not in OPTIONS:
        raise ConfigError(
            f"sweep file {source}: [{table}] {name!r} is not an option; options: {', '.join(OPTIONS)}"
        )


def _check_value(source: str, where: str, name: str, value: object) -> object:
    """A case option's value checked for its kind and physical range (:func:`check_option`)."""
    return check_option(name, value, f"sweep file {source}: {where} {name}")


def read_sweep(path: str | Path) -> SweepSpec:
    """Read and check a sweep file (module docstring). ConfigError says what is wrong and where."""
    source = str(path)
    doc = read_toml(path, "sweep file")
    unknown = sorted(set(doc) - {"sweep", "base", "grid", "random"})
    if unknown:
        raise ConfigError(
            f"sweep file {source}: unknown table(s) {unknown}; use [sweep], [base], [grid], [random]"
        )
    for t in ("sweep", "base", "grid", "random"):
        if t in doc and not isinstance(doc[t], dict):
            raise ConfigError(f"sweep file {source}: {t} must be a table ([{t}])")
    head = doc.get("sweep", {})
    bad = sorted(set(head) - {"mode", "samples", "seed", "execute"})
    if bad:
        raise ConfigError(
            f"sweep file {source}: unknown [sweep] key(s) {bad}; known: mode, samples, seed, execute"
        )
    mode = head.get("mode", "grid" if "grid" in doc else "random")
    if mode not in ("grid", "random"):
        raise ConfigError(f"sweep file {source}: [sweep] mode must be 'grid' or 'random', got {mode!r}")
    samples, seed, execute = head.get("samples", 16), head.get("seed", 0), head.get("execute", False)
    if isinstance(samples, bool) or not isinstance(samples, int) or not 1 <= samples <= MAX_CASES:
        raise ConfigError(
            f"sweep file {source}: [sweep] samples must be an integer from 1 to {MAX_CASES}, got {samples!r}"
        )
    check_option("seed", seed, f"sweep file {source}: [sweep] seed")
    if not isinstance(execute, bool):
        raise ConfigError(f"sweep file {source}: [sweep] execute must be true or false, got {execute!r}")
    base: dict[str, object] = {}
    for k, v in doc.get("base", {}).items():
        _check_name(source, "base", k)
        base[k] = _check_value(source, "[base]", k, v)
    grid: dict[str, list[object]] = {}
    rand: dict[str, tuple[float, float, bool]] = {}
    if mode == "grid":
        if "random" in doc:
            raise ConfigError(f"sweep file {source}: a grid sweep takes [grid], not [random]")
        for k, vals in doc.get("grid", {}).items():
            _check_name(source, "grid", k)
            if not isinstance(vals, list) or not vals:
                raise ConfigError(f"sweep file {source}: [grid] {k} must be a non-empty list of values")
            grid[k] = [_check_value(source, "[grid]", k, v) for v in vals]
        if not grid:
            raise ConfigError(
                f"sweep file {source}: a grid sweep needs a [grid] table with at least one option"
            )
        n = math.prod(len(v) for v in grid.values())
        if n > MAX_CASES:
            sizes = " x ".join(f"{len(v)} {k}" for k, v in grid.items())
            raise ConfigError(
                f"sweep file {source}: the [grid] makes {n} cases ({sizes}), more than {MAX_CASES}; "
                "use fewer values or a random sweep"
            )
    else:
        if "grid" in doc:
            raise ConfigError(f"sweep file {source}: a random sweep takes [random], not [grid]")
        for k, v in doc.get("random", {}).items():
            _check_name(source, "random", k)
            if k in _TEXT or k == "refine":
                raise ConfigError(f"sweep file {source}: [random] {k} is not a number to sample; use a grid")
            if isinstance(v, list) and len(v) == 2:
                lo, hi, log = v[0], v[1], False
            elif isinstance(v, dict) and set(v) <= {"low", "high", "log"} and {"low", "high"} <= set(v):
                lo, hi, log = v["low"], v["high"], v.get("log", False)
            else:
                raise ConfigError(
                    f"sweep file {source}: [random] {k} must be [low, high] or "
                    "{low = .., high = .., log = ..}"
                )
            lo = float(_check_value(source, "[random]", k, lo))  # type: ignore[arg-type]
            hi = float(_check_value(source, "[random]", k, hi))  # type: ignore[arg-type]
            if not lo < hi or (log and lo <= 0):
                raise ConfigError(
                    f"sweep file {source}: [random] {k} needs low < high"
                    + (" and low > 0 (log)" if log else "")
                )
            rand[k] = (lo, hi, bool(log))
        if not rand:
            raise ConfigError(
                f"sweep file {source}: a random sweep needs a [random] table with at least one option"
            )
    fingers = sweep_fingers(base, grid, source)
    return SweepSpec(mode, samples, seed, execute, base, grid, rand, source, fingers=fingers)


def sweep_fingers(
    base: Mapping[str, object], grid: Mapping[str, list[object]] | None = None, source: str = "<sweep>"
) -> tuple[str, ...]:
    """The fingers the hands of a sweep plan with (``base`` options over the defaults, each
    ``grid`` value of ``hand`` and ``fingertips``), opposing finger first. ConfigError names the
    sweep file when a hand cannot be read or two hands plan with different fingers."""
    from softgrasp.io.options import hand_model

    grid = grid or {}
    hands = grid.get("hand") or [base.get("hand", PLAN_DEFAULTS["hand"])]
    tips = grid.get("fingertips") or [base.get("fingertips")]
    radii = grid.get("fingertip_radius") or [base.get("fingertip_radius")]
    found: dict[tuple[str, ...], str] = {}
    for hand_name, mapping in itertools.product(hands, tips):
        try:
            hand = hand_model(str(hand_name), mapping, radii[0])  # type: ignore[arg-type]
            fingers = GRASP_FINGERS[0] if hand is None else tuple(hand.grasp_fingers)
        except ConfigError as exc:
            raise ConfigError(f"sweep file {source}: hand {hand_name!r}: {exc}") from None
        found.setdefault(fingers, str(hand_name))
    if len(found) > 1:
        what = "; ".join(f"{h} plans with {', '.join(f)}" for f, h in found.items())
        raise ConfigError(
            f"sweep file {source}: the hands plan with different fingers ({what}): sweep each hand apart"
        )
    return next(iter(found))


def sweep_cases(spec: SweepSpec) -> list[Case]:
    """The cases of a sweep, in a fixed order (grid: the last option varies fastest; random: the
    samples of a generator seeded with ``seed``)."""
    rows: list[dict[str, object]] = []
    if spec.mode == "grid":
        names = list(spec.grid)
        for combo in itertools.product(*(spec.grid[n] for n in names)):
            rows.append(dict(zip(names, combo, strict=True)))
    else:
        rng = np.random.default_rng(spec.seed)
        for _ in range(spec.samples):
            row: dict[str, object] = {}
            for n, (lo, hi, log) in spec.random.items():
                u = float(rng.random())
                row[n] = (
                    float(math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))))
                    if log
                    else lo + u * (hi - lo)
                )
            rows.append(row)
    cases = []
    for i, row in enumerate(rows):
        options = {**{k: v for k, v in spec.base.items() if k not in row}, **row}
        cases.append(Case(i, case_id(options), options))
    return cases


def split_options(options: Mapping[str, object]) -> tuple[dict[str, object], dict[str, float]]:
    """A case's plan options (over :data:`PLAN_DEFAULTS`) and its material parameters."""
    plan = {k: v for k, v in PLAN_DEFAULTS.items() if k not in MATERIAL_OVERRIDES}
    material: dict[str, float] = {}
    for k, v in options.items():
        if k in MATERIAL_OVERRIDES:
            if v is not None:
                material[k] = float(v)  # type: ignore[arg-type]
        else:
            plan[k] = v
    return plan, material


def describe_spec(spec: SweepSpec) -> dict[str, object]:
    """JSON-ready description of a sweep."""
    return {
        "mode": spec.mode,
        "samples": spec.samples if spec.mode == "random" else None,
        "seed": spec.seed if spec.mode == "random" else None,
        "execute": spec.execute,
        "base": spec.base,
        "grid": spec.grid,
        "random": {k: {"low": lo, "high": hi, "log": log} for k, (lo, hi, log) in spec.random.items()},
        "source": spec.source,
        "hold_setpoints_N": None if spec.hold is None else list(spec.hold),
        "fingers": list(spec.fingers),
    }


def spec_digest(spec: SweepSpec | Mapping[str, object]) -> str:
    """SHA-256 of a sweep's normalised spec (or of its :func:`describe_spec` as ``sweep.json``
    records it): what decides its cases, not how the file spells it (the file's name, the order of
    ``[base]``, the number formats). ``--resume`` continues only the sweep of the same digest."""
    d = describe_spec(spec) if isinstance(spec, SweepSpec) else spec
    base = d.get("base") or {}
    grid = d.get("grid") or {}
    rand = d.get("random") or {}
    norm = {
        "mode": d["mode"],
        "samples": d.get("samples") if d["mode"] == "random" else None,
        "seed": d.get("seed") if d["mode"] == "random" else None,
        "execute": bool(d.get("execute")),
        "base": sorted([k, v] for k, v in base.items()),  # type: ignore[union-attr]
        "grid": [[k, v] for k, v in grid.items()],  # type: ignore[union-attr]
        "random": [[k, v] for k, v in rand.items()],  # type: ignore[union-attr]
        "hold": d.get("hold_setpoints_N"),
    }
    return hashlib.sha256(json.dumps(norm, sort_keys=True, default=str).encode()).hexdigest()
