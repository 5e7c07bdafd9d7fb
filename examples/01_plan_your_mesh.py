"""Plan a grasp of your own mesh: a closed surface file (STL) in millimetres.

The example writes an ellipsoid (100 x 90 x 80 mm) as an STL file in millimetres, made with
softgrasp's own mesh generator, then loads it with ``units="mm"``, gives it a material and plans a
three-finger grasp with the packaged Shadow-like hand. It prints the fingers' normal-force
set-points [N].

Run:  python examples/01_plan_your_mesh.py [OUT_DIR]   (OUT_DIR: also write the plan's files)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import softgrasp as sg

#: The ellipsoid's semi-axes [mm].
SEMI_AXES_MM = (50.0, 45.0, 40.0)
#: Its material: a soft, light foam rubber.
MATERIAL = sg.Material(E_Pa=80e3, nu=0.45, density_kg_m3=120)


def write_ellipsoid_stl(folder: Path) -> Path:
    """An ellipsoid's closed surface, in millimetres, as ``folder/ellipsoid.stl``."""
    import meshio
    import numpy as np

    from softgrasp.model.mesh.generate import sphere

    ball = sphere(1.0, 0.3, on_table=False)  # a unit ball, coarse: its surface is all we keep
    points_mm = ball.points * np.array(SEMI_AXES_MM)
    path = folder / "ellipsoid.stl"
    meshio.write_points_cells(path, points_mm, [("triangle", ball.facets)])
    return path


def plan_ellipsoid(stl: Path) -> sg.Plan:
    """The grasp of the ellipsoid in ``stl`` (millimetres)."""
    obj = sg.load_object(stl, units="mm", material=MATERIAL, mesh_size_m=0.008)
    return sg.plan(obj, hand=sg.load_hand("shadow_like"), mu=0.8)


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        stl = write_ellipsoid_stl(Path(tmp))
        plan = plan_ellipsoid(stl)
    print(f"object: {plan.object.summary()}")
    for finger, force in plan.setpoints_N.items():
        print(f"{finger} {force:.6f} N")
    if len(sys.argv) > 1:
        print(f"wrote {plan.save(sys.argv[1])}")


if __name__ == "__main__":
    main()
