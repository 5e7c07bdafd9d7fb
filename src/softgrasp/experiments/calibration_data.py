"""Measured curves for the calibrations: compression (force-displacement or stress-strain, with
optional lateral strains) and indentation (force-penetration) files read into SI units and checked
for what a fit needs, and the specimen geometry that converts strain and stress."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError
from softgrasp.experiments.compression import outline_area
from softgrasp.experiments.measured import MeasuredTable, read_table
from softgrasp.model.mesh.tetmesh import TetMesh

__all__ = [
    "MAX_STRAIN",
    "CompressionData",
    "IndentationData",
    "read_compression_data",
    "read_indentation_data",
    "specimen_geometry",
]

#: Largest nominal strain a compression fit simulates.
MAX_STRAIN = 0.8

_DISPLACEMENT_UNITS = {"displacement_m": 1.0, "displacement_mm": 1e-3}
_STRESS_UNITS = {"stress_Pa": 1.0, "stress_kPa": 1e3, "stress_MPa": 1e6}
_PENETRATION_UNITS = {"penetration_m": 1.0, "penetration_mm": 1e-3}


@dataclass(frozen=True)
class CompressionData:
    """A measured compression curve in SI units (loading, increasing displacement).

    Attributes
    ----------
    displacement_m: plate travel from first contact [m], (P,).
    force_N: plate force [N], (P,).
    lateral_strain: change of width over initial width (positive: widening), (P,), or None.
    height_m, area_m2: the specimen height and nominal area used to convert strain and stress.
    source: the file.
    """

    displacement_m: NDArray[np.float64]
    force_N: NDArray[np.float64]
    lateral_strain: NDArray[np.float64] | None
    height_m: float
    area_m2: float
    source: str


@dataclass(frozen=True)
class IndentationData:
    """A measured force-penetration curve in SI units (loading, increasing penetration).

    Attributes
    ----------
    penetration_m: fingertip travel from first contact [m], (P,).
    force_N: fingertip force [N], (P,).
    tangential_force_N: tangential force [N], (P,), or None.
    source: the file.
    """

    penetration_m: NDArray[np.float64]
    force_N: NDArray[np.float64]
    tangential_force_N: NDArray[np.float64] | None
    source: str


def _check_curve(table: MeasuredTable, x: NDArray, y: NDArray, xname: str, yname: str, min_rows: int) -> None:
    """A loading curve: enough rows, x >= 0 strictly increasing, y >= 0; errors name the line."""
    if len(x) < min_rows:
        raise ConfigError(
            f"measured data file {table.name!r} has {len(x)} data row(s); a fit needs at least {min_rows} "
            "(more rows than fitted parameters)"
        )
    for i in range(len(x)):
        if x[i] < 0:
            raise ConfigError(
                f"measured data file {table.name!r}, line {table.line_of(i)}: {xname} {x[i]:.6g} is "
                "negative; measure from first contact (0 at first contact)"
            )
        if y[i] < 0:
            raise ConfigError(
                f"measured data file {table.name!r}, line {table.line_of(i)}: {yname} {y[i]:.6g} is "
                "negative; give compressive forces as positive numbers"
            )
        if i > 0 and not x[i] > x[i - 1]:
            raise ConfigError(
                f"measured data file {table.name!r}, line {table.line_of(i)}: {xname} {x[i]:.6g} does not "
                f"increase from the previous row's {x[i - 1]:.6g}; the fit needs the loading part of "
                "the curve only, with increasing values (drop the unloading rows, sort or average repeats)"
            )
    if not (y > 0).any():
        raise ConfigError(f"measured data file {table.name!r}: every {yname} is zero; nothing to fit")


def specimen_geometry(mesh: TetMesh) -> tuple[float, float]:
    """Height [m] (z extent) and nominal area [m^2] (outline seen from above) of a specimen, as
    the compression test measures them."""
    p = np.asarray(mesh.points)
    return float(np.ptp(p[:, 2])), outline_area(p)


def read_compression_data(path: str | Path, height_m: float, area_m2: float) -> CompressionData:
    """Read a compression curve: ``displacement_m`` (or ``_mm``) and ``force_N``, or ``strain``
    (nominal, compressive positive) and ``stress_Pa`` (or ``_kPa``, ``_MPa``), converted with the
    specimen's ``height_m`` and ``area_m2``; optional ``lateral_strain`` (positive: widening).

    Raises ConfigError naming the file, line and column for anything a fit cannot use: empty, too
    few rows, wrong columns, non-numbers, negative force, non-increasing displacement, a strain
    beyond 0.8.
    """
    table = read_table(path, min_rows=1)
    disp = table.unit_column(_DISPLACEMENT_UNITS)
    stress = table.unit_column(_STRESS_UNITS)
    # checked in the file's own units (messages quote the file), then converted
    if disp is not None and table.has("force_N"):
        xname, yname = disp[0], "force_N"
        xs, ys = disp[1], 1.0
    elif table.has("strain") and stress is not None:
        xname, yname = "strain", stress[0]
        xs, ys = height_m, stress[1] * area_m2
    else:
        raise ConfigError(
            f"measured data file {table.name!r}: the header (line {table.header_line}) must name "
            "displacement_m (or displacement_mm) and force_N, or strain and stress_Pa (or stress_kPa, "
            f"stress_MPa); it has {','.join(table.columns)!r}"
        )
    x, y = table.values(xname), table.values(yname)
    lateral = table.values("lateral_strain") if table.has("lateral_strain") else None
    _check_curve(table, x, y, xname, yname, 4)
    x, y = x * xs, y * ys
    over = np.flatnonzero(x / height_m > MAX_STRAIN)
    if over.size:
        i = int(over[0])
        raise ConfigError(
            f"measured data file {table.name!r}, line {table.line_of(i)}: a strain of "
            f"{x[i] / height_m:.0%} ({x[i] * 1e3:.4g} mm of the specimen height {height_m * 1e3:.4g} mm); "
            f"the fit simulates up to {MAX_STRAIN:.0%} (check the specimen: --object, --mesh-size)"
        )
    return CompressionData(x, y, lateral, height_m, area_m2, table.name)


def read_indentation_data(path: str | Path) -> IndentationData:
    """Read a force-penetration curve: ``penetration_m`` (or ``_mm``) and ``force_N``; optional
    ``tangential_force_N``. Errors as :func:`read_compression_data`."""
    table = read_table(path, min_rows=1)
    pen = table.unit_column(_PENETRATION_UNITS)
    if pen is None or not table.has("force_N"):
        raise ConfigError(
            f"measured data file {table.name!r}: the header (line {table.header_line}) must name "
            f"penetration_m (or penetration_mm) and force_N; it has {','.join(table.columns)!r}"
        )
    x = table.values(pen[0])
    y = table.values("force_N")
    _check_curve(table, x, y, pen[0], "force_N", 4)
    x = x * pen[1]
    tangential = table.values("tangential_force_N") if table.has("tangential_force_N") else None
    return IndentationData(x, y, tangential, table.name)
