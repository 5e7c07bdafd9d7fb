"""Figures of a finished sweep: set-points against mu and E, and a success map over two options."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from softgrasp.sweep.spec import SweepSpec

__all__ = ["sweep_figures"]


def _numeric(rows: Sequence[dict[str, object]], name: str) -> bool:
    return all(isinstance(r.get(name), (int, float)) and not isinstance(r.get(name), bool) for r in rows)


def sweep_figures(spec: SweepSpec, rows: Sequence[dict[str, object]], out: str | Path) -> list[Path]:
    """Write the sweep's figures into ``out``: ``force_vs_<option>.png`` for mu and E when they
    vary (any other varied number when neither does), and ``success_map.png`` over the first two
    varied numeric options. Returns the files written."""
    out = Path(out)
    from softgrasp.viz.plots import plot_success_map, plot_sweep_forces

    varied = [v for v in spec.varied if _numeric(rows, v) and len({r[v] for r in rows}) > 1]
    ok = np.array([r["status"] == "ok" for r in rows], dtype=bool)
    written: list[Path] = []
    against = [v for v in ("mu", "E") if v in varied] or varied[:1]
    for v in against:
        x = np.array([float(r[v]) for r in rows])  # type: ignore[arg-type]
        sp = np.array([[float(r[f"setpoint_{f}_N"]) for f in spec.fingers] for r in rows])  # type: ignore[arg-type]
        written.append(
            plot_sweep_forces(
                out / f"force_vs_{v}.png",
                x[ok],
                sp[ok],
                spec.fingers,
                parameter=v,
                title=f"Set-points against {v} ({ok.sum()} of {len(rows)} cases planned)",
                failed=x[~ok],
            )
        )
    if len(varied) >= 2:
        a, b = varied[:2]
        written.append(
            plot_success_map(
                out / "success_map.png",
                np.array([float(r[a]) for r in rows]),  # type: ignore[arg-type]
                np.array([float(r[b]) for r in rows]),  # type: ignore[arg-type]
                ok,
                np.array([float(r["setpoint_sum_N"]) for r in rows]),  # type: ignore[arg-type]
                x_name=a,
                y_name=b,
                title=f"Success map: {ok.sum()} of {len(rows)} cases planned",
            )
        )
    return written
