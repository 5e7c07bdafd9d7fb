"""Simulation: scene and state, explicit integrators, stable time step, static solver."""

from softgrasp.sim.explicit import (
    RK4,
    DormandPrince45,
    Integrator,
    SemiImplicitEuler,
    make_integrator,
    settle,
    simulate,
)
from softgrasp.sim.scene import Interaction, Scene, State
from softgrasp.sim.stability import BlowupMonitor, max_frequency, stable_time_step

__all__ = [
    "RK4",
    "BlowupMonitor",
    "DormandPrince45",
    "Integrator",
    "Interaction",
    "Scene",
    "SemiImplicitEuler",
    "State",
    "make_integrator",
    "max_frequency",
    "settle",
    "simulate",
    "stable_time_step",
]
