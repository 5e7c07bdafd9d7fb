"""The lock file of a warm server (:mod:`softgrasp.cli.zygote`): one server per socket, its
process id and state written in it, and this user's running servers found by their held locks.

A server holds ``SOCKET.lock`` locked (``flock``, exclusive) for its whole life and writes
``PID starting`` into it, then ``PID ready`` once it serves. A lock file nobody holds is an ended
server's: :func:`running` removes it, under an exclusive lock of its own, so that a server
starting meanwhile locks a new file (:func:`take_lock` checks that the file it locked is still
the one named).
"""

from __future__ import annotations

import fcntl
import os
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Server", "running", "stop", "take_lock", "write_state"]


def take_lock(path: Path, tries: int = 50):
    """The lock file at ``path``, opened and locked for this server, or None when another server
    holds it. A lock held for a moment by :func:`running`, or a file it removed meanwhile, is
    tried again."""
    for _ in range(tries):
        lock = open(path, "a+")  # noqa: SIM115 - held for the server's life
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.close()
            time.sleep(0.02)
            continue
        try:
            same = os.fstat(lock.fileno()).st_ino == os.stat(path).st_ino
        except OSError:
            same = False
        if same:
            return lock
        lock.close()  # removed as an ended server's meanwhile: lock the new file
    return None


def write_state(lock, text: str) -> None:
    """Write the server's process id and state into its lock file (:func:`running`)."""
    lock.seek(0)
    lock.truncate()
    lock.write(text + "\n")
    lock.flush()


@dataclass(frozen=True)
class Server:
    """A running server: its socket, process id and whether it serves yet."""

    socket: Path
    pid: int
    ready: bool


def running(folder: Path | None = None) -> list[Server]:
    """This user's running servers (their lock files held), in ``folder`` (default
    :func:`softgrasp.cli.launch.socket_folder`). The socket and lock file of an ended server
    (one killed outright leaves its socket) are removed, under the lock."""
    from softgrasp.cli.launch import socket_folder

    folder = socket_folder() if folder is None else folder
    if folder is None:
        return []
    sockets = {p.with_suffix("") for p in folder.glob("*.sock.lock")} | set(folder.glob("*.sock"))
    found = []
    for sock in sorted(sockets):
        lock_path = Path(f"{sock}.lock")
        try:
            with open(lock_path, "a+") as lock:
                try:
                    fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:  # held: a server runs
                    lock.seek(0)
                    words = lock.read().split()
                    if len(words) == 2 and words[0].isdigit():
                        found.append(Server(sock, int(words[0]), words[1] == "ready"))
                    continue
                sock.unlink(missing_ok=True)  # an ended server's (removed while locked)
                lock_path.unlink(missing_ok=True)
        except OSError:
            continue
    return found


def stop(server: Server) -> None:
    """Ask ``server`` to stop (``SIGTERM``: it stops listening; its running commands end first)."""
    import signal

    try:
        os.kill(server.pid, signal.SIGTERM)
    except ProcessLookupError:
        pass
