"""softgrasp's warm server: modules imported and kernels loaded once, a forked child per command.

``python -m softgrasp.cli.zygote SOCKET`` (started by :func:`softgrasp.cli.launch.start_server`):

1. takes ``SOCKET.lock`` (a second server for the same socket exits at once), listens on
   ``SOCKET`` (commands sent meanwhile wait), imports the command line's modules and what a plan
   imports (:data:`PRELOAD`), and loads the compiled kernels by the warm-up's tiny solve
   (:func:`softgrasp.cli.warm.warm_up`, on this main thread: Numba's TBB threads then reset
   themselves in each forked child). It serves nothing and exits when the kernels are not
   compiled (it would compile them while a command waited) or when Numba's threads would not
   survive a fork (GNU OpenMP's layer: :mod:`softgrasp.backend`);
2. for each command (a length-prefixed JSON document with the client's arguments, working
   directory, environment, CPU affinity, file-creation mask, priority and ignored signals, its
   stdin, stdout and stderr passed with it) forks a child, sends the client the child's process
   id and then lets the child go. The child takes all of these (a priority above the server's
   only where allowed), gives again the warnings the server gave, and runs the command line
   (:func:`softgrasp.cli.main`) as a fresh ``softgrasp`` process would; it ends as the
   interpreter ends one (its threads joined, its ``atexit`` functions run, its streams flushed)
   without freeing the server's objects one by one. Resource limits are the server's;
3. reports each child's exit status to its client (``128 + N`` for a child ended by signal N).
   A client that goes away first has its child interrupted (``SIGINT``: its run folder left as it
   was), and killed :data:`KILL_AFTER_S` later if it still runs;
4. exits after :data:`IDLE_S` without a command, when its socket is removed or replaced, or when
   softgrasp's sources or the installed packages change (:func:`softgrasp.cli.launch.server_key`
   no longer names its socket); it first stops listening and lets running children end.

The results do not depend on it: a child computes with the same modules, kernels and inputs as a
fresh process (``tests/test_zygote.py`` compares the files of both, byte for byte).
"""

from __future__ import annotations

import json
import os
import selectors
import signal
import socket
import struct
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from softgrasp.cli.launch import IDLE_MINUTES, server_key
from softgrasp.cli.serverlock import take_lock, write_state

__all__ = ["IDLE_S", "KILL_AFTER_S", "PRELOAD", "Command", "main", "serve"]

#: A server without a command for this long exits [s].
IDLE_S = 60.0 * IDLE_MINUTES
#: How often the server checks its socket and sources [s].
CHECK_S = 2.0
#: A child whose client went away is killed this long after its interrupt [s].
KILL_AFTER_S = 10.0
#: Modules a plan imports when it needs them, imported by the server beforehand (each only if
#: it imports).
PRELOAD = (
    "softgrasp.cli.main",
    "softgrasp.api.planning",
    "softgrasp.grasp.planner",
    "softgrasp.grasp.kept_rest",
    "softgrasp.model.objects",
    "softgrasp.viz.worker",
    "softgrasp.io.options",
    "softgrasp.io.runfolder",
    "softgrasp.io.paraview",
    "softgrasp.io.plan_document",
    "softgrasp.io.planfile",
    "softgrasp.io.portable",
    "softgrasp.execution.controller",
    "scipy.optimize",
    "scipy.spatial",
    "meshio",
    "tqdm",
)


@dataclass
class Command:
    """A client's command, in the child that runs it."""

    argv: list[str]
    cwd: str
    env: dict[str, str]
    affinity: list[int] | None
    fds: list[int]
    umask: int = 0o022
    nice: int = 0
    ignored: tuple[int, ...] = ()

    def run(self) -> int:
        """Take the client's terminal, folder, environment, affinity, file-creation mask,
        priority (where it is not above the server's) and ignored signals; run the command line."""
        import warnings

        for target, fd in enumerate(self.fds):
            os.dup2(fd, target)
            os.close(fd)
        os.environ.clear()
        os.environ.update(self.env)
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGCHLD):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for sig in self.ignored:
            signal.signal(sig, signal.SIG_IGN)
        signal.set_wakeup_fd(-1)
        os.umask(self.umask)
        from softgrasp.io import atomic

        atomic.read_umask()
        try:
            os.setpriority(os.PRIO_PROCESS, 0, self.nice)
        except OSError:  # a higher priority than the server's needs privileges
            pass
        if self.affinity and hasattr(os, "sched_setaffinity"):
            try:
                os.sched_setaffinity(0, self.affinity)
            except OSError:
                pass
        filters = warnings.filters[:]  # a warning the server gave (to nothing) is given again
        warnings.simplefilter("default")
        warnings.filters[:] = filters
        _standard_streams()
        if "numpy.random" in sys.modules:
            sys.modules["numpy.random"].seed()  # as unpredictable as a fresh process's
        sys.argv = ["softgrasp", *self.argv]
        try:
            os.chdir(self.cwd)
        except OSError as exc:
            print(f"softgrasp: error: cannot enter the working folder {self.cwd}: {exc}", file=sys.stderr)
            return 2
        from softgrasp.cli.main import main

        return main()


def _standard_streams() -> None:
    """``sys.stdin``, ``sys.stdout`` and ``sys.stderr`` on the client's descriptors, buffered as
    the interpreter buffers them at start (stdout by line on a terminal, stderr by line always)."""
    import io

    def stream(fd: int, mode: str, like, line: bool):
        raw = io.FileIO(fd, mode, closefd=False)
        buffered = io.BufferedReader(raw) if mode == "r" else io.BufferedWriter(raw)
        return io.TextIOWrapper(buffered, encoding=like.encoding, errors=like.errors, line_buffering=line)

    sys.stdin = sys.__stdin__ = stream(0, "r", sys.__stdin__, False)
    sys.stdout = sys.__stdout__ = stream(1, "w", sys.__stdout__, os.isatty(1))
    sys.stderr = sys.__stderr__ = stream(2, "w", sys.__stderr__, True)


def _warm() -> bool:
    """Import what a command uses and load the kernels; whether this process may serve."""
    import gc
    import importlib

    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except ImportError:
            pass
    from softgrasp import backend
    from softgrasp.cli import warm

    warm._import_modules()
    if warm.cold():
        return False
    warm.warm_up()
    if backend.forks_lose_threads():
        return False
    gc.collect()
    gc.freeze()
    return True


def serve(path: Path) -> Command | None:
    """Serve commands at ``path`` (module docstring). Returns None in the server when it ends,
    and the command in each forked child, which runs it after this returns."""
    server = os.getpid()
    inode: int | None = None  # the socket's, once bound
    # stopped while it loads: it ends at once, its socket removed. Raising an exception instead
    # could land inside the import of an extension module, which then cannot be imported again
    signal.signal(signal.SIGTERM, lambda *_: _terminate(path, inode))
    lock = take_lock(Path(f"{path}.lock"))
    if lock is None:
        return None  # another server for this socket
    with lock:
        write_state(lock, f"{server} starting")
        try:
            path.unlink()
        except FileNotFoundError:
            pass
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            # SIGTERM waits while the socket is bound and its inode read: the handler then
            # removes it (between the two it would leave the socket behind)
            mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
            try:
                listener.bind(str(path))
                inode = os.stat(path).st_ino
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, mask)
            listener.listen(64)
            if not _warm():
                return None
            write_state(lock, f"{server} ready")
            return _Loop(listener, path, inode).run()
        finally:
            listener.close()
            if os.getpid() == server:
                _remove(path, inode)


def _terminate(path: Path, inode: int | None) -> None:
    """End a server that has served nothing yet: its socket removed (if it is still this
    server's, bound with ``inode``) and its process ended with status 0. Its lock is released
    with the process."""
    _remove(path, inode)
    os._exit(0)


def _remove(path: Path, inode: int | None) -> None:
    """Remove the socket at ``path`` if it is still this server's."""
    try:
        if inode is not None and os.stat(path).st_ino == inode:
            path.unlink()
    except OSError:
        pass


@dataclass
class _Child:
    conn: socket.socket
    interrupted_at: float | None = None


class _Loop:
    """The server's event loop: new commands, clients gone, children ended, idle and stale."""

    def __init__(self, listener: socket.socket, path: Path, inode: int) -> None:
        self.listener, self.path, self.inode = listener, path, inode
        self.children: dict[int, _Child] = {}
        self.last = time.monotonic()
        self.listening = True
        self.stopping = False
        self.sel = selectors.DefaultSelector()
        self.wake_r, self.wake_w = socket.socketpair()
        self.wake_r.setblocking(False)
        self.wake_w.setblocking(False)

    def run(self) -> Command | None:
        signal.signal(signal.SIGCHLD, lambda *_: None)  # wakes the selector by the wakeup socket
        signal.signal(signal.SIGTERM, self._stop)
        signal.set_wakeup_fd(self.wake_w.fileno())
        self.sel.register(self.listener, selectors.EVENT_READ, None)
        self.sel.register(self.wake_r, selectors.EVENT_READ, 0)
        try:
            while self.listening or self.children:
                for key, _ in self.sel.select(timeout=1.0 if self.children else CHECK_S):
                    if key.data is None:
                        command = self._accept()
                        if command is not None:
                            return command  # in the child
                    elif key.data == 0:
                        self._drain()
                    else:
                        self._client_gone(key.data)
                self._reap()
                self._check()
            return None
        finally:
            self.sel.close()
            self.wake_r.close()
            self.wake_w.close()
            for child in self.children.values():
                child.conn.close()

    def _stop(self, _signum: int, _frame: object) -> None:
        """``SIGTERM`` (``softgrasp server stop``): stop listening; the running commands end."""
        self.stopping = True

    def _drain(self) -> None:
        try:
            while self.wake_r.recv(512):
                pass
        except BlockingIOError:
            pass

    def _accept(self) -> Command | None:
        try:
            conn, _ = self.listener.accept()
        except OSError:
            return None
        try:
            command = _read(conn)
        except (OSError, ValueError, KeyError):
            conn.close()
            return None
        go_r, go_w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: wait for the server's word that the client knows it
            os.close(go_w)
            signal.set_wakeup_fd(-1)
            conn.close()
            go = os.read(go_r, 1)
            os.close(go_r)
            if not go:
                os._exit(0)
            self.listening = False
            return command
        os.close(go_r)
        for fd in command.fds:
            os.close(fd)
        try:
            conn.sendall(f"pid {pid}\n".encode())
            os.write(go_w, b"g")
        except OSError:
            conn.close()  # the client is gone: the child exits without running anything
            os.close(go_w)
            os.waitpid(pid, 0)
            return None
        os.close(go_w)
        self.children[pid] = _Child(conn)
        self.sel.register(conn, selectors.EVENT_READ, pid)
        return None

    def _client_gone(self, pid: int) -> None:
        child = self.children.get(pid)
        if child is None:
            return
        try:
            data = child.conn.recv(64)
        except OSError:
            data = b""
        if not data and child.interrupted_at is None:
            self.sel.unregister(child.conn)
            child.interrupted_at = time.monotonic()
            _signal(pid, signal.SIGINT)

    def _reap(self) -> None:
        while self.children:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                return
            if pid == 0:
                return
            child = self.children.pop(pid, None)
            if child is None:
                continue
            code = os.waitstatus_to_exitcode(status)
            try:
                child.conn.sendall(f"exit {code if code >= 0 else 128 - code}\n".encode())
            except OSError:
                pass
            if child.interrupted_at is None:
                self.sel.unregister(child.conn)
            child.conn.close()
            self.last = time.monotonic()

    def _check(self) -> None:
        now = time.monotonic()
        for pid, child in self.children.items():
            if child.interrupted_at is not None and now - child.interrupted_at > KILL_AFTER_S:
                _signal(pid, signal.SIGKILL)
        if not self.listening:
            return
        stale = self.stopping or (now - self.last > IDLE_S and not self.children)
        try:
            stale = stale or os.stat(self.path).st_ino != self.inode
        except OSError:
            stale = True
        if not stale and now - getattr(self, "_checked", 0.0) > CHECK_S:
            self._checked = now
            stale = server_key() != self.path.stem
        if stale:  # new commands find no server (and start another); the running ones end
            self.listening = False
            self.sel.unregister(self.listener)
            self.listener.close()
            _remove(self.path, self.inode)


def _signal(pid: int, sig: int) -> None:
    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        pass


def _read(conn: socket.socket) -> Command:
    """A client's command (:func:`softgrasp.cli.launch._request`), after checking that the client
    is this user."""
    creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    if struct.unpack("3i", creds)[1] != os.getuid():
        raise ValueError("another user's client")
    conn.settimeout(5.0)
    first, fds, _, _ = socket.recv_fds(conn, 1, 3)
    if len(fds) != 3 or len(first) != 1:
        for fd in fds:
            os.close(fd)
        raise ValueError("a client without its terminal")
    try:
        head = first + _exactly(conn, 3)
        doc = json.loads(_exactly(conn, struct.unpack("!I", head)[0]).decode("utf-8", "surrogateescape"))
    except (OSError, ValueError):
        for fd in fds:
            os.close(fd)
        raise
    return Command(
        argv=[str(a) for a in doc["argv"]],
        cwd=str(doc["cwd"]),
        env={str(k): str(v) for k, v in doc["env"].items()},
        affinity=doc.get("affinity"),
        fds=list(fds),
        umask=int(doc.get("umask", 0o022)),
        nice=int(doc.get("nice", 0)),
        ignored=tuple(int(sig) for sig in doc.get("ignored", ())),
    )


def _exactly(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        part = conn.recv(n - len(data))
        if not part:
            raise ValueError("the client went away")
        data += part
    return data


def main(argv: list[str] | None = None) -> int:
    """Serve at the socket named in ``argv`` (default: the process's arguments); in a forked
    child, run its command and exit with its status."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m softgrasp.cli.zygote SOCKET", file=sys.stderr)
        return 2
    path = Path(args[0]).absolute()
    os.chdir("/")  # holds no folder of the client's; each child enters its client's
    command = serve(path)
    if command is None:
        return 0
    _exit(command.run())


def _exit(status: int) -> None:
    """End a child as the interpreter ends a process (its threads joined, its ``atexit``
    functions run, its streams flushed), without freeing the server's objects one by one."""
    import atexit
    import threading

    for thread in threading.enumerate():
        if thread is not threading.current_thread() and not thread.daemon:
            thread.join()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(status)


if __name__ == "__main__":
    raise SystemExit(main())
