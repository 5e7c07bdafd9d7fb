"""softgrasp: model-based grasp planning and force-controlled execution for soft 3D objects.

The package implements the non-linear mass-spring object model, the fingertip contact model
(Hunt-Crossley normal force, stick/slip friction) and the grasp strategy of the reference paper
(model-based strategy for grasping 3D deformable objects using a multi-fingered robotic hand), in SI
units throughout.

The public API (:mod:`softgrasp.api`)::

    import softgrasp as sg
    rubber = sg.Material(E_Pa=80e3, nu=0.45, density_kg_m3=950)
    obj = sg.load_object("banana.stl", units="mm", material=rubber)
    plan = sg.plan(obj, hand=sg.load_hand("shadow_like"), mu=0.8)
    plan.setpoints_N      # the fingers' normal-force set-points [N]
    plan.save("out/")     # the files of `softgrasp plan --out out/`
    run = sg.execute(plan)  # run.lifted, run.slip_m, run.measured_N

Its names load on first use: importing softgrasp loads no numerical module.
"""

from typing import TYPE_CHECKING, Any

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

if TYPE_CHECKING:
    from softgrasp.api import (
        Calibration,
        Compression,
        Execution,
        Indentation,
        LocalRefinement,
        Material,
        Plan,
        SoftObject,
        calibrate,
        compress,
        execute,
        indent,
        load_hand,
        load_object,
        material,
        plan,
    )

__version__ = "0.1.0"

#: The names of the public API, loaded from :mod:`softgrasp.api` when first used.
_API = (
    "Calibration",
    "Compression",
    "Execution",
    "Indentation",
    "LocalRefinement",
    "Material",
    "Plan",
    "SoftObject",
    "calibrate",
    "compress",
    "execute",
    "indent",
    "load_hand",
    "load_object",
    "material",
    "plan",
)

__all__ = [
    *_API,
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


def __getattr__(name: str) -> Any:
    if name in _API:
        import softgrasp.api as api

        return getattr(api, name)
    raise AttributeError(f"module 'softgrasp' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
