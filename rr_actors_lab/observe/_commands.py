"""`rr-actors observe` and `rr-actors graph`: their arguments and what they run.

`rr_actors_lab._cli` lists them in its `COMMANDS` (with their help lines, so that
`rr-actors --help` imports no observer); their code lives here.

    rr-actors observe --state state/            # the page of a state directory's backups
    rr-actors observe --system lab --certs certs/ --name viewer \
        --members robot,operator,viewer --connect tls/10.0.0.1:7447
                                                # the page of every host of a system
    rr-actors graph --state state/ --format dot  # the dependency graph as text
"""

from __future__ import annotations

import argparse
import contextlib
import math
import threading
from typing import TYPE_CHECKING, TextIO

from rr_actors._extras import needs
from rr_actors.errors import ConfigError
from rr_actors_lab.observe._observer import observe_backups, observe_system, require_extra
from rr_actors_lab.observe._sources import backup_files, read_catalogs
from rr_actors_lab.observe._text import FORMATS, render
from rr_actors_lab.observe._view import dependency_graph

if TYPE_CHECKING:
    from rr_actors._transport.zenoh.net import ZenohNetwork

__all__ = [
    "graph_arguments",
    "observe_arguments",
    "run_graph",
    "run_observe",
]


def observe_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments of `rr-actors observe`."""
    parser.add_argument("--state", metavar="DIR", help="a supervisor's state_dir (its *.db files)")
    hosts = parser.add_argument_group(
        "across hosts (instead of --state): this process joins the system as a member and "
        "shows every host that shares its observer (sup.observe() on a ZenohNetwork)"
    )
    hosts.add_argument("--system", metavar="NAME", help="the system's name (ZenohNetwork system=)")
    hosts.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="a member host's router to dial, tls/ADDR:PORT (repeat)",
    )
    hosts.add_argument(
        "--certs",
        metavar="DIR",
        help="holds ca.pem, NAME.pem and NAME.key (rr-actors certs); without it, plain TCP",
    )
    hosts.add_argument("--name", metavar="NAME", help="this process's member name (with --certs)")
    hosts.add_argument(
        "--members",
        metavar="A,B,...",
        help="the system's member names, this one's included (with --certs); every host "
        "must name this one among its members too",
    )
    hosts.add_argument(
        "--lease", type=float, default=1.0, help="ZenohNetwork lease, seconds (default 1)"
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (127.0.0.1)")
    parser.add_argument("--port", type=int, default=0, help="port (default: a free one)")
    parser.add_argument(
        "--allow-remote",
        action="store_true",
        help="allow a --host other machines can reach (they see every catalog)",
    )
    parser.add_argument(
        "--for",
        dest="duration",
        type=_seconds,
        default=None,
        metavar="SECONDS",
        help="serve this long, then exit (default: until Ctrl-C)",
    )


def _seconds(text: str) -> float:
    """`--for`'s type: a positive number of seconds a wait can take (argparse names the flag)."""
    try:
        seconds = float(text)
    except ValueError:
        seconds = math.nan
    if not 0 < seconds <= threading.TIMEOUT_MAX:  # (nan too; inf, 1e400: past any wait)
        raise argparse.ArgumentTypeError(f"a positive number of seconds, not {text!r}")
    return seconds


def run_observe(
    args: argparse.Namespace, out: TextIO, *, stop: threading.Event | None = None
) -> int:
    """Serve the page until Ctrl-C, `--for` seconds, or `stop` is set; returns 0.

    Raises:
        ConfigError: see `observe_backups` (a missing directory, a port in use, ...) and
            `observe_system`; neither or both of `--state` and `--system`; `--certs`
            without `--name` and `--members`.
        CatalogCorruptError: a backup cannot be read.
    """
    stop = stop or threading.Event()
    if (args.state is None) == (args.system is None):
        raise ConfigError("give either --state DIR (backups) or --system NAME (across hosts)")
    with contextlib.ExitStack() as stack:
        if args.state is not None:
            _require_observe()
            observer = observe_backups(
                args.state, host=args.host, port=args.port, allow_remote=args.allow_remote
            )
            what = f"backups in {args.state}"
        else:
            network = _network(args)  # (zenoh first: --system says it needs it)
            stack.callback(network.close)
            _require_observe()
            observer = observe_system(
                network, host=args.host, port=args.port, allow_remote=args.allow_remote
            )
            what = f"every host of system {args.system}"
        stack.callback(observer.close)
        out.write(f"observer: {observer.url} ({what}; Ctrl-C stops)\n")
        out.flush()
        with contextlib.suppress(KeyboardInterrupt):
            stop.wait(args.duration)
    return 0


def _require_observe() -> None:
    """The observe extra, which the whole command needs: `rr-actors observe needs an extra:
    pip install ...` (`MissingExtraError` with no `what`, the command as its subject)."""
    with needs("observe", ""):
        require_extra()


def _network(args: argparse.Namespace) -> ZenohNetwork:
    """The `ZenohNetwork` of `rr-actors observe --system` (ConfigError naming the flag)."""
    with needs("zenoh", "--system"):
        from rr_actors._transport.zenoh.net import ZenohNetwork  # noqa: PLC0415 - an extra
        from rr_actors_lab.observe import _feed  # noqa: F401, PLC0415 - its event feed beside
    tls = None
    if args.certs is not None:
        if not args.name or not args.members:
            raise ConfigError("--certs needs --name (this member) and --members (all of them)")
        with needs("zenoh", "--certs"):
            from rr_actors._transport.zenoh.ops.tls import ZenohTLS  # noqa: PLC0415 - an extra

        directory = args.certs.rstrip("/")
        tls = ZenohTLS(
            ca=f"{directory}/ca.pem",
            cert=f"{directory}/{args.name}.pem",
            key=f"{directory}/{args.name}.key",
            members=[m.strip() for m in args.members.split(",") if m.strip()],
        )
    return ZenohNetwork(system=args.system, connect=args.connect, tls=tls, lease=args.lease)


def graph_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments of `rr-actors graph`."""
    parser.add_argument(
        "--state", required=True, metavar="DIR", help="a supervisor's state_dir (its *.db files)"
    )
    parser.add_argument(
        "--format", choices=FORMATS, default="mermaid", help="mermaid (default) or dot"
    )


def run_graph(args: argparse.Namespace, out: TextIO) -> int:
    """Print the graph; returns 0.

    Raises:
        ConfigError: the directory does not exist or holds no backup.
        CatalogCorruptError: a backup cannot be read.
    """
    catalogs = read_catalogs(backup_files(args.state))
    out.write(render(dependency_graph(catalogs), None, args.format))
    return 0
