"""A plan's object for ParaView: the held state's arrays on ``object.vtu`` and the closing as a
``.pvd`` time series.

* ``object.vtu`` is the object as placed on the table, unloaded (the mesh ``execute`` simulates;
  its points and tets are what ``object.mesh_sha256`` fingerprints), with the held state's arrays:
  per node ``displacement_m`` (held minus placed position [m]: ParaView's *Warp By Vector* shows
  the held object) and ``contact_force_N`` (the fingertips' forces on the node [N], Eq. 17-20),
  per tetrahedron ``max_principal_strain`` (its largest principal engineering strain
  ``|lambda - 1|``, compression or tension).
* ``closing.pvd`` lists ``closing/increment_KKK.vtu``, one per closing increment at rest (the
  start at travel 0 first), each at its deformed positions with the same arrays; its timesteps are
  the fingertips' travel [m].
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
from numpy.typing import NDArray

from softgrasp.grasp.damage import principal_strains
from softgrasp.grasp.result import GraspPlan
from softgrasp.io.atomic import write_text
from softgrasp.physics.body import Body

__all__ = ["CLOSING_PVD", "CLOSING_DIR", "state_arrays", "write_object_vtu", "write_closing_series"]

#: The time series' index file and the folder of its steps, inside a plan's folder.
CLOSING_PVD = "closing.pvd"
CLOSING_DIR = "closing"


def state_arrays(
    body: Body,
    placed: NDArray[np.float64],
    x: NDArray[np.float64],
    contact_forces: NDArray[np.float64] | None,
) -> tuple[dict[str, NDArray[np.float64]], dict[str, NDArray[np.float64]]]:
    """Point and cell arrays of the object at positions ``x`` [m] (N, 3): ``displacement_m`` from
    ``placed`` (N, 3), ``contact_force_N`` (N, 3; zeros where None) and ``max_principal_strain``
    (M,)."""
    forces = np.zeros_like(x) if contact_forces is None else np.asarray(contact_forces, dtype=np.float64)
    points = {"displacement_m": np.asarray(x, dtype=np.float64) - placed, "contact_force_N": forces}
    return points, {"max_principal_strain": principal_strains(body, x)}


def write_object_vtu(path: str | Path, plan: GraspPlan, body: Body) -> None:
    """``object.vtu``: the placed object with the held state's arrays (module docstring)."""
    from softgrasp.model.mesh.io import save_mesh

    points, cells = state_arrays(body, plan.placed, plan.positions, plan.contact_forces)
    save_mesh(body.mesh, path, point_data=points, cell_data=cells, points=plan.placed)


def write_closing_series(folder: str | Path, plan: GraspPlan, body: Body) -> list[str]:
    """Write ``closing.pvd`` and ``closing/increment_KKK.vtu`` into ``folder`` (module docstring);
    return the names written, relative to ``folder``."""
    from softgrasp.model.mesh.io import save_mesh

    fr = plan.frames
    if fr is None:
        return []
    root = Path(folder)
    (root / CLOSING_DIR).mkdir(parents=True, exist_ok=True)
    names: list[str] = []
    lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">']
    lines.append("  <Collection>")
    for k, travel in enumerate(fr.travel):
        name = f"{CLOSING_DIR}/increment_{k:03d}.vtu"
        forces = None if fr.contact_forces is None else fr.contact_forces[k]
        points, cells = state_arrays(body, plan.placed, fr.positions[k], forces)
        save_mesh(body.mesh, root / name, point_data=points, cell_data=cells, points=fr.positions[k])
        names.append(name)
        lines.append(f'    <DataSet timestep="{float(travel)!r}" group="" part="0" file={quoteattr(name)}/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    write_text(root / CLOSING_PVD, "\n".join(lines))
    return [CLOSING_PVD, *names]
