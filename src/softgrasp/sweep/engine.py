"""Running a sweep on Dask, streaming one row per finished case into a results table.

The cases run on a ``dask.distributed`` cluster: a local one (worker processes on this machine,
talking TCP on the loopback interface) by default, or an existing cluster at ``scheduler``
(``tcp://host:port``), whose workers need softgrasp installed. Each finished case is appended at
once to ``results.csv`` (flushed: a killed sweep keeps every row it finished), and
``results.parquet`` is rewritten atomically as rows arrive and at the end, sorted by case.
``resume=True`` reads the finished rows back (one per case) and runs only the missing cases, after
checking that ``sweep.json`` records the same sweep (the digest of its normalised spec). The output
folder is locked while the sweep runs; its figures and the files of other commands are replaced
whole (:mod:`softgrasp.io.runfolder`).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from softgrasp import __version__
from softgrasp.errors import ConfigError
from softgrasp.io.atomic import atomic_write, write_json
from softgrasp.io.portable import PATH_OPTIONS, portable_options, portable_path
from softgrasp.sweep.case import output_columns, run_case
from softgrasp.sweep.spec import Case, SweepSpec, describe_spec, spec_digest

__all__ = ["SweepResult", "run_sweep", "dask_client", "check_scheduler", "read_rows", "columns"]

#: Seconds between rewrites of the Parquet table while rows stream in.
PARQUET_EVERY = 10.0
#: Thread counts of the numerical libraries in each worker (one case per core).
_WORKER_ENV = {
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
    "SOFTGRASP_THREADS": "1",
}


@dataclass(frozen=True)
class SweepResult:
    """A finished sweep.

    Attributes
    ----------
    rows: every case's row (inputs and outputs), sorted by case index.
    ran: cases run by this call.  resumed: finished rows read back (``resume``).
    failed: cases whose status is ``failed``.
    csv_path, parquet_path: the results table.
    wall_time_s: seconds.  workers: the cluster's workers.
    scheduler: the address of the Dask scheduler that ran the cases ("" when none was needed).
    """

    rows: list[dict[str, object]]
    ran: int
    resumed: int
    failed: int
    csv_path: Path
    parquet_path: Path
    wall_time_s: float
    workers: int
    scheduler: str = ""


def columns(spec: SweepSpec) -> list[str]:
    """The results table's columns: case index and id, the inputs, then the outputs."""
    outputs = output_columns(spec.execute, spec.hold is not None, spec.fingers)
    return ["case", "case_id", *spec.inputs, *outputs]


def _parse(value: str, column: str) -> object:
    """A CSV cell back to a value: numbers as floats (ints for counts), booleans, text."""
    if column in ("case", "nodes", "increments"):
        return int(float(value)) if value not in ("", "nan") else math.nan
    if value in ("True", "False"):
        return value == "True"
    try:
        return float(value)
    except ValueError:
        return value


def read_rows(path: Path, cols: Sequence[str]) -> list[dict[str, object]]:
    """The complete rows of a results CSV (a row cut short by a killed sweep is dropped).

    Raises ConfigError when the file's columns are not this sweep's (another sweep's results).
    """
    text = path.read_text(encoding="utf-8")
    reader = csv.reader(io.StringIO(text))
    header = next(reader, None)
    if header is None:
        return []
    if list(header) != list(cols):
        raise ConfigError(
            f"{path} holds the results of another sweep (its columns differ); give another --out or remove it"
        )
    complete = text.endswith("\n")
    lines = list(reader)
    if lines and not complete:
        lines = lines[:-1]  # the last row was being written when the sweep was killed
    rows = []
    for cells in lines:
        if len(cells) != len(cols) or cells[cols.index("status")] not in ("ok", "failed"):
            continue
        rows.append({c: _parse(v, c) for c, v in zip(cols, cells, strict=True)})
    return rows


def _cell(v: object) -> str:
    if isinstance(v, float):
        return repr(v)
    return "" if v is None else str(v)


def _write_csv(path: Path, cols: Sequence[str], rows: Sequence[dict[str, object]]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in cols])
    atomic_write(path, lambda p: p.write_text(buf.getvalue(), encoding="utf-8"))


def _write_parquet(path: Path, cols: Sequence[str], rows: Sequence[dict[str, object]]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    ordered = sorted(rows, key=lambda r: int(r["case"]))  # type: ignore[call-overload]
    data = {}
    for c in cols:
        vals = [r.get(c) for r in ordered]
        if all(isinstance(v, bool) or v is None or (isinstance(v, float) and math.isnan(v)) for v in vals):
            data[c] = pa.array([v if isinstance(v, bool) else None for v in vals], type=pa.bool_())
        elif all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
            data[c] = pa.array([float(v) for v in vals], type=pa.float64())  # type: ignore[arg-type]
        else:
            data[c] = pa.array([None if v is None else str(v) for v in vals], type=pa.string())
    table = pa.table(data)
    atomic_write(path, lambda p: pq.write_table(table, p))


@contextmanager
def _signals_deferred() -> Iterator[list[Callable[[], None]]]:
    """A Ctrl-C (SIGINT) or SIGTERM received in this block is remembered and acted on at its end.

    The block runs to its end (a cluster is never left half started or half closed); then, if a
    signal came meanwhile, the callables the block added to the yielded list run (closing what it
    started) and the signal is raised again, reaching the handler it would have reached
    (``KeyboardInterrupt`` for a Ctrl-C).

    SIGINT is also blocked in this thread meanwhile, and the threads and processes started in the
    block inherit that mask: Dask's worker processes (and their threads) keep SIGINT blocked for
    life, so a Ctrl-C at the terminal, which reaches every process of the group, interrupts only
    this one, which then shuts the cluster down; no worker prints a traceback or outlives the run.
    Multiprocessing's resource tracker unblocks SIGINT in the thread that starts it, so it is
    started here first."""
    import signal
    import threading

    undo: list[Callable[[], None]] = []
    if threading.current_thread() is not threading.main_thread():
        yield undo
        return
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    caught: list[int] = []
    sigs = (signal.SIGINT, signal.SIGTERM)
    before = {s: signal.getsignal(s) for s in sigs}
    for s in sigs:
        signal.signal(s, lambda n, _f: caught.append(n))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    ok = False
    try:
        yield undo
        ok = True
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a Ctrl-C kept pending is recorded now
        try:
            if caught and ok:
                for f in reversed(undo):
                    f()
        finally:
            for s, h in before.items():
                signal.signal(s, h if h is not None else signal.SIG_DFL)
            if caught:
                signal.raise_signal(caught[0])


def _close(client: Any, cluster: Any) -> None:
    """Close a client (and the local cluster it ran on) without being interrupted halfway."""
    with _signals_deferred():
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()


def _client(scheduler: str | None, workers: int):
    """A Dask client: of the cluster at ``scheduler``, or of a new local one (TCP on loopback)
    whose worker processes never see SIGINT; a Ctrl-C during the start closes the new cluster
    and then interrupts (:func:`_signals_deferred`)."""
    with _signals_deferred() as undo:
        client, cluster = _start_client(scheduler, workers)
        undo.append(lambda: _close(client, cluster))
    return client, cluster


def check_scheduler(address: str, timeout_s: float = 5.0) -> None:
    """ConfigError at once when nothing answers at the Dask scheduler ``address`` (a TCP address
    as :func:`softgrasp.io.options.scheduler_address` reads it): checked before any work, where the
    Dask client would retry for 20 s after it. Other protocols are left to the client."""
    import re
    import socket

    m = re.fullmatch(r"(?:tcp://)?\[?([^\[\]/]+?)\]?:(\d+)", address)
    if m is None:
        return
    try:
        socket.create_connection((m.group(1), int(m.group(2))), timeout=timeout_s).close()
    except OSError as exc:
        why = exc.strerror or str(exc) or type(exc).__name__
        raise ConfigError(
            f"cannot reach the Dask scheduler at {address}: {why.lower()}; start one there "
            "(dask scheduler) or leave --scheduler out for a local cluster"
        ) from None


def _start_client(scheduler: str | None, workers: int):
    from dask.distributed import Client, LocalCluster

    if not 1 <= workers <= 256:
        raise ConfigError(f"--workers must be from 1 to 256, got {workers}")
    if scheduler is not None:
        try:
            return Client(scheduler, timeout="20s"), None
        except (OSError, TimeoutError) as exc:
            raise ConfigError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        protocol="tcp",
        host="127.0.0.1",
        dashboard_address=None,
        # the scheduler's HTTP routes on a free port: no clash (and no warning) where another
        # cluster already holds Dask's default 8787
        scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
        silence_logs=logging.ERROR,
        env=_WORKER_ENV,  # the worker processes' environment (this process's stays as it is)
    )
    return Client(cluster), cluster


@contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2) -> Iterator[Any]:
    """A Dask client for several sweeps in a row (one cluster start): of the cluster at
    ``scheduler``, or of a local cluster of ``workers`` processes, closed on exit."""
    client, cluster = _client(scheduler, workers)
    try:
        yield client
    finally:
        _close(client, cluster)


def _portable_spec(doc: dict[str, Any], folder: Path) -> dict[str, Any]:
    """A sweep's description with the files it names relative to its output ``folder``."""
    out = dict(doc)
    out["base"] = portable_options(doc.get("base") or {}, folder)
    out["grid"] = {
        k: [portable_path(v, folder) if k in PATH_OPTIONS and isinstance(v, str) else v for v in vals]
        for k, vals in (doc.get("grid") or {}).items()
    }
    if isinstance(doc.get("source"), str):
        out["source"] = portable_path(doc["source"], folder)
    return out


def _resumable(
    out: Path, json_path: Path, csv_path: Path, spec: SweepSpec, cases: Sequence[Case], cols: Sequence[str]
) -> list[dict[str, object]]:
    """The finished rows of the sweep in ``out`` to keep, one per case, or ConfigError when that
    sweep was made by another sweep file (its ``sweep.json`` records the digest of its spec)."""
    try:
        made = json.loads(json_path.read_text(encoding="utf-8"))
        recorded = made.get("spec_sha256") or spec_digest(made)
    except (FileNotFoundError, ValueError, AttributeError, KeyError, TypeError):
        raise ConfigError(
            f"{out} holds results.csv but no readable sweep.json naming the sweep that made it, so --resume "
            "cannot check it is this sweep's; give another --out"
        ) from None
    if recorded != spec_digest(spec):
        raise ConfigError(
            f"--resume: {out} was made by another sweep file ({made.get('source', '?')}: its cases differ "
            f"from {spec.source}'s); resume with that file, or give another --out"
        )
    ids = {c.index: c.id for c in cases}
    kept: dict[int, dict[str, object]] = {}
    for r in read_rows(csv_path, cols):
        i = r["case"]
        if isinstance(i, int) and ids.get(i) == r["case_id"] and i not in kept:
            kept[i] = r  # one row per case: a case written twice counts once
    return [kept[i] for i in sorted(kept)]


def run_sweep(
    spec: SweepSpec,
    cases: Sequence[Case],
    out: str | Path,
    *,
    scheduler: str | None = None,
    workers: int = 2,
    resume: bool = False,
    progress: Callable[[int, int], None] | None = None,
    client: Any = None,
) -> SweepResult:
    """Run ``cases`` of ``spec`` on Dask and write ``out/results.csv`` and ``results.parquet``.

    Parameters
    ----------
    spec, cases: the sweep and its cases (:func:`softgrasp.sweep.spec.sweep_cases`).
    out: the output folder, locked while the sweep runs (:mod:`softgrasp.io.runfolder`).
    scheduler: address of a running Dask scheduler (``tcp://host:port``); None: a local cluster.
    workers: worker processes of the local cluster.
    resume: keep the finished rows of ``out/results.csv`` (one per case) and run only the missing
        cases; without it, existing results are an error (never silently overwritten).
    progress: called with (finished cases, all cases) as rows arrive.
    client: a Dask client to run the cases on (:func:`dask_client`; ``scheduler`` and ``workers``
        are then not used); None: one is made for this sweep and closed at its end.

    Raises
    ------
    ConfigError: results exist without ``resume``, or were made by another sweep file (the digest
    of the spec in ``sweep.json``); another run is writing ``out``; no scheduler there.
    """
    from softgrasp.io.runfolder import run_folder

    if client is None and not 1 <= workers <= 256:
        raise ConfigError(f"--workers must be from 1 to 256, got {workers}")
    with run_folder(out, "sweep") as folder:
        return _run(spec, cases, folder, scheduler, workers, resume, progress, client)


def _run(
    spec: SweepSpec,
    cases: Sequence[Case],
    folder: Any,
    scheduler: str | None,
    workers: int,
    resume: bool,
    progress: Callable[[int, int], None] | None,
    client: Any,
) -> SweepResult:
    t0 = time.perf_counter()
    cols = columns(spec)
    # The table grows in place as cases finish (what --resume continues from).
    csv_path, pq_path = folder.live("results.csv"), folder.live("results.parquet")
    json_path = folder.live("sweep.json")
    done: list[dict[str, object]] = []
    if csv_path.exists():
        if not resume:
            raise ConfigError(
                f"{folder.path / 'results.csv'} exists: add --resume to finish that sweep, "
                "or give another --out"
            )
        done = _resumable(folder.path, json_path, csv_path, spec, cases, cols)
    finished = {int(r["case"]) for r in done}  # type: ignore[call-overload]
    todo = [c for c in cases if c.index not in finished]
    rows = list(done)
    n_workers, address = 0, ""
    own = client is None and bool(todo)
    cluster = None
    if own:
        client, cluster = _client(scheduler, workers)  # reached before the folder changes
    try:
        _write_csv(csv_path, cols, done)  # the finished rows, clean, then appended to
        doc = {"schema": "softgrasp.sweep/1", **_portable_spec(describe_spec(spec), folder.path)}
        doc.update(cases=len(cases), softgrasp_version=__version__)
        write_json(json_path, {**doc, "spec_sha256": spec_digest(spec)})
        if progress is not None:
            progress(len(rows), len(cases))
        if todo:
            from dask.distributed import as_completed

            info = client.scheduler_info()
            n_workers, address = len(info.get("workers", {})), str(info.get("address", ""))
            token = uuid.uuid4().hex[:8]  # keys unique on a client shared by several sweeps
            futures = {
                client.submit(
                    run_case,
                    c.options,
                    spec.execute,
                    spec.hold,
                    spec.fingers,
                    key=f"softgrasp-case-{c.id}-{c.index}-{token}",
                    pure=False,
                ): c
                for c in todo
            }
            last_pq = time.perf_counter()
            with open(csv_path, "a", encoding="utf-8", newline="") as fh:
                w = csv.writer(fh, lineterminator="\n")
                for fut in as_completed(futures):
                    case = futures[fut]
                    try:
                        result = fut.result()
                    except Exception as exc:  # noqa: BLE001 - a lost worker: the case failed
                        result = dict.fromkeys(
                            output_columns(spec.execute, spec.hold is not None, spec.fingers), math.nan
                        )
                        kind = type(exc).__name__
                        result.update(status="failed", error=f"{kind}: {exc}", error_type=kind)
                    options = portable_options(case.options, folder.path)
                    row = {"case": case.index, "case_id": case.id, **options, **result}
                    for c in spec.inputs:
                        row.setdefault(c, None)
                    w.writerow([_cell(row.get(c)) for c in cols])
                    fh.flush()
                    rows.append(row)
                    if progress is not None:
                        progress(len(rows), len(cases))
                    if time.perf_counter() - last_pq > PARQUET_EVERY:
                        _write_parquet(pq_path, cols, rows)
                        last_pq = time.perf_counter()
    finally:
        _close(client if own else None, cluster)
    rows.sort(key=lambda r: int(r["case"]))  # type: ignore[call-overload]
    _write_parquet(pq_path, cols, rows)
    return SweepResult(
        rows=rows,
        ran=len(todo),
        resumed=len(done),
        failed=sum(r["status"] == "failed" for r in rows),
        csv_path=folder.path / "results.csv",
        parquet_path=folder.path / "results.parquet",
        wall_time_s=time.perf_counter() - t0,
        workers=n_workers,
        scheduler=address,
    )
