"""Every figure softgrasp draws, by name: the functions of the figure modules in one namespace.

The figure worker (:mod:`softgrasp.viz.worker`) calls them by name, in a child process or here.
Each is written as a PNG file by its module: :mod:`~softgrasp.viz.experiment_plots` (compression,
indentation, calibration), :mod:`~softgrasp.viz.grasp_plots` (planned grasp),
:mod:`~softgrasp.viz.execution_plots` (executed grasp), :mod:`~softgrasp.viz.sweep_plots` (sweeps
and robust planning); what they share is in :mod:`~softgrasp.viz.figure`.
"""

from __future__ import annotations

from softgrasp.viz.execution_plots import (
    EXECUTION_FRAME_TITLES,
    execution_frame_title,
    plot_execution_forces,
    plot_execution_frame,
    save_execution_image,
    write_execution_pictures,
)
from softgrasp.viz.experiment_plots import plot_calibration, plot_force_penetration, plot_stress_strain
from softgrasp.viz.figure import pyplot as _figure  # noqa: F401 - the figure worker warms pyplot up with it
from softgrasp.viz.grasp_plots import plot_grasp_3d, plot_plan_force_penetration, plot_plan_forces
from softgrasp.viz.sweep_plots import plot_robust, plot_success_map, plot_sweep_forces

__all__ = [
    "EXECUTION_FRAME_TITLES",
    "execution_frame_title",
    "plot_calibration",
    "plot_execution_forces",
    "plot_execution_frame",
    "plot_force_penetration",
    "plot_grasp_3d",
    "plot_plan_force_penetration",
    "plot_plan_forces",
    "plot_robust",
    "plot_stress_strain",
    "plot_success_map",
    "plot_sweep_forces",
    "save_execution_image",
    "write_execution_pictures",
]
