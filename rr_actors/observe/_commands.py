"""`rr-actors observe` and `rr-actors graph`: their arguments and what they run.

`rr_actors._cli` lists them in its `COMMANDS`; their code lives here.

    rr-actors observe --state state/            # the page of a state directory's backups
    rr-actors graph --state state/ --format dot  # the dependency graph as text
"""

from __future__ import annotations

import argparse
import contextlib
import threading
from typing import TextIO

from rr_actors.observe._observer import observe_backups
from rr_actors.observe._sources import backup_files, read_catalogs
from rr_actors.observe._text import FORMATS, render
from rr_actors.observe._view import dependency_graph

__all__ = [
    "GRAPH_HELP",
    "OBSERVE_HELP",
    "graph_arguments",
    "observe_arguments",
    "run_graph",
    "run_observe",
]

OBSERVE_HELP = (
    "serve the observer's page for a state directory's backups (read-only, no live system; "
    "needs the observe extra)"
)
GRAPH_HELP = "print the dependency graph of a state directory's backups as Mermaid or DOT text"


def observe_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments of `rr-actors observe`."""
    parser.add_argument(
        "--state", required=True, metavar="DIR", help="a supervisor's state_dir (its *.db files)"
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
        type=float,
        default=None,
        metavar="SECONDS",
        help="serve this long, then exit (default: until Ctrl-C)",
    )


def run_observe(
    args: argparse.Namespace, out: TextIO, *, stop: threading.Event | None = None
) -> int:
    """Serve the page until Ctrl-C, `--for` seconds, or `stop` is set; returns 0.

    Raises:
        ConfigError: see `observe_backups` (a missing directory, a port in use, ...).
        CatalogCorruptError: a backup cannot be read.
    """
    stop = stop or threading.Event()
    observer = observe_backups(
        args.state, host=args.host, port=args.port, allow_remote=args.allow_remote
    )
    try:
        out.write(f"observer: {observer.url} (backups in {args.state}; Ctrl-C stops)\n")
        out.flush()
        with contextlib.suppress(KeyboardInterrupt):
            stop.wait(args.duration)
    finally:
        observer.close()
    return 0


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
