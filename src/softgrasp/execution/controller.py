"""Executing a plan on a hand (paper step 3, Sec. 2 and 4.3.3): force-controlled closing to the
planned set-points, then the lift and the hold, with the slip check.

Phases, all driven through the :class:`~softgrasp.execution.protocol.Hand` interface:

1. **settle**: the hand starts in the plan's starting posture (fingertips one step off their
   initial contacts; the backend puts it there, a hardware hand by position control) and holds it
   while the object comes to rest on the table;
2. **close**: each fingertip advances along its planned straight closing line (palm frame) under
   force control on its tactile normal force (:mod:`~softgrasp.execution.force_loop`): at
   ``speed`` until it touches (the command comes back to the fingertip at its first touch),
   then a first-order approach of the set-point over ``response_time``; the closing is done
   when every finger has stayed within ``tolerance`` of its set-point for ``settle_band``
   seconds (a single reading without contact after a touch counting as the one before it);
3. **lift**: the base rises ``lift`` metres at ``lift_speed`` on average (a half-cosine profile),
   the fingers holding the posture that reached the set-points;
4. **hold**: ``hold_time`` seconds at the top.

The slip is the object's displacement relative to the fingertips during the lift and the hold:
``max_t |(c(t) - g(t)) - (c(t0) - g(t0))|`` with c the object's centre of mass and g the centroid
of the fingertips (world), t0 the start of the lift. The object is *dropped* when at the end it
has risen less than half the lift.

The lift and the hold end early once the object is out of the hand: no fingertip has read a
force for :data:`RELEASE_TIME` while the object, risen less than half the lift, lay at rest (its
centre of mass moved less than :data:`REST_DRIFT`). Nothing the fingertips do not touch then
lifts it (it lies on the table, or on a link without a sensor that is not rising either), so the
outcome is the one the rest of the run would give: dropped. The event ``released`` records when.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError, SimulationUnstable
from softgrasp.execution.force_loop import FingerLoops
from softgrasp.execution.protocol import Hand
from softgrasp.hand.placement import invert, transform
from softgrasp.io.planfile import PlanFile

__all__ = [
    "ClosingLine",
    "ExecuteConfig",
    "ExecutionResult",
    "closing_lines",
    "execute_plan",
    "PHASES",
    "MAX_SIMULATED_TIME",
]

PHASES = ("settle", "close", "lift", "hold")
#: Longest execution [s] of hand time (settle, closing, lift and hold together).
MAX_SIMULATED_TIME = 300.0
#: The object is out of the hand when no fingertip has read a force for this long [s] ...
RELEASE_TIME = 0.1
#: ... while its centre of mass moved less than this [m], below half the lift (module docstring).
REST_DRIFT = 5e-4
#: The default wall-clock bound of an execution: this many seconds ...
WALL_TIME_BASE = 60.0
#: ... plus this many times its longest hand time (MuJoCo runs the 388-node sphere ~6x slower
#: than real time on one core).
WALL_TIME_FACTOR = 100.0


@dataclass(frozen=True)
class ClosingLine:
    """One finger's task: its set-point and its straight closing line in the palm frame.

    Attributes
    ----------
    setpoint: normal force to reach [N] (> 0).
    start: fingertip centre where the closing starts [m], palm frame, (3,).
    direction: unit closing direction, palm frame, (3,).
    max_travel: farthest the fingertip may advance along the line [m] (the crushing guard), and
        back off behind its start.
    """

    setpoint: float
    start: NDArray[np.float64]
    direction: NDArray[np.float64]
    max_travel: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.setpoint) and self.setpoint > 0):
            raise ConfigError(f"set-point {self.setpoint} N must be a finite force > 0")
        if not (math.isfinite(self.max_travel) and self.max_travel > 0):
            raise ConfigError(f"max_travel {self.max_travel} m must be > 0")
        d = np.asarray(self.direction, dtype=np.float64)
        if d.shape != (3,) or abs(np.linalg.norm(d) - 1.0) > 1e-6:
            raise ConfigError("a closing direction must be a unit vector (3,)")


def closing_lines(plan: PlanFile, scale: float = 1.0) -> dict[str, ClosingLine]:
    """Each finger's task from a plan: set-point ``scale`` times its planned normal force, the line
    from its start to its final centre in the palm frame, and a crushing guard of three times the
    planned travel (at least 5 mm more than it)."""
    to_palm = invert(plan.palm_pose)
    lines = {}
    for f in plan.fingers:
        a, b = transform(to_palm, f.start), transform(to_palm, f.final)
        L = float(np.linalg.norm(b - a))
        lines[f.name] = ClosingLine(scale * f.normal_force, a, (b - a) / L, max(3.0 * L, L + 0.005))
    return lines


@dataclass(frozen=True)
class ExecuteConfig:
    """Controller settings.

    Attributes
    ----------
    lift: base rise [m].  lift_speed: [m/s].  hold_time: [s] at the top.
    tolerance: relative force error that counts as reaching a set-point (0.05 = 5 %).
    settle_time: [s] before the closing.  settle_band: [s] every finger must stay within the
        tolerance to end the closing.  max_close_time: [s] before giving up on the set-points.
    speed: largest fingertip speed of the force controller [m/s], and its approach speed.
    response_time: time constant [s] of the approach of the set-point after the touch
        (:func:`~softgrasp.execution.force_loop.closing_speed`); at least three times the hand's
        position lag, measured as each finger first touches.
    control_dt: controller period [s].
    max_wall_time: wall-clock bound of the whole execution [s]; None: :data:`WALL_TIME_BASE` +
        :data:`WALL_TIME_FACTOR` x :attr:`duration`. Past it the execution stops with
        :class:`~softgrasp.errors.SimulationUnstable`.
    force_control_in_lift: keep regulating each finger's force during the lift and the hold. Off
        by default: once the set-points are reached the fingers hold their posture (the paper's
        lift). Three independent force loops cannot hold the object's position: when the weight
        moves from the table to the fingers, the object drifts towards one finger, which backs
        off while the others chase it (measured in MuJoCo: the thumb retreated to its start and
        its force rose 15 %).
    """

    lift: float = 0.10
    lift_speed: float = 0.05
    hold_time: float = 2.0
    tolerance: float = 0.05
    settle_time: float = 0.3
    settle_band: float = 0.2
    max_close_time: float = 6.0
    speed: float = 0.005
    response_time: float = 0.05
    control_dt: float = 0.002
    force_control_in_lift: bool = False
    max_wall_time: float | None = None

    def __post_init__(self) -> None:
        for name in ("lift", "hold_time", "settle_time"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"execute parameter {name} = {v} must be finite and >= 0")
        for name in (
            "lift_speed",
            "tolerance",
            "settle_band",
            "max_close_time",
            "speed",
            "response_time",
            "control_dt",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"execute parameter {name} = {v} must be finite and > 0")
        w = self.max_wall_time
        if w is not None and not (math.isfinite(w) and w > 0):
            raise ConfigError(f"execute parameter max_wall_time = {w} s must be finite and > 0 (or None)")
        if self.duration > MAX_SIMULATED_TIME:
            raise ConfigError(
                f"the execution would last {self.duration:g} s (settle, closing, lift at "
                f"{self.lift_speed:g} m/s, hold), more than {MAX_SIMULATED_TIME:g} s: lower the lift "
                "height or the hold time"
            )

    @property
    def duration(self) -> float:
        """Longest hand time of an execution [s]: settle, the whole closing time, lift and hold."""
        return self.settle_time + self.max_close_time + self.lift / self.lift_speed + self.hold_time

    @property
    def wall_limit(self) -> float:
        """Wall-clock bound of an execution [s] (:attr:`max_wall_time` or its default)."""
        if self.max_wall_time is not None:
            return self.max_wall_time
        return WALL_TIME_BASE + WALL_TIME_FACTOR * self.duration

    def describe(self) -> dict[str, float | bool]:
        return {
            "lift_m": self.lift,
            "lift_speed_m_s": self.lift_speed,
            "hold_time_s": self.hold_time,
            "tolerance": self.tolerance,
            "settle_time_s": self.settle_time,
            "settle_band_s": self.settle_band,
            "max_close_time_s": self.max_close_time,
            "speed_m_s": self.speed,
            "response_time_s": self.response_time,
            "control_dt_s": self.control_dt,
            "force_control_in_lift": self.force_control_in_lift,
            "wall_limit_s": self.wall_limit,
        }


@dataclass
class ExecutionResult:
    """What happened.

    Attributes
    ----------
    fingers: finger names.  setpoints: [N] per finger.
    reached: whether the closing brought every finger within the tolerance.
    measured: tactile normal force per finger when the closing ended [N].
    held: mean tactile normal force per finger over the last half of the hold (over the
        :data:`RELEASE_TIME` before the end when the object was released) [N].
    lifted: the object rose with the hand.  dropped: it did not (rose < half the lift).
    slip: the object's largest displacement relative to the fingertips during lift and hold [m].
    rise: the object's final rise [m].
    series: time series, one row per control period: ``t``, ``phase`` (index in :data:`PHASES`),
        per finger ``force`` (normal, N) and ``travel`` (m), the base rise ``base_z`` and the
        object's centre ``com`` (3,), the fingertip centroid ``tips`` (3,).
    events: time [s] at which each phase began, ``first_contact`` per finger, and ``released``
        when the run ended early with the object out of the hand (:data:`RELEASE_TIME`).
    lag: per finger, the hand's position lag measured at its touch [s] (0 where it did not touch
        under way), which sets its closing's time constant.
    """

    fingers: tuple[str, ...]
    setpoints: dict[str, float]
    reached: bool
    measured: dict[str, float]
    held: dict[str, float]
    lifted: bool
    dropped: bool
    slip: float
    rise: float
    series: dict[str, NDArray[np.float64]]
    events: dict[str, float] = field(default_factory=dict)
    lag: dict[str, float] = field(default_factory=dict)

    def describe(self) -> dict[str, object]:
        """JSON-ready outcome: per finger its set-point, the force reached and held [N]; whether
        the set-points were reached and the object lifted; slip and rise [m]; event times [s]."""
        return {
            "fingers": [
                {
                    "name": n,
                    "setpoint_N": self.setpoints[n],
                    "measured_N": self.measured[n],
                    "error_N": self.measured[n] - self.setpoints[n],
                    "held_N": self.held[n],
                    "lag_s": self.lag.get(n, 0.0),
                }
                for n in self.fingers
            ],
            "reached": self.reached,
            "lifted": self.lifted,
            "dropped": self.dropped,
            "slip_m": self.slip,
            "rise_m": self.rise,
            "events_s": self.events,
        }


def execute_plan(
    hand: Hand,
    lines: Mapping[str, ClosingLine],
    config: ExecuteConfig = ExecuteConfig(),  # noqa: B008 - frozen dataclass
    *,
    palm_to_world: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
    progress: Callable[[float], None] | None = None,
    on_event: Callable[[str], None] | None = None,
) -> ExecutionResult:
    """Run the settle, force-controlled closing, lift and hold on ``hand``.

    Parameters
    ----------
    hand: the backend.  lines: per finger, its set-point and closing line (palm frame).
    config: controller settings.
    palm_to_world: maps palm-frame points (K, 3) to the world at the current base pose (for the
        slip measure); None when the palm frame is the world's translated by the base offset.
    progress: called with the fraction of the planned duration done.
    on_event: called with ``"start"`` (fingers at their start, object settled), ``"contact"``
        (every finger touches), ``"closed"`` (the closing ended), ``"end"`` (after the hold).
    """
    names = tuple(lines)
    missing = set(names) - set(hand.fingers)
    if missing:
        raise ConfigError(f"the hand has no finger(s) {', '.join(sorted(missing))}; it has {hand.fingers}")
    cfg = config
    dt = cfg.control_dt
    travel = {f: 0.0 for f in names}
    rows: list[tuple] = []
    events: dict[str, float] = {}
    base = np.zeros(3)
    planned = cfg.settle_time + cfg.max_close_time / 3 + cfg.lift / cfg.lift_speed + cfg.hold_time
    wall0, wall_limit = time.perf_counter(), cfg.wall_limit

    def step() -> None:
        """One control period on the hand, with the guards that bound every execution."""
        t = hand.time
        hand.step(dt)
        if not hand.time > t:
            raise SimulationUnstable(
                f"the hand's clock did not advance in a control period (t = {t:g} s, then {hand.time:g} s): "
                "its simulation or driver is stuck"
            )
        wall = time.perf_counter() - wall0
        if wall > wall_limit:
            raise SimulationUnstable(
                f"the execution took {wall:.3g} s of wall-clock time for {hand.time:.3g} s of hand time "
                f"(limit {wall_limit:.3g} s for at most {cfg.duration:.3g} s): the simulation is too "
                "slow; plan on a coarser mesh (a larger --mesh-size)"
            )

    def command() -> None:
        hand.command_fingertips({f: lines[f].start + travel[f] * lines[f].direction for f in names})

    def record(phase: int, forces: Mapping[str, float]) -> None:
        where = hand.fingertip_positions()
        tips = np.array([where[f] for f in names])
        world = palm_to_world(tips) if palm_to_world is not None else tips + base
        rows.append(
            (
                hand.time,
                phase,
                tuple(forces[f] for f in names),
                tuple(travel[f] for f in names),
                base[2],
                hand.object_position().copy(),
                world.mean(axis=0),
            )
        )
        if progress is not None:
            progress(min(hand.time / planned, 1.0))

    loops = FingerLoops(names, cfg.response_time, cfg.speed)

    def control(forces: Mapping[str, float]) -> None:
        where = hand.fingertip_positions()
        for f in names:
            line = lines[f]
            at = float((np.asarray(where[f]) - line.start) @ line.direction)  # measured travel
            v, travel[f] = loops.advance(f, forces[f], line.setpoint, at, travel[f])
            travel[f] = float(np.clip(travel[f] + v * dt, -line.max_travel, line.max_travel))

    # 1. settle
    command()
    t_end = hand.time + cfg.settle_time
    events["settle"] = hand.time
    last = hand.fingertip_normal_forces()  # the tactile reading after the latest step
    while hand.time < t_end - 1e-12:
        step()
        last = hand.fingertip_normal_forces()
        record(0, last)
    if on_event is not None:
        on_event("start")
    # 2. force-controlled closing
    events["close"] = hand.time
    touching = False
    t_limit = hand.time + cfg.max_close_time
    inside_since: float | None = None
    reached = False
    while hand.time < t_limit - 1e-12:
        forces = last
        for f in names:
            if forces[f] > 0 and f"first_contact_{f}" not in events:
                events[f"first_contact_{f}"] = hand.time
        if not touching and all(f"first_contact_{f}" in events for f in names):
            touching = True
            if on_event is not None:
                on_event("contact")
        # (a single reading without contact after a touch, which the finger waits out, counts
        # as the reading before it)
        counted = {f: loops.counted(f, forces[f], lines[f].setpoint) for f in names}
        within = all(abs(counted[f] - lines[f].setpoint) <= cfg.tolerance * lines[f].setpoint for f in names)
        if within:
            inside_since = hand.time if inside_since is None else inside_since
            if hand.time - inside_since >= cfg.settle_band - 1e-12:
                reached = True
                break
        else:
            inside_since = None
        control(forces)
        command()
        step()
        last = hand.fingertip_normal_forces()
        record(1, last)
    measured = dict(last)
    if on_event is not None:
        on_event("closed")

    # 3. lift, and 4. hold
    window = max(1, math.ceil(RELEASE_TIME / dt - 1e-9))  # control periods in RELEASE_TIME
    untouched = 0  # control periods since a fingertip last read a force
    lift_com = hand.object_position()  # where the rise is measured from

    def released() -> bool:
        """Whether the object is out of the hand (module docstring)."""
        if untouched < window or len(rows) <= window:
            return False
        com, before = rows[-1][5], rows[-1 - window][5]
        return bool(np.linalg.norm(com - before) < REST_DRIFT and com[2] - lift_com[2] < 0.5 * cfg.lift)

    def run(phase: int, duration: float, base_z: Callable[[float], float] | None = None) -> bool:
        """``duration`` seconds of control periods; ``base_z(elapsed)`` commands the base. False
        when it ended early, the object released."""
        nonlocal last, untouched
        start = hand.time
        while hand.time < start + duration - 1e-12:
            if base_z is not None:
                base[2] = base_z(hand.time + dt - start)
                hand.command_base(base.copy())
            if cfg.force_control_in_lift:
                control(last)
                command()
            step()
            last = hand.fingertip_normal_forces()
            record(phase, last)
            untouched = 0 if any(last[f] > 0 for f in names) else untouched + 1
            if released():
                events["released"] = hand.time
                return False
        return True

    rise_time = cfg.lift / cfg.lift_speed
    events["lift"] = hand.time
    lift_start = len(rows)
    # A smooth rise (half a cosine: no jerk at either end) at lift_speed on average.
    rising = run(2, rise_time, lambda e: cfg.lift * 0.5 * (1.0 - math.cos(math.pi * min(e / rise_time, 1.0))))
    hold_start = len(rows)
    if rising:
        events["hold"] = hand.time
        run(3, cfg.hold_time)
    events["end"] = hand.time
    if on_event is not None:
        on_event("end")

    t = np.array([r[0] for r in rows])
    series = {
        "t": t,
        "phase": np.array([r[1] for r in rows], dtype=np.int64),
        "force": np.array([r[2] for r in rows]).reshape(len(rows), len(names)),
        "travel": np.array([r[3] for r in rows]).reshape(len(rows), len(names)),
        "base_z": np.array([r[4] for r in rows]),
        "com": np.array([r[5] for r in rows]).reshape(len(rows), 3),
        "tips": np.array([r[6] for r in rows]).reshape(len(rows), 3),
    }
    rel = series["com"] - series["tips"]
    if lift_start < len(rows):
        ref = rel[lift_start - 1] if lift_start > 0 else rel[0]
        slip = float(np.linalg.norm(rel[lift_start:] - ref, axis=1).max())
    else:
        slip = 0.0
    rise = float(series["com"][-1, 2] - lift_com[2]) if len(rows) else 0.0
    dropped = rise < 0.5 * cfg.lift
    if "released" in events:  # the readings of the release window (none touches)
        last = series["force"][len(rows) - window :]
    else:
        last = series["force"][hold_start + (len(rows) - hold_start) // 2 :]
    held = {f: float(last[:, j].mean()) if len(last) else math.nan for j, f in enumerate(names)}
    return ExecutionResult(
        fingers=names,
        setpoints={f: lines[f].setpoint for f in names},
        reached=reached,
        measured={f: float(measured[f]) for f in names},
        held=held,
        lifted=not dropped,
        dropped=dropped,
        slip=slip,
        rise=rise,
        series=series,
        events=events,
        lag=dict(loops.lag),
    )
