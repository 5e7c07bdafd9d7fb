"""The force control of a fingertip's closing on a hand (paper step 3): how fast the fingertip
advances along its closing line, from its tactile normal force and its measured position.

The fingertip approaches at full speed until its force reaches :data:`TOUCH_FRACTION` of the
set-point. At its first touch under way the hand's position lag is measured (the command's lead
over the measured fingertip, over the speed) and the command comes back to the fingertip: the
lead would press on.
Then a first-order approach of the set-point in ``G = F^(1/1.5)``, in which Hertz's law is
linear: the travel left is ``(G_set - G) / slope``, ``slope`` the contact's stiffness in G
measured over the fingertip's latest stretch of travel; less the travel the hand's lag still
carries, the command covers it with a time constant of at least :data:`LAG_FACTOR` lags. A loop
on the force error alone cannot do this on a stiff object: a hand lagging its command by 16 ms at
5 mm/s carries 0.08 mm into the touch, while MuJoCo's contact with the rubber sphere reaches the
set-point 0.06 mm in. A finger that already touches when the closing starts measures no lag (its
time constant is the configured one).

A contact lost after the touch: the finger waits out a single reading without contact (a reading
that drops out, a fingertip that slips for one period off an edge of a coarse flex). Then it
seeks the contact at the approach of the set-point with the stiffness measured before, until it
has passed where the set-point lay (:meth:`FingerLoops._depth`), and beyond that at full speed. A
contact found again that far away is a new touch: the command comes back to the fingertip and
the stiffness is measured anew; found again nearer, it keeps both (a finger brought back at
every touch, the object bouncing off it, hovers at the touch force and never closes). Seeking
every lost contact at full speed, with the stiffness measured anew after each, pressed a stiff
contact to hundreds of times its set-point when readings dropped out one period in 7.

The fingers close on one object: a finger in contact does not press further while another in
contact presses more than :data:`PAST_SETPOINT` past its own set-point (it holds its command).
Pressing on would only push the object into that finger: each finger's stiffness is measured on
its own, and one measured while the object gave way under it (the others not yet holding) reads
many times softer than one measured against the held object, so the first advances on a small
force error many times faster than the second backs off from a large one. On a coarse stiff
ellipsoid in MuJoCo a thumb measured 18 times stiffer than the middle finger sat 8-9 % past its
set-point for 0.7 s while the middle finger, 2 % short of its own, pushed the object into it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = [
    "FingerLoops",
    "closing_speed",
    "HERTZ_EXPONENT",
    "TOUCH_FRACTION",
    "COMING_LAGS",
    "LAG_FACTOR",
    "SLOPE_BASE",
    "PAST_SETPOINT",
]

#: The exponent of Hertz's law, F ~ d^1.5 for a sphere pressed into an elastic solid: the closing
#: works in G = F^(1/1.5), linear in the travel for a Hertzian contact.
HERTZ_EXPONENT = 1.5
#: A finger touches when its tactile force reaches this fraction of its set-point.
TOUCH_FRACTION = 0.02
#: The travel still coming to the fingertip is its command's lead over it, but at most this many
#: times its lag times its speed: a lead that stays where the fingertip rests is the servo's give
#: under the force (MuJoCo's position servos: 12 um at 0.24 N), not travel to come.
COMING_LAGS = 2.0
#: The closing's response time is at least this many times the hand's position lag, measured
#: as each finger first touches.
LAG_FACTOR = 3.0
#: The contact's stiffness is measured again over every stretch of the fingertip's travel this
#: long [m], or a quarter of its travel since the touch where that is longer.
SLOPE_BASE = 1e-5
#: A finger in contact holds its command while another in contact presses more than this fraction
#: past its set-point (module docstring).
PAST_SETPOINT = 0.02


def closing_speed(
    force_N: float,
    setpoint_N: float,
    slope: float | None,
    coming_m: float,
    response_s: float,
    speed_m_s: float,
) -> float:
    """A fingertip's speed [m/s] along its closing line (> 0 closes) from its tactile normal force
    ``force_N`` and set-point ``setpoint_N`` [N].

    Before the touch (``slope`` None) it approaches at ``speed_m_s``. After it, ``slope`` is the
    contact's measured stiffness in ``G = F^(1/1.5)`` [N^(2/3)/m] (0 while not measured yet),
    and the set-point lies ``(G_set - G) / slope`` further. Of that travel, ``coming_m`` [m] is
    already on its way (where the fingertip ends if the command stops); the command covers the
    rest with the time constant ``response_s``, so the force approaches the set-point without
    passing it; ``coming_m`` above the travel left makes it back off. Otherwise the least speed is
    a creep of ``(F_set - F) / F_set`` :data:`SLOPE_BASE` per ``response_s``, and while the
    stiffness is not measured yet the creep is the speed: such a finger covers a measuring
    stretch per time constant. The speed is at most ``speed_m_s``.
    """
    if slope is None:
        return speed_m_s
    err = min(max((setpoint_N - force_N) / setpoint_N, -1.0), 1.0)
    v = creep = err * SLOPE_BASE / response_s
    if slope > 0:
        k = 1.0 / HERTZ_EXPONENT
        left = (setpoint_N**k - max(force_N, 0.0) ** k) / slope
        v = (left - coming_m) / response_s
        if v * err >= 0 and abs(v) < abs(creep):  # (opposite signs: the travel coming passes it)
            v = creep
    return min(max(v, -speed_m_s), speed_m_s)


@dataclass
class FingerLoops:
    """The closing's state per finger, between control periods.

    Attributes
    ----------
    names: the fingers.
    response_time: the least time constant of the approach of the set-point [s].
    speed: largest fingertip speed [m/s].
    free: measured travel at the latest reading without contact [m].
    pressing: whether the finger touches.
    touched: whether it has touched since the closing began.
    lost: measured travel where it last lost its contact [m], and the readings without contact
        since then.
    anchor: measured travel [m] and G where the stiffness was last measured (or, until it is
        measured once, where the finger touched).
    slope: the contact's stiffness in G, dG/dx [N^(2/3)/m], over the latest stretch (0: not yet);
        kept while a lost contact is sought.
    lag: the hand's position lag measured at the finger's first touch under way [s]; the finger's
        time constant is ``response_time`` or :data:`LAG_FACTOR` lags, whichever is longer.
    speed_now: each finger's latest commanded speed [m/s].
    force: each finger's latest tactile reading [N].
    setpoint: each finger's set-point [N], as its latest reading was taken.
    """

    names: tuple[str, ...]
    response_time: float
    speed: float
    free: dict[str, float] = field(default_factory=dict)
    pressing: dict[str, bool] = field(default_factory=dict)
    touched: dict[str, bool] = field(default_factory=dict)
    lost: dict[str, tuple[float, int]] = field(default_factory=dict)
    anchor: dict[str, tuple[float, float]] = field(default_factory=dict)
    slope: dict[str, float] = field(default_factory=dict)
    lag: dict[str, float] = field(default_factory=dict)
    speed_now: dict[str, float] = field(default_factory=dict)
    force: dict[str, float] = field(default_factory=dict)
    setpoint: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for f in self.names:
            self.free[f], self.pressing[f], self.anchor[f], self.slope[f] = 0.0, False, (0.0, 0.0), 0.0
            self.touched[f], self.lost[f] = False, (0.0, 0)
            self.lag[f], self.speed_now[f], self.force[f], self.setpoint[f] = 0.0, 0.0, 0.0, 0.0

    def _pressed_past(self, finger: str) -> bool:
        """Whether another finger in contact presses more than :data:`PAST_SETPOINT` past its
        set-point (by its latest reading)."""
        return any(
            g != finger and self.pressing[g] and self.force[g] > (1.0 + PAST_SETPOINT) * self.setpoint[g]
            for g in self.names
        )

    def counted(self, finger: str, force_N: float, setpoint_N: float) -> float:
        """The force [N] a new reading counts for, before :meth:`advance` takes it: the reading,
        except that a single reading without contact after a touch, which the finger waits out,
        counts as the reading before it."""
        lost = self.pressing[finger] and force_N < TOUCH_FRACTION * setpoint_N
        return self.force[finger] if lost else force_N

    def _depth(self, finger: str, setpoint_N: float) -> float:
        """How far past its surface the set-point lies by the measured stiffness [m] (at least
        one measuring stretch)."""
        slope = self.slope[finger]
        return max(setpoint_N ** (1.0 / HERTZ_EXPONENT) / slope, SLOPE_BASE) if slope > 0 else SLOPE_BASE

    def advance(
        self, finger: str, force_N: float, setpoint_N: float, measured_m: float, command_m: float
    ) -> tuple[float, float]:
        """The finger's speed [m/s] and the command [m] (travel along its line) to advance from,
        given its tactile force and set-point [N] and its measured and commanded travel [m]."""
        f = finger
        self.force[f], self.setpoint[f] = force_N, setpoint_N
        G = max(force_N, 0.0) ** (1.0 / HERTZ_EXPONENT)
        depth = self._depth(f, setpoint_N)
        if force_N < TOUCH_FRACTION * setpoint_N:  # not (or no longer) touching
            where, reads = self.lost[f]
            self.lost[f] = (measured_m, 1) if self.pressing[f] else (where, reads + 1)
            self.pressing[f], self.free[f] = False, measured_m
        elif not self.pressing[f]:
            self.pressing[f] = True
            v0 = self.speed_now[f]
            if self.lag[f] == 0.0 and v0 > 0:  # the first touch under way
                self.lag[f] = max(command_m - measured_m, 0.0) / v0
            if not self.touched[f] or abs(measured_m - self.lost[f][0]) > depth:
                # a first touch, or a contact found again elsewhere: its stiffness is measured
                # from here, and the command comes back to the fingertip (a touch again where
                # the contact was lost keeps both: brought back at every touch, a finger whose
                # force hovers at the touch force, the object bouncing off it, never closes)
                self.anchor[f], self.slope[f] = (measured_m, G), 0.0
                if v0 > 0:
                    command_m = min(command_m, measured_m)
            self.touched[f] = True
            self.speed_now[f] = 0.0
        if self.pressing[f]:
            x0, G0 = self.anchor[f]
            dx = measured_m - x0
            if abs(dx) >= max(SLOPE_BASE, 0.25 * (measured_m - self.free[f])):
                if (G - G0) / dx > 0:
                    self.slope[f] = (G - G0) / dx
                self.anchor[f] = (measured_m, G)
            slope: float | None = self.slope[f]
        elif self.touched[f] and self.lost[f][1] == 1:
            self.speed_now[f] = 0.0  # a single reading without contact: the finger waits
            return 0.0, command_m
        elif self.slope[f] > 0 and abs(measured_m - self.lost[f][0]) <= depth:
            slope = self.slope[f]  # a contact lost nearby: sought at the approach of the set-point
        else:
            slope = None  # not touched yet, or the contact is not near: the approach
        cap = COMING_LAGS * self.lag[f] * abs(self.speed_now[f])
        coming = min(max(command_m - measured_m, -cap), cap)  # (< 0: backing off)
        response = max(self.response_time, LAG_FACTOR * self.lag[f])
        v = closing_speed(force_N, setpoint_N, slope, coming, response, self.speed)
        if v > 0 and self.pressing[f] and self._pressed_past(f):
            v = 0.0  # pressing on would push the object into the finger past its set-point
        self.speed_now[f] = v
        return v, command_m
