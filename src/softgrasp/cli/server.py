"""``softgrasp server``: start, list and stop softgrasp's warm servers (:mod:`softgrasp.cli.launch`)."""

from __future__ import annotations

import argparse
import sys
import time

__all__ = ["START_SEEN_S", "START_WAIT_S", "add_parser", "run"]

#: Longest wait [s] of ``softgrasp server start`` for the new server to serve.
START_WAIT_S = 120.0
#: Longest wait [s] for the new server's process to take its socket.
START_SEEN_S = 15.0


def add_parser(sub) -> None:
    sv = sub.add_parser(
        "server",
        help="start, list or stop the warm server a plan runs in (modules and kernels loaded once)",
    )
    sv.add_argument(
        "action",
        choices=("start", "status", "stop"),
        help="start: start this program's server (once its kernels are compiled) and wait until it "
        "serves; status: list this user's servers; stop: stop this program's server (its running "
        "commands end first)",
    )
    sv.add_argument("--all", action="store_true", help="stop: every server of this user")
    sv.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from softgrasp.cli import launch, serverlock
    from softgrasp.cli.status import NOT_DONE
    from softgrasp.errors import ConfigError

    path = launch.socket_path()
    if path is None:
        raise ConfigError(
            "softgrasp's server needs a private socket folder ($XDG_RUNTIME_DIR or the temporary "
            "folder, mode 700): commands run in their own process"
        )
    if args.all and args.action != "stop":
        raise ConfigError("--all applies to 'softgrasp server stop'")
    servers = serverlock.running(path.parent)
    mine = [s for s in servers if s.socket == path]
    if args.action == "status":
        if not servers:
            print("no softgrasp server is running")
        for s in servers:
            state = "serving" if s.ready else "starting"
            whose = "this program's" if s.socket == path else "another program's or environment's"
            print(f"pid {s.pid}: {state}, {whose} ({s.socket})")
        return 0
    if args.action == "stop":
        stopped = servers if args.all else mine
        for s in stopped:
            serverlock.stop(s)
        print(f"stopped {len(stopped)} server{'s' if len(stopped) != 1 else ''}")
        return 0
    from softgrasp.cli.warm import cold

    if cold():
        raise ConfigError("the kernels are not compiled yet: run a plan first (it compiles them), then start")
    if not mine:
        launch.start_server(path)
    start, seen = time.monotonic(), False
    while time.monotonic() - start < START_WAIT_S:
        mine = [s for s in serverlock.running(path.parent) if s.socket == path]
        if mine and mine[0].ready:
            print(f"serving: pid {mine[0].pid} ({path})")
            return 0
        if seen and not mine or not seen and time.monotonic() - start > START_SEEN_S:
            break  # it ended (it serves only where Numba's threads survive a fork), or never began
        seen = seen or bool(mine)
        time.sleep(0.1)
    print(
        "softgrasp: error: the server did not start serving; commands run in their own process "
        "as with --no-server",
        file=sys.stderr,
    )
    return NOT_DONE
