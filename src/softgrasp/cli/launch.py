"""The ``softgrasp`` program: a ``plan`` runs in a child of softgrasp's warm server when one is up.

A fresh Python process pays about 0.5 s to import NumPy, SciPy and Numba and about 0.3 s to load
softgrasp's compiled kernels before a plan can start; on the default object that is more than the
plan itself. The warm server (:mod:`softgrasp.cli.zygote`) has done both once: for each command it
forks a child, which takes this program's terminal (its stdin, stdout and stderr, passed over a
Unix socket), working directory, environment, CPU affinity and arguments, and runs the command
line (:func:`softgrasp.cli.main`) exactly as this process would have. This process waits for the
child, passes it every Ctrl-C, ``SIGTERM`` and ``SIGHUP``, stops and continues it with itself
(Ctrl-Z, ``fg``), and exits with its status.

A server serves only the program it was started by: its socket's name is keyed by the Python
executable, softgrasp's sources (their sizes and times), the installed packages' folders and the
environment (:func:`server_key`), so an edit, an upgrade or another environment finds no server
and starts its own. When there is none, the command runs in this process, as before, and a served
command that ended normally then starts one in the background for the next
(:func:`start_server`, saying so); it exits after :data:`IDLE_MINUTES` without a command.
``--no-server`` runs a command here; ``softgrasp server`` starts, lists and stops servers.
Linux only (Unix sockets passing file descriptors, ``fork``); elsewhere every command runs here.

This module imports only the standard library (its cost is part of every command's start).
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import struct
import sys
from pathlib import Path

__all__ = ["SERVED", "connect", "entry", "server_key", "socket_folder", "socket_path", "start_server"]

#: The environment this program started with (a command's imports add to ``os.environ``).
ENVIRON = dict(os.environ)
#: The commands a warm server runs.
SERVED = frozenset({"plan"})
#: Environment variables that do not key a server: a child takes the client's whole
#: environment, and these are read when a command runs, not when the server imports its modules.
UNKEYED_ENV = frozenset(
    {"PWD", "OLDPWD", "SHLVL", "_", "COLUMNS", "LINES", "TERM", "XDG_CACHE_HOME", "PYTEST_CURRENT_TEST"}
)
#: Longest wait [s] for a server to take a command (it may still be importing and loading its
#: kernels, about a second) before the command runs in this process instead.
TAKE_WAIT_S = 30.0
#: A server exits after this many minutes without a command (:data:`softgrasp.cli.zygote.IDLE_S`).
IDLE_MINUTES = 15
#: Global options that take a value (skipped when finding the command in the arguments).
_VALUED = frozenset({"--threads"})


def entry() -> int:
    """The ``softgrasp`` program (and ``python -m softgrasp``): run the command in a warm server's
    child when one is up, else in this process; its exit status."""
    argv = sys.argv[1:]
    served = _served(argv)
    path = socket_path() if served else None
    if path is not None:
        status = _run_served(path, argv)
        if status is not None:
            return status
    from softgrasp.cli.main import main

    status = main()
    if path is not None and status == 0 and _forkable() and start_server(path):
        print(
            "softgrasp: a warm server starts for the next plans (it stops after "
            f"{IDLE_MINUTES} min unused; 'softgrasp server stop' stops it now)",
            file=sys.stderr,
        )
    return status


def _forkable() -> bool:
    """Whether this process's Numba threads would survive a fork (a server's children would
    otherwise run the serial kernels: :mod:`softgrasp.backend`)."""
    from softgrasp import backend

    return not backend.forks_lose_threads()


def _served(argv: list[str]) -> bool:
    """Whether ``argv`` names a served command without ``--no-server``, in a process whose
    interpreter options a server started plainly would share."""
    if "--no-server" in argv or sys._xoptions or sys.warnoptions:
        return False
    flags = sys.flags
    if flags.optimize or flags.isolated or flags.ignore_environment or flags.dev_mode:
        return False
    if not sys.platform.startswith("linux") or not hasattr(socket, "send_fds"):
        return False
    it = iter(argv)
    for token in it:
        if token in _VALUED:
            next(it, None)
        elif token in ("-h", "--help", "--version"):
            return False
        elif not token.startswith("-"):
            return token in SERVED
    return False


def server_key(environ: dict[str, str] | None = None) -> str:
    """What a server must share with this program, hashed: the Python executable and version,
    softgrasp's source files (names, sizes, modification times), the folders of the installed
    packages (their times change when a package is installed or removed) and the environment
    but :data:`UNKEYED_ENV` (default: :data:`ENVIRON`)."""
    env = ENVIRON if environ is None else environ
    h = hashlib.sha256()
    h.update(json.dumps([os.path.realpath(sys.executable), sys.version, sys.prefix]).encode())
    root = Path(__file__).resolve().parent.parent
    for folder, dirs, files in os.walk(root):
        dirs.sort()
        for name in sorted(files):
            if name.endswith(".py"):
                st = os.stat(os.path.join(folder, name))
                h.update(f"{folder}/{name}\0{st.st_size}\0{st.st_mtime_ns}\0".encode())
    for entry_ in sys.path:
        if entry_.endswith("-packages") and os.path.isdir(entry_):
            h.update(f"{entry_}\0{os.stat(entry_).st_mtime_ns}\0".encode())
    h.update(json.dumps(sorted((k, v) for k, v in env.items() if k not in UNKEYED_ENV)).encode())
    return h.hexdigest()[:24]


def socket_folder() -> Path | None:
    """This user's folder of server sockets (``$XDG_RUNTIME_DIR/softgrasp``, else
    ``softgrasp-UID`` in the temporary folder), made private (mode 700) if new; None when it
    cannot be made or is not this user's alone."""
    import tempfile

    runtime = ENVIRON.get("XDG_RUNTIME_DIR")
    base = Path(runtime) / "softgrasp" if runtime and os.path.isdir(runtime) else None
    folder = base or Path(tempfile.gettempdir()) / f"softgrasp-{os.getuid()}"
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        st = folder.lstat()
    except OSError:
        return None
    import stat

    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
        return None
    return folder


def socket_path() -> Path | None:
    """The socket of the server this program would use (:func:`server_key`), or None where none
    may run."""
    folder = socket_folder()
    return None if folder is None else folder / f"{server_key()}.sock"


def connect(path: Path) -> socket.socket | None:
    """A connection to the server listening at ``path``, or None when none listens there."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.connect(str(path))
    except OSError:
        s.close()
        return None
    return s


def start_server(path: Path | None = None) -> bool:
    """Start a server for this program at ``path`` (default :func:`socket_path`) in the
    background, in the environment this program started with, detached from its terminal, with
    no working folder on its ``sys.path`` (``-P``: a child imports what the ``softgrasp`` program
    imports wherever its client runs) (:mod:`softgrasp.cli.zygote`; a second one for the same
    socket exits at once). Whether it was started."""
    import subprocess

    path = socket_path() if path is None else path
    if path is None:
        return False
    try:
        subprocess.Popen(
            [sys.executable, "-P", "-m", "softgrasp.cli.zygote", str(path)],  # no folder on sys.path
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
            close_fds=True,
            env=ENVIRON,
        )
    except OSError:
        return False
    return True


def _request(argv: list[str]) -> bytes:
    """The command as the server reads it, a length-prefixed JSON document: the arguments, the
    working folder, the environment, the CPU affinity, the file-creation mask, the scheduling
    priority and the signals this process ignores."""
    affinity = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    umask = os.umask(0o022)
    os.umask(umask)
    ignored = [int(sig) for sig in _Relay.SIGNALS if signal.getsignal(sig) is signal.SIG_IGN]
    body = json.dumps(
        {
            "argv": argv,
            "cwd": os.getcwd(),
            "env": ENVIRON,
            "affinity": affinity,
            "umask": umask,
            "nice": os.getpriority(os.PRIO_PROCESS, 0),
            "ignored": ignored,
        }
    )
    data = body.encode("utf-8", "surrogateescape")
    return struct.pack("!I", len(data)) + data


def _run_served(path: Path, argv: list[str]) -> int | None:
    """Run the command in a child of the server at ``path``; its exit status, or None when no
    server took it (then nothing ran, and it runs here)."""
    conn = connect(path)
    if conn is None:
        return None
    relay = _Relay()
    with conn, relay:
        try:
            data = _request(argv)
            conn.sendmsg([data[:1]], [(socket.SOL_SOCKET, socket.SCM_RIGHTS, struct.pack("3i", 0, 1, 2))])
            conn.sendall(data[1:])
            conn.settimeout(TAKE_WAIT_S)
            reader = conn.makefile("rb")
            line = _line(reader)
        except (OSError, ValueError):
            line = b""
        if not line.startswith(b"pid "):  # the server ended or waited too long: nothing ran
            return 130 if signal.SIGINT in relay.pending else None
        conn.settimeout(None)
        relay.attach(int(line.split()[1]))
        line = _line(reader)
        if line.startswith(b"exit "):
            return int(line.split()[1])
        relay.wait_gone()  # the server ended first: its child ran on, unwatched
    print("softgrasp: error: softgrasp's server ended while it ran this command", file=sys.stderr)
    return 3


def _line(reader) -> bytes:
    """One line from the server (a signal handled meanwhile does not end the wait)."""
    while True:
        try:
            return reader.readline()
        except InterruptedError:
            continue


class _Relay:
    """While a command runs in a server's child: every Ctrl-C, ``SIGTERM`` and ``SIGHUP`` passed
    on to the child (those before the child is known, once it is), Ctrl-Z stopping the child and
    then this process, ``fg`` continuing both. The handlers are this process's own again after."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

    def __init__(self) -> None:
        self.child: int | None = None
        self.pending: list[int] = []
        self._saved: dict[int, object] = {}

    def __enter__(self) -> _Relay:
        for sig in (*self.SIGNALS, signal.SIGTSTP, signal.SIGCONT):
            self._saved[sig] = signal.getsignal(sig)
        for sig in self.SIGNALS:
            if self._saved[sig] is not signal.SIG_IGN:  # an ignored one the child ignores too
                signal.signal(sig, self._forward)
        signal.signal(signal.SIGTSTP, self._stop)
        signal.signal(signal.SIGCONT, self._continue)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._saved.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]

    def attach(self, child: int) -> None:
        self.child = child
        for sig in self.pending:
            self._send(sig)

    def _send(self, sig: int) -> None:
        if self.child is None:
            return
        try:
            os.kill(self.child, sig)
        except ProcessLookupError:
            pass

    def _forward(self, signum: int, _frame: object) -> None:
        if self.child is None:
            self.pending.append(signum)
        self._send(signum)

    def _stop(self, _signum: int, _frame: object) -> None:
        self._send(signal.SIGSTOP)
        signal.signal(signal.SIGTSTP, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTSTP)

    def _continue(self, _signum: int, _frame: object) -> None:
        signal.signal(signal.SIGTSTP, self._stop)
        self._send(signal.SIGCONT)

    def wait_gone(self) -> None:
        """Wait until the child has ended."""
        import time

        while self.child is not None:
            try:
                os.kill(self.child, 0)
            except (ProcessLookupError, PermissionError):
                return
            time.sleep(0.05)
