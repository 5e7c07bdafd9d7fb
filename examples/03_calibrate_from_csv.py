"""Calibrate a material from a measured compression curve (CSV).

Measurements are stood in for by a synthetic curve: softgrasp compresses a 50 mm cube of a known
material (E = 200 kPa, nu = 0.3) by 15 % and writes plate displacement [mm] and force [N] as a
CSV file, as a testing machine would. Calibration then fits Young's modulus (a linear spring law,
nu kept at 0.3) by simulating the same test, and the example prints the fitted E [Pa].

Run:  python examples/03_calibrate_from_csv.py [OUT_DIR]   (OUT_DIR: also write material.toml, ...)
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import softgrasp as sg

#: The material that made the "measured" curve.
TRUE_MATERIAL = sg.Material(E_Pa=2.0e5, nu=0.3)
#: The specimen's element size [m] (coarse: a quick example).
MESH_SIZE_M = 0.0125


def write_compression_csv(folder: Path) -> Path:
    """A compression curve of the cube made of :data:`TRUE_MATERIAL`, as
    ``folder/compression.csv`` (columns ``displacement_mm,force_N``)."""
    cube = sg.load_object("cube", material=TRUE_MATERIAL, mesh_size_m=MESH_SIZE_M)
    test = sg.compress(cube, strain=0.15, steps=6)
    rows = zip(test.result.displacement_m[1:], test.result.force_N[1:], strict=True)
    path = folder / "compression.csv"
    path.write_text("displacement_mm,force_N\n" + "".join(f"{d * 1e3:.9g},{f:.9g}\n" for d, f in rows))
    return path


def calibrate_cube(csv: Path) -> sg.Calibration:
    """The material of the cube fitted to the curve in ``csv``."""
    cube = sg.load_object("cube", mesh_size_m=MESH_SIZE_M)
    return sg.calibrate(cube, compression=csv, law="linear", nu=0.3)


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        csv = write_compression_csv(Path(tmp))
        cal = calibrate_cube(csv)
        if len(sys.argv) > 1:
            print(f"wrote {cal.save(sys.argv[1])}")
    print(f"E {cal.E_Pa:.6f} Pa")
    print(f"nu {cal.material.nu:g}")


if __name__ == "__main__":
    main()
