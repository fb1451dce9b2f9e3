"""Command-line options that join a system over Zenoh: `--network`, `--system`, TLS files.

Shared by the `rr-actors` commands that watch a system from another process (`events`;
`observe` across hosts can take the same): `add_network_arguments(parser)` adds them,
`network_from(args)` makes the `ZenohNetwork` (importing Zenoh only then, so the command
line works without the `zenoh` extra until one of them is used).

```
rr-actors events --network tls/10.0.0.1:7447 --system lab --certs certs --member watcher
rr-actors events --network tcp/127.0.0.1:7447 --system lab --plain     # one trusted network
```

`--certs DIR` holds what `rr-actors certs` made: `DIR/ca.pem`, `DIR/<member>.pem` and
`DIR/<member>.key`; `--members` defaults to every `DIR/<name>.pem` but `ca.pem` (the
hosts whose certificates were issued there), `--member` included.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rr_actors.errors import ConfigError

__all__ = ["add_network_arguments", "network_from"]


def add_network_arguments(parser: argparse.ArgumentParser) -> None:
    """Add `--network`, `--system`, `--certs`, `--member`, `--members`, `--plain`, `--lease`."""
    group = parser.add_argument_group("joining the system (ZenohNetwork)")
    group.add_argument(
        "--network",
        metavar="ENDPOINT",
        action="append",
        default=[],
        help="a member host's router to connect to: tls/ADDRESS:PORT (tcp/ with --plain); "
        "repeat for more",
    )
    group.add_argument("--system", metavar="NAME", help="the system's name (as its hosts')")
    group.add_argument(
        "--certs",
        metavar="DIR",
        help="the system's TLS files (rr-actors certs): DIR/ca.pem, DIR/MEMBER.pem, .key",
    )
    group.add_argument(
        "--member", metavar="NAME", help="this process's member name (its certificate's)"
    )
    group.add_argument(
        "--members",
        metavar="A,B,...",
        help="the member names admitted (default: every DIR/NAME.pem but ca.pem)",
    )
    group.add_argument(
        "--plain",
        action="store_true",
        help="plain TCP, no TLS (one trusted network only: whoever reaches it can run code)",
    )
    group.add_argument(
        "--lease", metavar="SECONDS", type=float, default=1.0, help="see ZenohNetwork (1.0)"
    )


def network_from(args: argparse.Namespace) -> Any:
    """The `ZenohNetwork` the options of `add_network_arguments` describe (not opened).

    Raises:
        ConfigError: `--network` or `--system` missing, TLS options missing or given
            with `--plain`, or what `ZenohTLS` / `ZenohNetwork` refuse (naming it).
    """
    if not args.network:
        raise ConfigError("--network ENDPOINT is required (a member host's router)")
    if not args.system:
        raise ConfigError("--system NAME is required (the system's name)")
    from rr_actors._transport.zenoh.net import ZenohNetwork  # noqa: PLC0415 - the extra
    from rr_actors_lab.observe import _feed  # noqa: F401, PLC0415 - its event feed beside

    if args.plain:
        if args.certs or args.member or args.members:
            raise ConfigError("--plain takes no --certs, --member or --members")
        return ZenohNetwork(system=args.system, connect=args.network, tls=None, lease=args.lease)
    if not args.certs or not args.member:
        raise ConfigError("--certs DIR and --member NAME are required (or --plain)")
    from rr_actors._transport.zenoh.ops.tls import ZenohTLS  # noqa: PLC0415 - cryptography

    directory = Path(args.certs)
    if args.members:
        members = [name.strip() for name in args.members.split(",") if name.strip()]
    else:
        members = sorted({p.stem for p in directory.glob("*.pem") if p.stem != "ca"})
        members += [args.member] * (args.member not in members)
    tls = ZenohTLS(
        ca=directory / "ca.pem",
        cert=directory / f"{args.member}.pem",
        key=directory / f"{args.member}.key",
        members=members,
    )
    return ZenohNetwork(system=args.system, connect=args.network, tls=tls, lease=args.lease)
