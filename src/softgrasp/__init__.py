"""softgrasp: model-based grasp planning and force-controlled execution for soft 3D objects.

The package implements the non-linear mass-spring object model, the fingertip contact model
(Hunt-Crossley normal force, stick/slip friction) and the grasp strategy of the reference paper
(model-based strategy for grasping 3D deformable objects using a multi-fingered robotic hand), in SI
units throughout.
"""

from softgrasp.errors import (
    ConfigError,
    ContactError,
    InfeasibleGrasp,
    MaterialError,
    MeshError,
    NotConverged,
    SimulationUnstable,
    SoftgraspError,
)

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "ContactError",
    "InfeasibleGrasp",
    "MaterialError",
    "MeshError",
    "NotConverged",
    "SimulationUnstable",
    "SoftgraspError",
    "__version__",
]
