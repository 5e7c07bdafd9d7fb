"""The command line a person expects: progress by phase that never goes backwards, a "compiling
kernels" status on a cold cache, global options anywhere, a run given as its folder or its
plan.json, distinct exit statuses, ``python -m softgrasp``, every command's help with an example,
and a message naming the extra to install when a command's optional dependency is missing."""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shlex
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from softgrasp.cli import build_parser, main
from softgrasp.cli.help import COMMANDS
from softgrasp.cli.progress import PLAN_SHARES, PhaseBar, kernels_phase
from softgrasp.cli.status import EXIT_CODES, exit_status
from softgrasp.errors import (
    ConfigError,
    ContactError,
    InfeasibleGrasp,
    MaterialError,
    MeshError,
    NotConverged,
    SimulationUnstable,
)
from softgrasp.grasp.progress import PHASES, PlanProgress

SRC = str(Path(__file__).resolve().parents[1] / "src")
ENV = {**os.environ, "PYTHONPATH": SRC}
#: A coarse plan of the default sphere: a few seconds.
COARSE = ["plan", "--mesh-size", "0.032", "--hold-time", "0.3"]


@pytest.fixture(scope="module")
def coarse_run(tmp_path_factory) -> tuple[Path, str, list[float], list[str]]:
    """A coarse plan by the command line: its folder, what it printed on stderr (not a terminal),
    and the fractions done and phases the planner reported to it."""
    import softgrasp.api.planning as planning

    out = tmp_path_factory.mktemp("coarse") / "run"
    err = io.StringIO()
    fractions: list[float] = []
    phases: list[str] = []
    plan = planning.plan

    def recorded(*args, progress, phase, **kwargs):
        def fraction(f: float) -> None:
            fractions.append(f)
            progress(f)

        def named(name: str) -> None:
            phases.append(name)
            phase(name)

        return plan(*args, progress=fraction, phase=named, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(planning, "plan", recorded)
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            assert main([*COARSE, "--out", str(out)]) == 0
    return out, err.getvalue(), fractions, phases


# ------------------------------------------------------------------------------ progress
def test_plan_prints_one_line_per_phase_off_a_terminal(coarse_run):
    err = coarse_run[1]
    lines = err.strip().splitlines()
    names = [line.removeprefix("softgrasp: plan: ") for line in lines]
    assert all(line.startswith("softgrasp: plan: ") for line in lines), err
    kernels = [n for n in names if "kernels" in n]  # loading, or compiling on a first run, or done
    assert names[len(kernels) :] == [*PHASES, "figures"], err
    # one line, or a first run's (a cache another test left stale): what it compiles, group by group
    assert len(kernels) <= 1 or all(k.startswith("compiling kernels") for k in kernels), err
    assert "%" not in err  # no bar off a terminal


def test_a_margin_held_at_every_scale_tried_says_so(tmp_path, capsys, monkeypatch):
    """A critical-scale search whose every scale tried holds, down to its lowest: the search of
    the default plan, started at and floored at 1 times the held forces, which hold there (the
    closing stops where they first hold). The margin line says that, and that the least that
    holds lies lower, instead of naming a scale not held (plan.json: ``not_held_scale`` 0)."""
    from softgrasp.grasp import margin as margin_module
    from softgrasp.grasp import planner

    def floored(body, config, normal_N, **kw):
        return margin_module.critical_scale(body, config, normal_N, **dict(kw, guess=1.0, lowest=1.0))

    monkeypatch.setattr(planner, "critical_scale", floored)
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main([*COARSE, "--out", str(tmp_path / "floored")]) == 0
    margin = json.loads((tmp_path / "floored" / "plan.json").read_text())["margin"]
    assert margin["not_held_scale"] == 0.0
    assert margin["critical_scale"] == pytest.approx(1.0 / margin["safety_factor"])  # the held forces
    assert [c["held"] for c in margin["checks"]] == [True]
    line = next(x for x in out.getvalue().splitlines() if x.startswith("margin:"))
    assert f"held at every scale tried, down to {margin['critical_scale']:.2f} x the set-points" in line
    assert "least that holds" in line and "not at" not in line


def test_set_points_without_room_to_the_least_that_holds_are_noted(coarse_run, tmp_path, capsys):
    """The default plan's set-points are 1.25 times the least normal forces that hold: no note.
    With --safety-factor 1 a scale of them within the force controller's 5 % tolerance is not
    held, and the command says so and what to change."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main([*COARSE, "--safety-factor", "1", "--out", str(tmp_path / "tight")]) == 0
    tight = json.loads((tmp_path / "tight" / "plan.json").read_text())["margin"]
    assert tight["not_held_scale"] >= 0.95
    assert f"note: at {tight['not_held_scale']:.2f} x the set-points the object is not held" in out.getvalue()
    assert "--safety-factor" in out.getvalue()
    # the margin line: the least scale held and the one not held, printed apart (3 decimals where 2
    # would print them alike), each the plan.json's
    held, not_held = re.search(
        r"held down to ([\d.]+) x the set-points, not at ([\d.]+)", out.getvalue()
    ).groups()
    assert held != not_held
    assert float(held) == pytest.approx(tight["critical_scale"], abs=0.005)
    assert float(not_held) == pytest.approx(tight["not_held_scale"], abs=0.005)
    roomy = json.loads((coarse_run[0] / "plan.json").read_text())["margin"]
    assert roomy["not_held_scale"] < 0.95
    with contextlib.redirect_stdout(out := io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main([*COARSE, "--out", str(tmp_path / "roomy")]) == 0
    assert "note:" not in out.getvalue()


def test_plan_names_each_hold_check_that_did_not_hold_and_only_those(tmp_path):
    """The 5 kPa rubber sphere is not held at the closing's first hold check; the least travel
    held is then bracketed, by checks that hold and checks that do not. The command prints one
    line per check that did not hold, with its travel and why (the plan.json's), none for a
    check that held, and no advice on load steps: a release step that finds no equilibrium is
    the check's verdict, not something a user could change."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main([*COARSE, "--material", "rubber,E=5000", "--out", str(tmp_path / "soft")]) == 0
    checks = json.loads((tmp_path / "soft" / "plan.json").read_text())["hold"]["checks"]
    failed = [c for c in checks if c["result"] != "held"]
    assert failed and len(failed) < len(checks) - 1, checks  # held checks before the last one too
    lines = [line for line in out.getvalue().splitlines() if line.startswith("not held at ")]
    assert lines == [
        f"not held at {c['travel_m'] * 1e3:.2f} mm of travel: {c['result']}; closed further" for c in failed
    ]
    assert "load steps" not in out.getvalue()


def test_the_planners_progress_never_goes_back_and_passes_every_phase(coarse_run):
    _, _, fractions, phases = coarse_run
    assert phases == list(PHASES)
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    # The closing moves the bar in steps, not 0 then 100 %.
    assert len(set(fractions)) >= 6 and sum(0.0 < f < 1.0 for f in fractions) >= 5, fractions


def test_plan_progress_ignores_a_step_back_and_reports_only_in_its_phase():
    seen: list[float] = []
    names: list[str] = []
    p = PlanProgress(seen.append, names.append)
    closing = p.within("closing")
    closing(0.5)  # before the closing starts: not reported
    p.enter("initial grasp")
    p.enter("closing")
    closing(0.4)
    closing(0.3)  # the solve for the least passing travel steps back: the bar does not
    closing(0.6)
    p.enter("hold check")
    closing(1.0)  # the closing's increments during the hold check do not move the bar
    p.finish()
    assert names == ["initial grasp", "closing", "hold check"]
    assert seen == sorted(seen) and seen[-1] == 1.0
    assert seen == pytest.approx([0.15, 0.15 + 0.45 * 0.4, 0.15 + 0.45 * 0.6, 0.6, 1.0])


def test_the_bar_on_a_terminal_is_labelled_by_phase_and_never_goes_back(monkeypatch):
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    bar = PhaseBar("plan", PLAN_SHARES, tty=True)
    bar.phase("meshing", quiet=True)
    bar.phase("loading kernels")
    update = bar.within("planning")
    shown = []
    for f in (0.1, 0.5, 0.3, 0.9):
        update(f)
        shown.append(bar.done)
    bar.close()
    assert shown == sorted(shown) and shown[2] == shown[1]
    text = err.getvalue()
    assert "plan: meshing" in text and "plan: loading kernels" in text and "%|" in text


def test_quiet_phases_print_no_line_off_a_terminal(capsys):
    bar = PhaseBar("plan", PLAN_SHARES, tty=False)
    bar.phase("meshing", quiet=True)
    bar.phase("closing")
    bar.close()
    assert capsys.readouterr().err == "softgrasp: plan: closing\n"


class _WarmUp:
    """A stand-in for :class:`softgrasp.cli.warm.WarmUp` that has found the cache cold or warm."""

    def __init__(self, cold: bool, compiles: tuple[str, ...] = ()) -> None:
        import threading

        self.cold, self.checked = cold, threading.Event()
        self.checked.set()
        self.compiles, self.compiling = list(compiles), ""
        self.alive = 2 + len(compiles)

    def is_alive(self) -> bool:
        self.alive -= 1
        return self.alive >= 0

    def join(self, timeout: float | None = None) -> None:
        if self.compiles:
            self.compiling = self.compiles.pop(0)


@pytest.mark.parametrize(
    ("cold", "line"), [(True, "compiling kernels (first run only, ~"), (False, "loading kernels")]
)
def test_waiting_for_the_kernels_says_whether_they_compile(capsys, cold, line):
    bar = PhaseBar("plan", PLAN_SHARES, tty=False)
    kernels_phase(bar, _WarmUp(cold))
    err = capsys.readouterr().err
    assert err.startswith(f"softgrasp: plan: {line}") and err.count("\n") == 1, err
    if cold:  # the planner's part of the bar starts where the compiling's ends
        assert bar.shares["planning"][0] == PLAN_SHARES["compiling kernels"][1]


def test_a_first_run_names_what_it_compiles_once_each(capsys):
    groups = ("body forces", "fingertip contact", "body forces", "hand kinematics")
    kernels_phase(PhaseBar("plan", PLAN_SHARES, tty=False), _WarmUp(True, groups))
    lines = capsys.readouterr().err.splitlines()
    assert lines[1:] == [
        "softgrasp: plan: compiling kernels: body forces",
        "softgrasp: plan: compiling kernels: fingertip contact",
        "softgrasp: plan: compiling kernels: hand kinematics",
    ]


def test_every_kernel_module_has_a_name_for_the_first_run():
    from softgrasp.cli.warm import kernel_group
    from softgrasp.jitcache import KERNEL_MODULES

    assert all(kernel_group(m) for m in KERNEL_MODULES)
    assert kernel_group("numba.np.linalg") == ""


def test_a_cold_kernel_cache_is_told_from_a_warm_one(tmp_path):
    """:func:`softgrasp.jitcache.cached` reads a kernel's cache index: no machine code for the current
    sources before the first call, some after it (also in a new process); another digest of the
    sources has none. :func:`softgrasp.cli.warm.cold` and :func:`~softgrasp.cli.warm.solvers_cold`
    say so for an empty cache folder, and not once the kernels are loaded (compiled if need be)."""
    (tmp_path / "kern.py").write_text(
        textwrap.dedent(
            """
            from softgrasp import jitcache

            @jitcache.jit()
            def twice(x):
                return 2 * x
            """
        )
    )
    probe = (
        f"import sys; sys.path.insert(0, {str(tmp_path)!r}); from softgrasp import jitcache; import kern; "
        "print(jitcache.cached(kern.twice)); kern.twice(2.0); print(jitcache.cached(kern.twice)); "
        "kern.twice._cache.digest = '0' * 64; print(jitcache.cached(kern.twice))"
    )
    env = {**ENV, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    first = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=120
    )
    again = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True, timeout=120
    )
    assert first.stdout.split() == ["False", "True", "False"], first.stderr
    assert again.stdout.split() == ["True", "True", "False"], again.stderr
    empty = {**ENV, "NUMBA_CACHE_DIR": str(tmp_path / "empty")}
    from softgrasp.cli.warm import warm_up, warm_up_solvers

    warm_up()
    warm_up_solvers()
    probe = "from softgrasp.cli.warm import cold, solvers_cold; print(cold(), solvers_cold())"
    for where, expected in ((empty, ["True", "True"]), (ENV, ["False", "False"])):
        told = subprocess.run(
            [sys.executable, "-c", probe], env=where, capture_output=True, text=True, timeout=120
        )
        assert told.stdout.split() == expected, told.stderr


def test_the_install_compiles_the_kernels_ahead_and_says_so_only_when_it_does(monkeypatch, capsys):
    """``python -m softgrasp.cli.warm`` (the Makefile's install runs it): on a cold cache it says
    it compiles and compiles the fingertip contact's kernels in a second process; on a warm one it
    loads them quietly; then the other solvers' kernels, saying so when they compile; a failure
    is one line and does not fail the install. The Makefile runs it after both installs."""
    from softgrasp.cli import warm

    calls = []
    monkeypatch.setattr(warm, "warm_up", lambda split=False: calls.append(split))
    monkeypatch.setattr(warm, "warm_up_solvers", lambda: calls.append("solvers"))
    for first in (True, False):
        monkeypatch.setattr(warm, "cold", lambda first=first: first)
        monkeypatch.setattr(warm, "solvers_cold", lambda first=first: not first)
        assert warm.main() == 0
        err = capsys.readouterr().err
        assert ("compiling kernels (first run only" in err) is first, err
        solvers = "compiling the dynamic and multigrid solvers' and the nodal volume term's kernels"
        assert (solvers in err) is not first, err
    assert calls == [True, "solvers", False, "solvers"]

    def broken(split=False):
        raise RuntimeError("no space left on device")

    monkeypatch.setattr(warm, "warm_up", broken)
    assert warm.main() == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no space left on device" in err[0] and "first plan compiles" in err[0]
    makefile = (Path(__file__).resolve().parents[1] / "Makefile").read_text()
    for target in ("install:", "install-test:"):
        recipe = makefile.split("\n" + target, 1)[1].split("\n\n", 1)[0]
        assert "-m softgrasp.cli.warm" in recipe, recipe
        assert "-m compileall -q src/softgrasp" in recipe, recipe  # the bytecode, written ahead


def test_the_collector_pause_ends_once_and_only_if_it_began(monkeypatch):
    """:func:`~softgrasp.cli.warm.pause_collector` turns the cyclic garbage collector off;
    :func:`~softgrasp.cli.warm.resume_collector` turns it on again, the objects made meanwhile
    frozen, once; a collector someone else turned off stays off; a warm-up that finds the kernel
    cache cold (it will compile) resumes it itself."""
    import gc

    from softgrasp.cli import warm

    assert gc.isenabled()
    frozen = gc.get_freeze_count()
    try:
        warm.pause_collector()
        assert not gc.isenabled()
        junk = [[i] for i in range(1000)]  # made while paused
        warm.resume_collector()
        assert gc.isenabled() and gc.get_freeze_count() >= frozen + len(junk)
        gc.disable()
        warm.resume_collector()  # nothing left to resume
        assert not gc.isenabled()
        warm.pause_collector()  # off already: not this pause's to end
        warm.resume_collector()
        assert not gc.isenabled()
        gc.enable()
        warm.pause_collector()
        monkeypatch.setattr(warm, "_loaded", False)  # (a warm-up run earlier in this process)
        monkeypatch.setattr(warm, "cold", lambda: True)
        monkeypatch.setattr(warm, "_quietly", lambda split=False: None)
        thread = warm.WarmUp()
        thread.start()
        thread.join(timeout=60)
        assert gc.isenabled()
    finally:
        gc.enable()
        gc.unfreeze()


def test_the_plan_command_collects_no_garbage_until_its_kernels_are_loaded(tmp_path):
    """The ``softgrasp plan`` process: the collector is off while it imports and loads its
    kernels (the meshing phase), on from the first planner phase; a command called with its
    arguments in a caller's process leaves the caller's collector alone."""
    script = textwrap.dedent(
        f"""
        import gc, sys
        from softgrasp.cli import main, progress
        seen = []
        phase = progress.PhaseBar.phase
        def record(self, name, *args, **kwargs):
            seen.append((name, gc.isenabled()))
            return phase(self, name, *args, **kwargs)
        progress.PhaseBar.phase = record
        sys.argv = ["softgrasp", "plan", "--out", {str(tmp_path / "run")!r}]
        status = main()
        print(status, seen)
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    status, seen = out.stdout.strip().splitlines()[-1].split(" ", 1)
    assert status == "0"
    phases = dict(eval(seen))  # noqa: S307 - the list printed just above
    assert phases["meshing"] is False and phases["initial grasp"] is True, phases
    assert all(phases[name] for name in ("closing", "hold check", "set-points", "figures")), phases
    import gc

    assert gc.isenabled()
    assert main(["plan", "--out", str(tmp_path / "bad"), "--mu", "-1"]) == 2
    assert gc.isenabled()


# ------------------------------------------------------------------------------ options
@pytest.mark.parametrize(
    "argv",
    [
        ["--verbose", "--debug", "--threads", "2", "view", "RUN"],
        ["view", "RUN", "--verbose", "--debug", "--threads", "2"],
        ["--verbose", "view", "--threads", "2", "RUN", "--debug"],
    ],
)
def test_global_options_are_taken_before_and_after_the_command(argv):
    args = build_parser().parse_args(argv)
    assert (args.verbose, args.debug, args.threads, args.run_dir) == (True, True, 2, "RUN")


def test_global_options_not_repeated_after_the_command_keep_their_value():
    args = build_parser().parse_args(["--threads", "3", "--debug", "plan"])
    assert (args.threads, args.debug, args.verbose) == (3, True, False)
    args = build_parser().parse_args(["plan"])
    assert (args.threads, args.debug, args.verbose) == (None, False, False)


@pytest.mark.parametrize("value", ["0", "-2", "two", "1.5"])
def test_a_bad_thread_count_is_one_line_exit_2(capsys, value):
    assert main(["plan", "--threads", value, "--out", "never"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("softgrasp: error:") and "--threads" in err
    assert not Path("never").exists()


def test_threads_sets_the_solvers_thread_count(coarse_run, tmp_path, monkeypatch, capsys):
    from softgrasp.linalg import threads

    monkeypatch.delenv(threads.THREADS_ENV, raising=False)
    try:
        assert main(["view", str(coarse_run[0]), "--out", str(tmp_path / "v.html"), "--threads", "1"]) == 0
        assert threads.fixed_threads() == 1 and threads.choose_threads() == 1
        assert os.environ[threads.THREADS_ENV] == "1"  # and in the worker processes started
    finally:
        threads.set_threads(None)
        os.environ.pop(threads.THREADS_ENV, None)


def test_view_takes_the_run_folder_or_its_plan_json(coarse_run, tmp_path, capsys):
    run = coarse_run[0]
    a, b = tmp_path / "a.html", tmp_path / "b.html"
    assert main(["view", str(run), "--out", str(a)]) == 0
    assert main(["view", str(run / "plan.json"), "--out", str(b)]) == 0
    assert a.read_bytes() == b.read_bytes()


def test_execute_takes_the_run_folder_or_its_plan_json(tmp_path, capsys):
    """A folder is read as its plan.json: the same refusal names that file."""
    (tmp_path / "plan.json").write_text("{not json")
    for given in (tmp_path, tmp_path / "plan.json"):
        assert main(["execute", str(given), "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(tmp_path / "plan.json") in err, err


# ------------------------------------------------------------------------------ exit statuses
@pytest.mark.parametrize(
    ("error", "status"),
    [
        (InfeasibleGrasp("no grasp"), 1),
        (NotConverged("no equilibrium"), 1),
        (SimulationUnstable("blew up"), 1),
        (ConfigError("bad option"), 2),
        (MeshError("bad mesh"), 2),
        (MaterialError("bad material"), 2),
        (ContactError("bad contact"), 2),
        (RuntimeError("a bug"), 3),
    ],
)
def test_each_error_has_its_exit_status(coarse_run, tmp_path, monkeypatch, capsys, error, status):
    import softgrasp.viz.view as view

    def fail(*_a, **_k):
        raise error

    monkeypatch.setattr(view, "write_view", fail)
    assert main(["view", str(coarse_run[0]), "--out", str(tmp_path / "v.html")]) == status
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(error) in err
    assert err.startswith("softgrasp: internal error:" if status == 3 else "softgrasp: error:")
    if isinstance(error, Exception) and status != 3:
        assert exit_status(error) == status


def test_an_argument_error_exits_2(capsys):
    assert main(["plan", "--no-such-option"]) == 2
    assert main(["no-such-command"]) == 2


def test_the_exit_statuses_are_in_the_help_and_the_docs(capsys):
    assert main(["--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "exit status:" in text
    for code in (0, 1, 2, 3):
        assert f" {code} " in text
    assert "bad input" in text and "internal error" in text and "no grasp holds the object" in text
    root = Path(__file__).resolve().parents[1]
    for doc in (root / "README.md", root / "docs" / "guide.md"):
        words = " ".join(doc.read_text(encoding="utf-8").split())
        assert "Exit status" in words or "exit status" in words, doc
        for code in EXIT_CODES:
            assert f"| {code} |" in words, (doc, code)


# ------------------------------------------------------------------------------ help
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_each_command_has_a_description_and_an_example_that_parses(capsys, command):
    assert main([command, "--help"]) == 0
    out = capsys.readouterr().out
    line, example = COMMANDS[command]
    assert " ".join(line.split()[:4]) in " ".join(out.split())
    assert f"example:\n  {example}" in out and "exit status:" in out
    argv = shlex.split(example)
    assert argv[:2] == ["softgrasp", command]
    args = build_parser().parse_args(argv[1:])  # the example is a valid command line
    assert args.command == command


@pytest.mark.parametrize("module", ["softgrasp", "softgrasp.cli"])
def test_python_dash_m_runs_the_command_line(module):
    proc = subprocess.run(
        [sys.executable, "-m", module, "--help"], env=ENV, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: softgrasp") and "exit status:" in proc.stdout
    bad = subprocess.run(
        [sys.executable, "-m", module, "plan", "--mu", "x"],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and bad.stderr.startswith("softgrasp: error:")


# ------------------------------------------------------------------------------ extras
@pytest.mark.parametrize(
    ("missing", "argv", "extra"),
    [
        ("pyarrow", ["sweep", "{d}/s.toml"], "sweep"),
        ("dask.distributed", ["sweep", "{d}/s.toml"], "sweep"),
        ("dask.distributed", ["plan", "--uncertain", "mu=0.4..0.8"], "sweep"),
        ("mujoco", ["execute", "{d}/plan.json"], "execute"),
        ("mujoco", ["sweep", "{d}/x.toml"], "execute"),
    ],
)
def test_a_missing_extra_is_named_with_its_install_command(
    tmp_path, monkeypatch, capsys, missing, argv, extra
):
    (tmp_path / "s.toml").write_text('[base]\nobject = "sphere"\n[grid]\nmu = [0.5]\n')
    executing = '[sweep]\nexecute = true\n[base]\nobject = "sphere"\n[grid]\nmu = [0.5]\n'
    (tmp_path / "x.toml").write_text(executing)
    monkeypatch.setitem(sys.modules, missing, None)  # its import now fails as if not installed
    out = tmp_path / "out"
    assert main([a.replace("{d}", str(tmp_path)) for a in argv] + ["--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert f"pip install 'softgrasp[{extra}]'" in err and missing.split(".")[0] in err, err
    assert not out.exists()


def test_the_core_install_leaves_the_extras_out():
    """pyproject: Dask and PyArrow only in the 'sweep' extra, MuJoCo only in 'execute'; the test
    extra and the Makefile install all the tests need."""
    import tomllib

    root = Path(__file__).resolve().parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    core = " ".join(project["dependencies"])
    extras = project["optional-dependencies"]
    for name in ("dask", "distributed", "pyarrow", "mujoco"):
        assert name not in core, name
    assert any(d.startswith("dask[distributed]") for d in extras["sweep"])
    assert any(d.startswith("pyarrow") for d in extras["sweep"])
    assert any(d.startswith("mujoco") for d in extras["execute"])
    makefile = (root / "Makefile").read_text()
    assert '".[execute,sweep]"' in makefile and '".[test,execute,sweep]"' in makefile


# ------------------------------------------------------------------------------ the wheel
@pytest.mark.slow
def test_the_wheel_installs_into_a_fresh_venv_and_plans(tmp_path):
    """Build the wheel, install it with its dependencies into a new virtual environment (no
    site-packages of this one), and run ``softgrasp plan`` from there: the packaged hand and the
    view's static files come with it."""
    root = Path(__file__).resolve().parents[1]
    # Nothing of this checkout or this environment on the new one's path (pip would take the
    # checkout's softgrasp.egg-info on PYTHONPATH for an installed softgrasp).
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NUMBA_CACHE_DIR")}
    dist = tmp_path / "dist"
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(root)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert build.returncode == 0, build.stderr[-3000:]
    (wheel,) = dist.glob("softgrasp-*.whl")
    import zipfile

    names = zipfile.ZipFile(wheel).namelist()
    assert "softgrasp/hand/shadow_like.urdf" in names and "softgrasp/py.typed" in names
    assert any(n.startswith("softgrasp/viz/static/") for n in names), names
    venv = tmp_path / "venv"
    # A venv without pip of its own (no ensurepip run): this environment's pip installs into it
    # (``--python``), and skips byte-compiling the dependencies, which Python does on import.
    subprocess.run(
        [sys.executable, "-m", "venv", "--without-pip", str(venv)], env=env, check=True, timeout=300
    )
    py = venv / "bin" / "python"
    install = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-compile", str(wheel)],
        env=env,
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert install.returncode == 0, install.stderr[-3000:]
    out = tmp_path / "run"
    plan = subprocess.run(
        [str(venv / "bin" / "softgrasp"), *COARSE, "--out", str(out)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=1200,
    )
    assert plan.returncode == 0, plan.stderr[-3000:]
    assert "compiling kernels (first run only" in plan.stderr  # its own, empty cache
    # the fingertip contact's kernels compile in the warm-up's second process and load here
    # (compiled here as well, the warm-up would name them: another argument type, for one)
    assert "compiling kernels: body forces" in plan.stderr
    assert "compiling kernels: fingertip contact" not in plan.stderr, plan.stderr
    doc = json.loads((out / "plan.json").read_text())
    assert doc["equilibrium"]["satisfied"] is True
    where = subprocess.run(
        [str(py), "-c", "import softgrasp; print(softgrasp.__file__)"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert where.stdout.strip().startswith(str(venv)), where.stdout  # the installed copy ran


def test_the_set_points_are_printed_before_the_files_are_written(tmp_path, monkeypatch, capsys):
    """``plan`` prints its table of set-points as soon as the planner returns, before it writes
    the files, figures and view data (which take longer than the answer)."""
    from softgrasp.api.planning import Plan

    printed_first: list[bool] = []
    save = Plan.save

    def save_after_looking(self, *args, **kwargs):
        printed_first.append("set-point N" in capsys.readouterr().out)
        return save(self, *args, **kwargs)

    monkeypatch.setattr(Plan, "save", save_after_looking)
    assert main(["plan", "--out", str(tmp_path / "p")]) == 0
    assert printed_first == [True]
    assert (tmp_path / "p" / "plan.json").exists()
