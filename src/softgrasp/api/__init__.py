"""The public Python API: load an object, plan a grasp, execute it, run and calibrate material
tests; each result has ``to_dict()`` and ``save(dir)``, which writes the files of the matching
``softgrasp`` command. SI units throughout; units are in the argument names (``mesh_size_m``,
``lift_m`` ...).

>>> import softgrasp as sg
>>> obj = sg.load_object("sphere")
>>> plan = sg.plan(obj, hand=sg.load_hand("shadow_like"), mu=0.8)
>>> plan.setpoints_N  # doctest: +SKIP
{'thumb': 0.310..., 'first': 0.202..., 'middle': 0.209...}
"""

from softgrasp.api.calibration import Calibration, calibrate
from softgrasp.api.execution import Execution, execute
from softgrasp.api.experiments import Compression, Indentation, compress, indent
from softgrasp.api.objects import SoftObject, load_hand, load_object, material
from softgrasp.api.planning import Plan, plan
from softgrasp.model.material import Material
from softgrasp.model.mesh.generate import LocalRefinement

__all__ = [
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
]
