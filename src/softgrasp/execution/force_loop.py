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
time constant is the configured one). A contact lost after its stiffness was measured (a reading
that drops out, a fingertip that slips off an edge) is sought again at the approach of the
set-point, with the stiffness measured before, not at full speed: a full-speed step into a stiff
contact at every dropout presses on without bound.
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
    free: measured travel at the latest reading before the touch [m].
    pressing: whether the finger touches.  touched: whether it has touched since the closing began.
    anchor: measured travel [m] and G where the stiffness was last measured.
    slope: the contact's stiffness in G, dG/dx [N^(2/3)/m], over the latest stretch (0: not yet).
    lag: the hand's position lag measured at the finger's first touch [s]; the finger's time
        constant is ``response_time`` or :data:`LAG_FACTOR` lags, whichever is longer.
    speed_now: each finger's latest commanded speed [m/s].
    """

    names: tuple[str, ...]
    response_time: float
    speed: float
    free: dict[str, float] = field(default_factory=dict)
    pressing: dict[str, bool] = field(default_factory=dict)
    touched: dict[str, bool] = field(default_factory=dict)
    anchor: dict[str, tuple[float, float]] = field(default_factory=dict)
    slope: dict[str, float] = field(default_factory=dict)
    lag: dict[str, float] = field(default_factory=dict)
    speed_now: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for f in self.names:
            self.free[f], self.pressing[f], self.anchor[f], self.slope[f] = 0.0, False, (0.0, 0.0), 0.0
            self.touched[f] = False
            self.lag[f], self.speed_now[f] = 0.0, 0.0

    def advance(
        self, finger: str, force_N: float, setpoint_N: float, measured_m: float, command_m: float
    ) -> tuple[float, float]:
        """The finger's speed [m/s] and the command [m] (travel along its line) to advance from,
        given its tactile force and set-point [N] and its measured and commanded travel [m]."""
        f = finger
        G = max(force_N, 0.0) ** (1.0 / HERTZ_EXPONENT)
        if force_N < TOUCH_FRACTION * setpoint_N:
            self.pressing[f], self.free[f] = False, measured_m  # not (or no longer) touching
        elif not self.pressing[f]:
            self.pressing[f] = True
            if self.slope[f] > 0 or not self.touched[f]:
                # (a touch again keeps the stiffness measured before and measures it anew from
                # here; before it is measured once, it is measured from the first touch)
                self.anchor[f] = (measured_m, G)
            self.touched[f] = True
            v0 = self.speed_now[f]
            if self.lag[f] == 0.0 and v0 > 0:  # the first touch under way
                self.lag[f] = max(command_m - measured_m, 0.0) / v0
                # (only here: brought back at every touch, a finger whose force hovers at the
                # touch force, the object bouncing off it, never closes on its set-point)
                command_m = min(command_m, measured_m)
            self.speed_now[f] = 0.0
        if self.pressing[f]:
            x0, G0 = self.anchor[f]
            dx = measured_m - x0
            if abs(dx) >= max(SLOPE_BASE, 0.25 * (measured_m - self.free[f])):
                if (G - G0) / dx > 0:
                    self.slope[f] = (G - G0) / dx
                self.anchor[f] = (measured_m, G)
        # (a contact lost after its stiffness was measured is sought at the approach of the
        # set-point, not at full speed: a tactile reading that drops out must not press on)
        slope = self.slope[f] if self.pressing[f] or self.slope[f] > 0 else None
        cap = COMING_LAGS * self.lag[f] * abs(self.speed_now[f])
        coming = min(max(command_m - measured_m, -cap), cap)  # (< 0: backing off)
        response = max(self.response_time, LAG_FACTOR * self.lag[f])
        v = closing_speed(force_N, setpoint_N, slope, coming, response, self.speed)
        self.speed_now[f] = v
        return v, command_m
