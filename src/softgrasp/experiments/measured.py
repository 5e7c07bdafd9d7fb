"""Reading measured curves (CSV) with errors that name the file, the line and the column.

A measured-data file is UTF-8 CSV with a header row; blank lines and lines starting with ``#``
are skipped; columns the caller does not ask for are ignored. Column names carry their unit
(``force_N``, ``displacement_mm``, ``stress_kPa``); values are converted to SI units on reading.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from softgrasp.errors import ConfigError

__all__ = ["MeasuredTable", "read_table"]


@dataclass(frozen=True)
class MeasuredTable:
    """The rows of a measured-data file, as text, with their line numbers.

    Attributes
    ----------
    name: the file name, for messages.
    header_line: the file line number of the header row (1-based).
    columns: header names, in file order.
    rows: the data rows' cells (stripped), in file order.
    lines: the file line number of each data row (1-based).
    """

    name: str
    header_line: int
    columns: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    lines: tuple[int, ...]

    def __len__(self) -> int:
        return len(self.rows)

    def has(self, column: str) -> bool:
        """Whether the header names ``column``."""
        return column in self.columns

    def pick(self, *groups: Sequence[str]) -> tuple[str, ...]:
        """The first group of column names that the header has in full.

        Raises ConfigError listing the accepted groups when none is present.
        """
        for g in groups:
            if all(c in self.columns for c in g):
                return tuple(g)
        wanted = " or ".join("+".join(g) for g in groups)
        raise ConfigError(
            f"measured data file {self.name!r}: the header (line {self.header_line}) must name the "
            f"columns {wanted}; it has {','.join(self.columns)!r}"
        )

    def unit_column(self, units: Mapping[str, float]) -> tuple[str, float] | None:
        """The one column among ``units`` (name -> factor to SI) that the header has, or None.

        Raises ConfigError when the header has more than one of them (ambiguous)."""
        found = [c for c in units if c in self.columns]
        if len(found) > 1:
            raise ConfigError(
                f"measured data file {self.name!r} has both {found[0]} and {found[1]}; keep one of them"
            )
        return (found[0], units[found[0]]) if found else None

    def values(self, column: str, scale: float = 1.0) -> NDArray[np.float64]:
        """The column as finite floats times ``scale``; ConfigError naming the line otherwise."""
        j = self.columns.index(column)
        out = np.empty(len(self.rows))
        for i, (row, line) in enumerate(zip(self.rows, self.lines, strict=True)):
            cell = row[j]
            try:
                v = float(cell)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise ConfigError(
                    f"measured data file {self.name!r}, line {line}: {column} = {cell!r} "
                    "is not a finite number"
                )
            out[i] = v * scale
        return out

    def line_of(self, row: int) -> int:
        """File line number of data row ``row`` (0-based)."""
        return self.lines[row]


def read_table(path: str | Path, *, min_rows: int = 2) -> MeasuredTable:
    """Read a measured-data CSV file (see the module docstring).

    Raises
    ------
    ConfigError: missing, unreadable or non-text file; no header; a row with fewer cells than the
        header (the message names the line); fewer than ``min_rows`` data rows.
    """
    p = Path(path)
    name = str(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(f"measured data file {name!r} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"measured data file {name!r} is a directory, not a CSV file") from None
    except UnicodeDecodeError:
        raise ConfigError(f"measured data file {name!r} is not a UTF-8 text (CSV) file") from None
    except OSError as exc:
        raise ConfigError(f"cannot read measured data file {name!r}: {exc.strerror or exc}") from None
    lines = [
        (i, ln)
        for i, ln in enumerate(text.splitlines(), start=1)
        if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if not lines:
        raise ConfigError(f"measured data file {name!r} is empty")
    header = tuple(c.strip() for c in next(csv.reader([lines[0][1]])))
    dup = sorted({c for c in header if c and header.count(c) > 1})
    if dup:
        raise ConfigError(f"measured data file {name!r}, line {lines[0][0]}: column(s) {dup} appear twice")
    rows: list[tuple[str, ...]] = []
    numbers: list[int] = []
    for lineno, ln in lines[1:]:
        row = tuple(c.strip() for c in next(csv.reader([ln])))
        while len(row) > len(header) and not row[-1]:
            row = row[:-1]  # empty trailing cells (a trailing comma)
        if len(row) != len(header):
            raise ConfigError(
                f"measured data file {name!r}, line {lineno}: expected {len(header)} values (one per header "
                f"column), got {len(row)}"
            )
        rows.append(row)
        numbers.append(lineno)
    if len(rows) < min_rows:
        raise ConfigError(
            f"measured data file {name!r} has {len(rows)} data row(s); at least {min_rows} are needed"
        )
    return MeasuredTable(name, lines[0][0], header, tuple(rows), tuple(numbers))
