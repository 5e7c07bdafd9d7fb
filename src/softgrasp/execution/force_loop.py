"""The force control of a fingertip's closing on a hand (paper step 3): how fast the fingertip
advances along its closing line, from its tactile normal force and its measured position.

A guarded approach at the touch speed until the force reaches :data:`TOUCH_FRACTION` of the
set-point; there the hand's position lag is measured (the command's lead over the measured
fingertip, over the speed) and the command comes back to the fingertip. Then a first-order
approach of the set-point: the travel left to it is estimated from the force and the
fingertip's measured travel since the touch by Hertz's law ``F ~ d^1.5``, less the travel the
hand's position lag still carries, and the command covers the rest with a time constant of at
least :data:`LAG_FACTOR` lags. A loop on the force error alone cannot do this on a
stiff object: a hand lagging its command by 16 ms at 10 mm/s carries 0.16 mm into the touch,
while MuJoCo's contact with the rubber sphere reaches the set-point 0.06 mm in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["FingerLoops", "closing_speed", "HERTZ_EXPONENT", "TOUCH_FRACTION", "CREEP_FRACTION", "LAG_FACTOR"]

#: The exponent of Hertz's law, F ~ d^1.5 for a sphere pressed into an elastic solid: the closing
#: estimates from it the travel left to a set-point (:func:`closing_speed`).
HERTZ_EXPONENT = 1.5
#: A finger touches when its tactile force reaches this fraction of its set-point.
TOUCH_FRACTION = 0.02
#: The least speed of a finger after the touch, as a fraction of the touch speed at a force error
#: of 100 %, slow enough for the stiffest contacts the executor meets (MuJoCo's: the set-point
#: 0.06 mm into the object).
CREEP_FRACTION = 0.1
#: The closing's response time is at least this many times the hand's position lag, measured
#: as each finger touches (command ahead of the measured fingertip, over the approach speed).
LAG_FACTOR = 3.0


def closing_speed(
    force_N: float,
    setpoint_N: float,
    pressed_m: float | None,
    coming_m: float,
    response_s: float,
    speed_m_s: float,
    touch_speed_m_s: float,
    fast: bool = False,
) -> float:
    """A fingertip's speed [m/s] along its closing line (> 0 closes) from its tactile normal force
    ``force_N`` and set-point ``setpoint_N`` [N].

    Before the touch (``pressed_m`` None) it approaches at ``touch_speed_m_s`` (at ``speed_m_s``
    while ``fast``). After it, ``pressed_m`` [m] is the fingertip's measured travel since the
    touch; with the force growing as Hertz's ``d^1.5`` the set-point lies
    ``d ((F_set / F)^(1/1.5) - 1)`` further (exact for a Hertzian contact, short of it for a
    linear one). Of that travel, ``coming_m`` [m] is already on its way (the hand's lag times its
    speed: where the fingertip ends if the command stops); the command covers the rest with the
    time constant ``response_s``, so the force approaches the set-point without passing it. A
    creep of :data:`CREEP_FRACTION` ``touch_speed (F_set - F) / F_set`` is the least speed, so a
    finger whose travel since the touch says little (the object moved with it) still closes on
    its set-point; the speed is at most ``speed_m_s`` either way.
    """
    if pressed_m is None:
        return speed_m_s if fast else touch_speed_m_s
    err = min(max((setpoint_N - force_N) / setpoint_N, -1.0), 1.0)
    creep = CREEP_FRACTION * touch_speed_m_s * err
    left = max(pressed_m, 0.0) * ((setpoint_N / force_N) ** (1.0 / HERTZ_EXPONENT) - 1.0)
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
    speed: largest fingertip speed [m/s].  touch_speed: speed of the guarded approach [m/s].
    free: measured travel at the latest reading before the touch [m].
    pressing: whether the finger touches.  lag: the hand's position lag measured at its first touch [s].
    response: each finger's time constant (``response_time``, or :data:`LAG_FACTOR` lags).
    speed_now: each finger's latest commanded speed [m/s].
    """

    names: tuple[str, ...]
    response_time: float
    speed: float
    touch_speed: float
    free: dict[str, float] = field(default_factory=dict)
    pressing: dict[str, bool] = field(default_factory=dict)
    lag: dict[str, float] = field(default_factory=dict)
    response: dict[str, float] = field(default_factory=dict)
    speed_now: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for f in self.names:
            self.free[f], self.pressing[f], self.lag[f] = 0.0, False, 0.0
            self.response[f], self.speed_now[f] = self.response_time, 0.0

    def advance(
        self,
        finger: str,
        force_N: float,
        setpoint_N: float,
        measured_m: float,
        command_m: float,
        fast: bool,
    ) -> tuple[float, float]:
        """The finger's speed [m/s] and the command [m] (travel along its line) to advance from,
        given its tactile force and its measured and commanded travel [m]. At the finger's first
        touch the hand's lag is measured and the command comes back to the measured travel: the
        lead it had would press on (a lag of 50 ms carries 0.1 mm at 2 mm/s)."""
        f = finger
        if force_N < TOUCH_FRACTION * setpoint_N:
            self.pressing[f], self.free[f] = False, measured_m  # not (or no longer) touching
        elif not self.pressing[f]:
            self.pressing[f] = True
            v0 = self.speed_now[f]
            if self.lag[f] == 0.0 and v0 > 0:
                self.lag[f] = max(command_m - measured_m, 0.0) / v0
                self.response[f] = max(self.response_time, LAG_FACTOR * self.lag[f])
                command_m, self.speed_now[f] = min(command_m, measured_m), 0.0
        pressed = measured_m - self.free[f] if self.pressing[f] else None
        coming = self.lag[f] * self.speed_now[f]
        v = closing_speed(
            force_N, setpoint_N, pressed, coming, self.response[f], self.speed, self.touch_speed, fast
        )
        self.speed_now[f] = v
        return v, command_m
