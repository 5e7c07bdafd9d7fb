"""Sweeps on a real dask.distributed cluster: the rows equal the cases run one by one, a failing
case is a row with its error, an interrupted sweep resumes with only the missing cases."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import softgrasp
from softgrasp.cli import main
from softgrasp.errors import ConfigError
from softgrasp.sweep.case import output_columns, run_case
from softgrasp.sweep.engine import _WORKER_ENV, read_rows, run_sweep
from softgrasp.sweep.spec import read_sweep, sweep_cases

#: Every case: the coarse default sphere, a short hold (about a second a case).
BASE = 'object = "sphere"\nmesh_size = 0.032\nhold_time = 0.3\n'


def _spec(tmp_path: Path, body: str, name: str = "s.toml"):
    f = tmp_path / name
    f.write_text(body)
    return f


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("[grid]\nfriction = [0.5]\n", "'friction' is not an option"),
        ('[sweep]\nmode = "all"\n[grid]\nmu = [0.5]\n', "mode must be 'grid' or 'random'"),
        ("[grid]\nmu = []\n", "must be a non-empty list"),
        ("[grid]\nmu = [0.5, true]\n", "[grid] mu must be a number in [0, 5], got True"),
        ("[random]\nmu = [0.9, 0.3]\n", "needs low < high"),
        ("[random]\nmu = {low = 0, high = 0.9, log = true}\n", "and low > 0 (log)"),
        ("[random]\nE = {low = 0, high = 1e5, log = true}\n", "[random] E must be a number in [10, 1e+09] Pa"),
        ('[random]\nobject = ["a", "b"]\n', "object is not a number to sample"),
        ('[sweep]\nmode = "grid"\n[random]\nmu = [0.3, 0.9]\n', "takes [grid], not [random]"),
        ("[sweep]\nsamples = 0\n[random]\nmu = [0.3, 0.9]\n", "samples must be an integer from 1"),
        ("[plates]\nx = 1\n", "unknown table(s) ['plates']"),
        ("[grid\n", "not valid TOML"),
    ],
)
def test_sweep_file_errors(tmp_path, body, message):
    with pytest.raises(ConfigError) as exc:
        read_sweep(_spec(tmp_path, body))
    assert message in str(exc.value)


def test_cases_grid_and_random(tmp_path):
    grid = read_sweep(_spec(tmp_path, "[base]\n" + BASE + "[grid]\nmu = [0.4, 0.8]\nE = [5e4, 8e4, 1.1e5]\n"))
    cases = sweep_cases(grid)
    assert len(cases) == 6
    assert [(c.options["mu"], c.options["E"]) for c in cases][:4] == [
        (0.4, 5e4),
        (0.4, 8e4),
        (0.4, 1.1e5),
        (0.8, 5e4),
    ]
    assert all(c.options["mesh_size"] == 0.032 for c in cases)
    assert len({c.id for c in cases}) == 6 and [c.id for c in sweep_cases(grid)] == [c.id for c in cases]
    body = "[sweep]\nsamples = 50\nseed = 7\n[random]\nmu = [0.3, 0.9]\n"
    body += "E = {low = 4e4, high = 1.6e5, log = true}\n"
    rnd = sweep_cases(read_sweep(_spec(tmp_path, body, "r.toml")))
    assert len(rnd) == 50 and [c.id for c in rnd] == [
        c.id for c in sweep_cases(read_sweep(tmp_path / "r.toml"))
    ]
    mus = [c.options["mu"] for c in rnd]
    Es = [c.options["E"] for c in rnd]
    assert 0.3 <= min(mus) and max(mus) <= 0.9 and 4e4 <= min(Es) and max(Es) <= 1.6e5
    # log-uniform: about half the samples below the geometric mean (binomial, 50 draws: > 4 sigma)
    below = sum(e < math.sqrt(4e4 * 1.6e5) for e in Es)
    assert 11 <= below <= 39


def test_a_failing_case_is_a_row_not_an_exception():
    row = run_case({"object": "sphere", "mesh_size": 0.032, "nu": 0.6})
    assert row["status"] == "failed"
    assert "Poisson's ratio nu = 0.6 is invalid" in str(row["error"]) and row["error_type"] == "MaterialError"
    assert set(row) == set(output_columns(False)) and math.isnan(row["setpoint_thumb_N"])  # type: ignore[arg-type]
    row = run_case({"object": "no-such-object"})
    assert row["status"] == "failed" and "unknown object" in str(row["error"])


_NUMERIC_OUT = [c for c in output_columns(False) if c not in ("status", "error", "error_type", "wall_time_s")]


@pytest.mark.slow
def test_sweep_on_a_local_tcp_cluster_gives_the_rows_of_the_cases_run_one_by_one(tmp_path):
    """12 cases (6 that plan, 6 whose squeeze limit is too small to hold; mu and E at the ends and
    the middle of their ranges) on 2 worker processes over TCP on loopback:
    every row equals the case run here by itself; the failed cases carry their error."""
    body = "[base]\n" + BASE + "[grid]\nmu = [0.45, 0.9]\nE = [6e4, 9e4, 1.2e5]\nmax_squeeze = [0.5, 0.001]\n"
    spec = read_sweep(_spec(tmp_path, body))
    cases = sweep_cases(spec)
    n = len(cases)
    assert n == 12
    res = run_sweep(spec, cases, tmp_path / "out", workers=2)
    assert res.workers == 2 and res.scheduler.startswith("tcp://127.0.0.1:")
    assert res.ran == n and res.resumed == 0 and res.failed == n // 2
    assert [r["case"] for r in res.rows] == list(range(n))
    on_disk = read_rows(res.csv_path, list(res.rows[0]))
    assert len(on_disk) == n
    import pyarrow.parquet as pq

    table = pq.read_table(res.parquet_path)
    assert table.num_rows == n and table.column("case").to_pylist() == [float(i) for i in range(n)]
    # The same cases one by one, in one fresh process with the workers' settings (one thread per
    # numerical library: the static solver's rounding, and with it the friction path, is the same).
    script = (
        "import json, sys\n"
        "from softgrasp.sweep.case import run_case\n"
        "for options in json.load(sys.stdin):\n"
        "    print(json.dumps(run_case(options)), flush=True)\n"
    )
    env = dict(os.environ, **_WORKER_ENV, PYTHONPATH=str(Path(softgrasp.__file__).resolve().parents[1]))
    done = subprocess.run(
        [sys.executable, "-c", script],
        input=json.dumps([c.options for c in cases]),
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    one_by_one = [json.loads(line) for line in done.stdout.splitlines()]
    assert len(one_by_one) == n
    for case, row, alone in zip(cases, res.rows, one_by_one, strict=True):
        alone = {k: math.nan if v is None else v for k, v in alone.items()}
        assert row["status"] == alone["status"], case.options
        assert row["error"] == alone["error"] and row["error_type"] == alone["error_type"]
        if row["status"] == "failed":
            assert "--max-squeeze" in str(row["error"]) and case.options["max_squeeze"] == 0.001
            continue
        for c in _NUMERIC_OUT:
            # equal to 12 digits; the equilibrium residual (~1e-15 N, round-off) to 1e-12 N
            assert row[c] == pytest.approx(alone[c], rel=1e-12, abs=1e-12), (c, case.options)
    assert all(r["status"] == "ok" for r in res.rows if r["max_squeeze"] == 0.5)


@pytest.mark.slow
def test_an_interrupted_sweep_resumes_with_only_the_missing_cases(tmp_path):
    body = "[sweep]\nsamples = 10\nseed = 2\n[base]\n" + BASE + "[random]\nmu = [0.4, 0.9]\n"
    f = _spec(tmp_path, body)
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(Path(softgrasp.__file__).resolve().parents[1]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "softgrasp.cli", "sweep", str(f), "--out", str(out), "--workers", "1"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    csv_path = out / "results.csv"
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            if csv_path.exists() and len(csv_path.read_text().splitlines()) - 1 >= 3:
                break
            time.sleep(0.2)
        else:
            pytest.fail("the sweep wrote no rows within two minutes")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    spec = read_sweep(f)
    cases = sweep_cases(spec)
    cols = ["case", "case_id", *spec.inputs, *output_columns(False)]
    before = read_rows(csv_path, cols)
    assert 3 <= len(before) < 10, "the sweep was not interrupted half-way"
    with pytest.raises(ConfigError, match="add --resume"):
        run_sweep(spec, cases, out, workers=1)
    res = run_sweep(spec, cases, out, workers=2, resume=True)
    assert res.resumed == len(before) and res.ran == 10 - len(before)
    assert sorted(r["case_id"] for r in res.rows) == sorted(c.id for c in cases)
    kept = {r["case_id"]: r["wall_time_s"] for r in before}
    for r in res.rows:  # the rows of the first run are kept as they were, not run again
        if r["case_id"] in kept:
            assert r["wall_time_s"] == kept[r["case_id"]]
    assert len(read_rows(csv_path, cols)) == 10


def test_sweep_command_writes_table_and_figures(tmp_path, capsys):
    body = "[base]\n" + BASE + "[grid]\nmu = [0.5, 0.9]\nE = [6e4, 1.2e5]\n"
    out = tmp_path / "out"
    assert main(["sweep", str(_spec(tmp_path, body)), "--out", str(out), "--workers", "2"]) == 0
    text = capsys.readouterr().out
    assert "4 cases: 4 planned, 0 failed" in text
    for name in ("results.csv", "results.parquet", "force_vs_mu.png", "force_vs_E.png", "success_map.png"):
        assert (out / name).stat().st_size > 1000, name
    head = json.loads((out / "sweep.json").read_text())
    assert head["cases"] == 4 and head["grid"] == {"mu": [0.5, 0.9], "E": [6e4, 1.2e5]}
    # friction carries the weight: more friction, less squeeze, at either stiffness
    rows = read_rows(out / "results.csv", (out / "results.csv").read_text().splitlines()[0].split(","))
    by = {(r["mu"], r["E"]): r["setpoint_sum_N"] for r in rows}
    assert by[(0.9, 6e4)] < by[(0.5, 6e4)] and by[(0.9, 1.2e5)] < by[(0.5, 1.2e5)]
    assert main(["sweep", str(tmp_path / "s.toml"), "--out", str(out)]) == 2
    assert "add --resume" in capsys.readouterr().err


def test_a_local_cluster_leaves_dasks_default_port_to_others():
    """With Dask's default port 8787 held by someone else (another cluster's dashboard), a local
    cluster starts without a word about it: its scheduler's HTTP routes take a free port."""
    import socket
    import warnings

    from softgrasp.sweep.engine import dask_client

    holder = socket.socket()
    try:
        holder.bind(("127.0.0.1", 8787))
        holder.listen()
    except OSError:
        pass  # already held: the same situation
    try:
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            with dask_client(workers=1) as client:
                assert client.submit(sum, [1, 2]).result() == 3
    finally:
        holder.close()
    assert not [w for w in seen if "already in use" in str(w.message)], [str(w.message) for w in seen]
