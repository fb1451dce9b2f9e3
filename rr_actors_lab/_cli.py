"""The `rr-actors` command line.

Each subcommand is one `Command`: a name, a one-line help, a function that adds its
arguments, and a function that runs it. Add a subcommand by appending to `COMMANDS`. Both
functions import what the subcommand needs: the arguments are added only when the
subcommand is chosen, and this module imports only the standard library (`rr-actors
--version` and `--help` take Python's start, not the tools').

    rr-actors demo                          # the thesis's robot mission (Linux)
    rr-actors inspect state/erm.db          # a catalog backup as a tree
    rr-actors inspect state/erm.db --json   # the same as JSON
    rr-actors inspect state/                # every backup in a state_dir
    rr-actors observe --state state/        # the observer's page of the backups
    rr-actors graph --state state/          # the dependency graph as Mermaid (or --format dot)
    rr-actors experiment plan.toml --out results   # a supervision experiment
    rr-actors events --network tls/10.0.0.1:7447 --system lab --certs certs --member watcher
                                            # every host's events as JSON lines, by hlc
    rr-actors events --merge a.jsonl b.jsonl       # events files merged, ordered by hlc
    rr-actors certs init certs --system lab        # a system's CA: certs/ca.pem, ca.key
    rr-actors certs issue certs robot --address 10.0.0.2   # certs/robot.pem, robot.key
    rr-actors --version
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import math
import re
import reprlib
import sys
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn, TextIO

if TYPE_CHECKING:  # (only these: a command imports the runtime's modules when it runs)
    from rr_actors import events
    from rr_actors._catalog import ClientRecord, Resource
    from rr_actors._store import Backup

__all__ = ["COMMANDS", "Command", "backup_to_dict", "main", "render_tree", "version"]


@dataclasses.dataclass(frozen=True)
class Command:
    """One `rr-actors` subcommand.

    Attributes:
        name: the subcommand's name.
        help: one line for `rr-actors --help`.
        add_arguments: adds the subcommand's arguments to its parser (called only when
            the command line names this subcommand).
        run: runs it with the parsed arguments and an output stream; returns the exit code.
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace, TextIO], int]


THIS_COMMAND = ""
"""What needs an extra when a whole subcommand does (`MissingExtraError.what`): the
command is the line's subject, `rr-actors check needs an extra: pip install ...`."""


# -- inspect ------------------------------------------------------------------------------

Node = tuple[str, list[Any]]
"""A tree line and its children."""


def _short(value: Any, width: int = 60) -> str:
    from rr_actors._store import Unreadable

    text = repr(value)
    if isinstance(value, Unreadable) or len(text) <= width:
        return text
    return text[: width - 3] + "..."


def _in_doubt(resource: Resource) -> bool:
    from rr_actors._catalog import ResourceState

    return resource.state is not ResourceState.LOADED


def _client_dict(record: ClientRecord) -> dict[str, Any]:
    query = record.query
    return {
        "query_id": query.id,
        "serving_rr": query.serving_rr,
        "server": query.server,
        "request": repr(query.request),
        "response": repr(query.response),
        "loaded": record.loaded,
    }


def backup_to_dict(backup: Backup) -> dict[str, Any]:
    """A backup as JSON-able data (requests and responses as their `repr`):
    `{"path", "schema_version", "servers": {server: [resource, ...]}, "clients": [...]}`, a
    resource with `id`, `state`, `in_doubt`, `failed` (reported `FATAL`), `request`,
    `response`, `consumers` (`query_id`, `origin_rr`) and `dependencies` (client records);
    `clients`: the top-level queries this registrar holds elsewhere."""
    dependencies: dict[str, list[ClientRecord]] = {}
    for record in backup.clients:
        if record.parent is not None:
            dependencies.setdefault(record.parent, []).append(record)
    servers: dict[str, list[dict[str, Any]]] = {}
    for resource in backup.resources:
        servers.setdefault(resource.server, []).append(
            {
                "id": resource.id,
                "state": resource.state.value,
                "in_doubt": _in_doubt(resource),
                "failed": resource.failed,
                "request": repr(resource.request),
                "response": repr(resource.response),
                "consumers": [
                    {"query_id": qid, "origin_rr": origin}
                    for qid, origin in resource.consumers.items()
                ],
                "dependencies": [_client_dict(r) for r in dependencies.get(resource.id, ())],
            }
        )
    return {
        "path": backup.path,
        "schema_version": backup.schema_version,
        "servers": servers,
        "clients": [_client_dict(r) for r in backup.clients if r.parent is None],
    }


def _client_line(record: ClientRecord) -> str:
    query = record.query
    state = "" if record.loaded else "  [in flight]"
    return (
        f"{query.id} -> {query.serving_rr}/{query.server} {_short(query.request)}"
        f" = {_short(query.response)}{state}"
    )


def _tree(lines: list[str], prefix: str, items: Sequence[tuple[str, list[Any]]]) -> None:
    """Append `items` (label, children) as box-drawn tree lines."""
    for index, (label, children) in enumerate(items):
        last = index == len(items) - 1
        lines.append(f"{prefix}{'└── ' if last else '├── '}{label}")
        _tree(lines, prefix + ("    " if last else "│   "), children)


def render_tree(backup: Backup) -> str:
    """A backup as a tree (servers, resources, consumer ids, dependencies; `[IN DOUBT: ...]`
    marked)."""
    data_deps: dict[str, list[ClientRecord]] = {}
    for record in backup.clients:
        if record.parent is not None:
            data_deps.setdefault(record.parent, []).append(record)
    servers: dict[str, list[Resource]] = {}
    for resource in backup.resources:
        servers.setdefault(resource.server, []).append(resource)
    doubtful = sum(_in_doubt(r) for r in backup.resources)
    lines = [
        f"{backup.path} (schema {backup.schema_version}): {len(backup.resources)} resources, "
        f"{len(backup.clients)} client records" + (f", {doubtful} in doubt" if doubtful else "")
    ]
    server_items = []
    for server, resources in servers.items():
        resource_items = []
        for resource in resources:
            mark = f"  [IN DOUBT: {resource.state.value}]" if _in_doubt(resource) else ""
            mark += "  [FATAL: not shared]" if resource.failed else ""
            consumers: list[Node] = [
                (f"consumer {q} (from {o})", []) for q, o in resource.consumers.items()
            ]
            deps: list[Node] = [
                (f"dependency {_client_line(r)}", []) for r in data_deps.get(resource.id, ())
            ]
            label = (
                f"{_short(resource.request)} = {_short(resource.response)}"
                f"  (resource {resource.id}){mark}"
            )
            resource_items.append((label, [*consumers, *deps]))
        server_items.append((f"server {server}", resource_items))
    tops: list[Node] = [(_client_line(r), []) for r in backup.clients if r.parent is None]
    items: list[Node] = [("servers", server_items)]
    if tops:
        items.append(("queries held elsewhere", tops))
    _tree(lines, "", items)
    return "\n".join(lines) + "\n"


def _inspect_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "path",
        help="the catalog backup (a registrar's backup_path), or a folder of them (a "
        "state_dir): each *.db in it and its subfolders",
    )
    parser.add_argument(
        "--json", action="store_true", help="print JSON instead of a tree (a list, for a folder)"
    )


def _backups_in(folder: Path) -> list[Path]:
    """The catalog backups in `folder` and its subfolders, by path (a `ConfigError` if none)."""
    from rr_actors.errors import ConfigError

    found = sorted(folder.rglob("*.db"))
    if not found:
        raise ConfigError(
            f"{str(folder)!r} is a folder that holds no catalog backup (*.db): name a "
            "registrar's backup file, or its state_dir"
        )
    return found


def _inspect(args: argparse.Namespace, out: TextIO) -> int:
    from rr_actors._store import read_backup

    path = Path(args.path)
    paths = _backups_in(path) if path.is_dir() else [path]
    backups = [read_backup(p) for p in paths]
    if args.json:
        data = [backup_to_dict(b) for b in backups]
        json.dump(data if path.is_dir() else data[0], out, indent=2)
        out.write("\n")
    else:
        out.write("\n".join(render_tree(b) for b in backups))
    return 0


def _demo_arguments(parser: argparse.ArgumentParser) -> None:
    from rr_actors_lab.mission import run  # only the demo needs the mission

    run.add_arguments(parser)


def _demo(args: argparse.Namespace, _out: TextIO) -> int:
    from rr_actors_lab.mission import run  # only the demo needs the mission

    return run.run(args)


def _experiment_arguments(parser: argparse.ArgumentParser) -> None:
    try:
        from rr_actors_lab.experiments import cli  # only experiments need it
    except ImportError:  # the experiments extra is missing: say so when it is used
        parser.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
        parser.set_defaults(any_arguments=True)  # (--list too: `_Parser` lets them through)
        return
    cli.add_arguments(parser)


def _experiment(args: argparse.Namespace, out: TextIO) -> int:
    from rr_actors._extras import needs

    with needs("experiments", THIS_COMMAND):
        from rr_actors_lab.experiments import cli  # only experiments need it
    return cli.main(args, out)


_REPLAY_HELP = "run a seed of a simulated experiment again: the same history, its hash checked"

_SHRINK_HELP = (
    "shrink a violating seed of a simulated experiment to a small plan that violates the "
    "same way, written as a run `replay` reads"
)


def _sweep_arguments(command: str, parser: argparse.ArgumentParser) -> None:
    """The arguments of the simulation's `command` (`replay`, `shrink`): `sweep`'s
    `<command>_arguments`, or none if the experiments extra is missing (said when used)."""
    try:
        from rr_actors_lab.experiments import sweep  # only experiments need it
    except ImportError:  # the experiments extra is missing: say so when it is used
        parser.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
        parser.set_defaults(any_arguments=True)
        return
    getattr(sweep, f"{command}_arguments")(parser)


def _sweep_command(command: str, args: argparse.Namespace, out: TextIO) -> int:
    """Run the simulation's `command` (`sweep.run_<command>`), its extras checked first."""
    from rr_actors._extras import needs

    with needs("experiments", THIS_COMMAND):
        from rr_actors import simulation  # its extra (greenlet): said at once
        from rr_actors_lab.experiments import sweep  # only experiments need it
    del simulation
    code: int = getattr(sweep, f"run_{command}")(args, out)
    return code


_CHECK_HELP = "check a run's events against the semantic rules: a verdict per run"


def _check_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "run_dir",
        metavar="RUN_DIR",
        help="an experiment's output directory (or a run's), or an events.jsonl file",
    )
    parser.add_argument(
        "--quiet", "-q", action="store_true", help="print the verdicts only, not the windows"
    )


def _check(args: argparse.Namespace, out: TextIO) -> int:
    """Print each run's verdict and findings; exit 1 if any run violated a rule."""
    from rr_actors._extras import needs

    with needs("experiments", THIS_COMMAND):
        from rr_actors_lab.experiments import check  # only this command needs it
    from rr_actors.errors import ConfigError

    path = Path(args.run_dir)
    try:
        verdicts = check.check_file(path)
    except ConfigError as exc:
        sys.stderr.write(f"rr-actors check: {exc}\n")
        return 2
    file = path / "events.jsonl" if path.is_dir() else path
    if not verdicts:
        sys.stderr.write(f'rr-actors check: {file}: no events (no line with a "schema")\n')
        return 2
    wanted: set[int] = set()
    if not args.quiet:
        wanted = {n for v in verdicts.values() for f in v.findings for n in f.lines}
    texts: dict[int, str] = {}
    if wanted:  # (those lines only: the file may hold a million events)
        with file.open("rb") as stream:
            for number, raw in enumerate(stream, start=1):
                if number in wanted:
                    texts[number] = raw[:300].decode("utf-8", "replace").rstrip("\n")

    def show(number: int) -> str:
        text = texts.get(number, "")
        return text if len(text) <= 200 else text[:197] + "..."

    for run, verdict in verdicts.items():
        lines = check.format_verdict(run, verdict, None if args.quiet else show)
        out.write("\n".join(lines[:1] if args.quiet else lines) + "\n")
    return 1 if any(v.verdict == "violated" for v in verdicts.values()) else 0


# -- observe, graph (rr_actors_lab.observe._commands) -------------------------------------

_OBSERVE_HELP = (
    "serve the observer's page for a state directory's backups (--state: read-only, no live "
    "system), or of every host of a system across hosts (--system: as a member; needs the "
    "zenoh extra); needs the observe extra"
)
_GRAPH_HELP = "print the dependency graph of a state directory's backups as Mermaid or DOT text"


def _observe_arguments(parser: argparse.ArgumentParser) -> None:
    from rr_actors_lab.observe import _commands  # only these need the observer

    _commands.observe_arguments(parser)


def _observe(args: argparse.Namespace, out: TextIO) -> int:
    from rr_actors_lab.observe import _commands  # only these need the observer

    return _commands.run_observe(args, out)


def _graph_arguments(parser: argparse.ArgumentParser) -> None:
    from rr_actors_lab.observe import _commands  # only these need the observer

    _commands.graph_arguments(parser)


def _graph(args: argparse.Namespace, out: TextIO) -> int:
    from rr_actors_lab.observe import _commands  # only these need the observer

    return _commands.run_graph(args, out)


# -- events ----------------------------------------------------------------------------------

_EVENTS_HELP = "print every host's events as JSON lines, ordered by their clock stamps (hlc)"


_TEACH_HELP = "a classroom kit: exercises checked by the verdict of simulated runs"


def _teach_arguments(parser: argparse.ArgumentParser) -> None:
    try:
        from rr_actors_lab.teach import cli  # only the kit needs it
    except ImportError:  # the teach extra is missing: say so when it is used
        parser.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
        parser.set_defaults(any_arguments=True)
        return
    cli.add_arguments(parser)


def _teach(args: argparse.Namespace, out: TextIO) -> int:
    from rr_actors._extras import needs

    with needs("teach", THIS_COMMAND):
        from rr_actors_lab.teach import cli  # only the kit needs it
    return cli.main(args, out)


def _positive_whole(of: str) -> Callable[[str], int]:
    """An argparse `type` for a positive whole number of `of` (the message names it)."""

    def parse(text: str) -> int:
        try:
            number = int(text)
        except ValueError:
            number = 0
        if number < 1:
            raise argparse.ArgumentTypeError(f"a positive whole number of {of}, not {text!r}")
        return number

    return parse


def _positive_seconds(text: str) -> float:
    try:
        seconds = float(text)
    except ValueError:
        seconds = math.nan
    if not (seconds > 0 and math.isfinite(seconds)):
        raise argparse.ArgumentTypeError(f"a positive number of seconds, not {text!r}")
    return seconds


def _events_arguments(parser: argparse.ArgumentParser) -> None:
    from rr_actors_lab._tools.options import add_network_arguments

    parser.add_argument(
        "--merge",
        metavar="FILE",
        nargs="+",
        help="print these events.jsonl files merged, ordered by hlc (instead of --network)",
    )
    parser.add_argument(
        "--window",
        metavar="SECONDS",
        type=float,
        default=0.5,
        help="seconds an event is held for those of other hosts to overtake it (0.5)",
    )
    parser.add_argument(
        "--count", metavar="N", type=_positive_whole("events"), help="stop after N events"
    )
    parser.add_argument(
        "--seconds", metavar="S", type=_positive_seconds, help="stop after S seconds"
    )
    add_network_arguments(parser)


def _events(args: argparse.Namespace, out: TextIO) -> int:
    """Print the system's events (`--network`) or merge files (`--merge`), one JSON line each."""
    import threading

    from rr_actors import events
    from rr_actors._extras import needs
    from rr_actors.errors import ConfigError
    from rr_actors.events.lines import json_lines
    from rr_actors_lab._tools.options import network_from

    if args.merge:
        merged: list[tuple[int, str]] = []  # (stamp, line), in the files' order
        for name in args.merge:
            stamp = 0
            for number, data in json_lines(name):
                try:
                    stamp, line = _merged_line(data, stamp)
                except ConfigError as exc:
                    raise ConfigError(f"{name} line {number}: {exc}") from None
                merged.append((stamp, line))
        merged.sort(key=lambda stamped: stamped[0])  # (stable: as events.order)
        for _, line in merged[: args.count]:
            out.write(line + "\n")
        return 0
    with needs("zenoh", "--network"):
        network = network_from(args)
    done = threading.Event()
    shown = 0

    def show(event: events.Event) -> None:  # (the subscription's thread)
        nonlocal shown
        if done.is_set():
            return
        out.write(json.dumps(events.to_dict(event)) + "\n")
        out.flush()
        shown += 1
        if args.count is not None and shown >= args.count:
            done.set()

    with (
        network,
        network.subscribe_events(show, window=args.window),
        contextlib.suppress(KeyboardInterrupt),  # (Ctrl-C ends it: exit 0)
    ):
        done.wait(args.seconds)
    return 0


RUN_KEYS = ("run", "seed")
"""What an experiment adds to each event's line of its `events.jsonl`: the run's number
and seed (`rr_actors_lab.experiments.runner`)."""

FAULT_LINES = ("FaultInjected", "FaultSkipped", "Crashed")  # (a crashed seed's last line)
"""The `type` of an experiment's lines for its faults (`experiments.runner.fault_line`):
not events (no `schema`, no `hlc`); merged at their `at`, the wall clock."""


def _merged_line(data: Any, previous: int) -> tuple[int, str]:
    """One line of an events file as `--merge` prints it (`events.to_dict`'s, with its `run` and
    `seed`; a fault line as it is, stamped at its `at` or else `previous`), and its stamp.

    Raises:
        ConfigError: not an event or fault line, a field of a wrong type, a fault's `at` not
            a number.
    """
    from rr_actors import events
    from rr_actors._core import hlc
    from rr_actors.errors import ConfigError

    if isinstance(data, dict) and "schema" not in data and data.get("type") in FAULT_LINES:
        at = data.get("at")
        if at is None:
            return previous, json.dumps(data)
        if type(at) not in (int, float) or not math.isfinite(at):
            raise ConfigError(f"{data['type']}.at must be a number, got {reprlib.repr(at)}")
        return hlc.from_seconds(at), json.dumps(data)
    run: dict[str, int] = {}
    if isinstance(data, dict) and "schema" in data:
        data = dict(data)
        for key in RUN_KEYS:
            if key in data:
                value = data.pop(key)
                if type(value) is not int or (key == "run" and value < 0):
                    least = " >= 0" if key == "run" else ""
                    raise ConfigError(f"{key} must be an int{least}, got {reprlib.repr(value)}")
                run[key] = value
    event = events.from_dict(data)
    return event.hlc, json.dumps({**events.to_dict(event), **run})


# -- certs -----------------------------------------------------------------------------------

_CERTS_HELP = "make a system's CA and its hosts' certificates for ZenohNetwork's mutual TLS"


def _certs_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="certs_command", metavar="SUBCOMMAND", required=True)
    init = sub.add_parser(
        "init",
        help="write DIR/ca.pem and DIR/ca.key (0600): the system's certificate authority",
        description="Write DIR/ca.pem and DIR/ca.key (0600), the system's certificate "
        "authority (10 years). DIR is made 0700 if missing; an existing DIR must be yours "
        "and writable by nobody else. ca.key stays here.",
    )
    init.add_argument("dir", metavar="DIR", help="where the CA's files go")
    init.add_argument(
        "--system", required=True, help="the system's name (ZenohNetwork system=; at most 64)"
    )
    init.add_argument(
        "--force",
        action="store_true",
        help="replace an existing CA; write into a DIR others may write to",
    )
    issue = sub.add_parser(
        "issue",
        help="write DIR/NAME.pem and DIR/NAME.key (0600): a host's certificate, signed by the CA",
        description="Write DIR/NAME.pem and DIR/NAME.key (0600), signed by DIR/ca.pem and "
        "DIR/ca.key: common name NAME (the member name), every --address peers dial. "
        "ca.key and DIR must be yours and private to you.",
    )
    issue.add_argument("dir", metavar="DIR", help="holds ca.pem and ca.key; the files go here")
    issue.add_argument(
        "name", metavar="NAME", help="the host's member name (its common name; at most 64)"
    )
    issue.add_argument(
        "--address",
        action="append",
        default=[],
        metavar="ADDR",
        help="an IP address or DNS name peers dial this host at (repeat; default: NAME)",
    )
    issue.add_argument(
        "--days", type=_positive_whole("days"), default=365, help="days it is valid (default 365)"
    )
    issue.add_argument(
        "--force",
        action="store_true",
        help="replace an existing NAME; sign with a ca.key or in a DIR others may reach",
    )


def _certs(args: argparse.Namespace, out: TextIO) -> int:
    from rr_actors._extras import needs

    with needs("zenoh", THIS_COMMAND):
        from rr_actors_lab._tools import certs  # needs cryptography
    if args.certs_command == "init":
        pem, key = certs.init_ca(args.dir, args.system, force=args.force)
        out.write(
            f"wrote {pem} and {key} (0600)\n"
            + _words(
                "ca.key stays here: whoever holds it can make members. Next, each host's "
                "certificate:"
            )
            + f"    rr-actors certs issue {args.dir} NAME --address ADDR\n"
        )
        return 0
    pem, key = certs.issue_cert(args.dir, args.name, args.address, days=args.days, force=args.force)
    ca = pem.parent / "ca.pem"
    out.write(
        f"wrote {pem} and {key} (0600)\n"
        + _words(
            f"Next: copy {ca}, {pem} and {key} to the host {args.name} (keep {key} 0600; "
            f"ca.key stays here), and name {args.name!r} in every host's "
            f"rr.ZenohTLS(members=[...])"
        )
    )
    return 0


def _words(text: str, width: int = 80) -> str:
    """`text` wrapped at words to `width` columns, each line ended; a path or a name is
    never cut (it stands alone on a line when it is longer)."""
    lines = textwrap.wrap(text, width, break_long_words=False, break_on_hyphens=False)
    return "".join(f"{line}\n" for line in lines)


COMMANDS: list[Command] = [
    Command(
        "demo",
        "run the thesis's fault-injected robot mission on real processes (the main demo; Linux)",
        _demo_arguments,
        _demo,
    ),
    Command(
        "inspect",
        "print a catalog backup as a tree (safe on a live file; unpickles its values)",
        _inspect_arguments,
        _inspect,
    ),
    Command("observe", _OBSERVE_HELP, _observe_arguments, _observe),
    Command("graph", _GRAPH_HELP, _graph_arguments, _graph),
    Command("events", _EVENTS_HELP, _events_arguments, _events),
    Command(
        "experiment",
        "run a supervision experiment from a TOML plan: faults, workload, repeats, plots",
        _experiment_arguments,
        _experiment,
    ),
    Command("check", _CHECK_HELP, _check_arguments, _check),
    Command(
        "replay",
        _REPLAY_HELP,
        functools.partial(_sweep_arguments, "replay"),
        functools.partial(_sweep_command, "replay"),
    ),
    Command(
        "shrink",
        _SHRINK_HELP,
        functools.partial(_sweep_arguments, "shrink"),
        functools.partial(_sweep_command, "shrink"),
    ),
    Command("certs", _CERTS_HELP, _certs_arguments, _certs),
    Command("teach", _TEACH_HELP, _teach_arguments, _teach),
]
"""The subcommands, in the order `--help` lists them."""


def version() -> str:
    """The installed distribution's version (the package's `__version__` if not installed)."""
    import importlib.metadata  # (its import costs more than the rest of `--help`'s)

    try:
        return importlib.metadata.version("rr-actors")
    except importlib.metadata.PackageNotFoundError:
        import rr_actors

        return rr_actors.__version__


class _Version(argparse.Action):
    """`--version`: print `rr-actors VERSION` and exit 0 (the version read when asked)."""

    def __init__(self, option_strings: Sequence[str], dest: str, help: str) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> NoReturn:
        sys.stdout.write(f"{parser.prog} {version()}\n")
        parser.exit()


_INVALID_CHOICE = re.compile(r"invalid choice: '(?P<name>[^']*)' \(choose from (?P<known>.*)\)$")
"""argparse's error for a value that is not one of an argument's choices."""


class _Parser(argparse.ArgumentParser):
    """An argument parser that adds its arguments when it first parses, and whose errors
    say what was meant.

    A subcommand's parser gets its arguments (`Command.add_arguments`, which imports what
    the subcommand needs) only when argparse chooses it: `rr-actors --version`, `--help`
    and every other subcommand import none of it. A choice that is not one, or an option
    the parser does not know, is an error of the parser that was given it (its usage, then
    the closest name: `unknown option --fats; did you mean --fast?`), exit 2; argparse
    itself reports a subcommand's unknown options with the top-level usage and no hint
    (its `suggest_on_error` is 3.14's). A subcommand whose extra is missing takes any
    arguments (`any_arguments` in its defaults): running it says what to install.
    """

    def __init__(
        self,
        *args: Any,
        arguments: Callable[[argparse.ArgumentParser], None] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        self._add_arguments = arguments

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        """Parse `args` as `parse_args` does (argparse calls this on a chosen subcommand's
        parser); the unknown arguments are returned only when `any_arguments` is set."""
        if self._add_arguments is not None:
            add, self._add_arguments = self._add_arguments, None
            add(self)
        parsed, unknown = super().parse_known_args(args, namespace)
        if unknown and not getattr(parsed, "any_arguments", False):
            self.error(self._unknown(unknown))
        return parsed, unknown

    def _unknown(self, unknown: list[str]) -> str:
        """What is wrong with `unknown` arguments: the first option argparse does not know,
        with the closest one this parser has (what follows it may be its value: not named);
        or, without an option, the arguments."""
        options = [a for a in unknown if a[:1] == "-" and a[1:2] not in ("", *"0123456789.")]
        if not options:
            return f"unrecognized arguments: {' '.join(unknown)}"
        import difflib  # an error's path only

        wrong = options[0].split("=", 1)[0]
        known = {  # (compared without their dashes: `--` alone would make --bogus --out)
            o.lstrip("-"): o
            for a in self._actions
            if a.help != argparse.SUPPRESS
            for o in a.option_strings
        }
        close = difflib.get_close_matches(wrong.lstrip("-"), known)
        close.sort(key=lambda name: sorted(name) != sorted(wrong.lstrip("-")))  # (a swap first)
        hint = f"; did you mean {known[close[0]]}?" if close else ""
        return f"unknown option {wrong}{hint}"

    def error(self, message: str) -> NoReturn:
        """Print the usage and `message` (with the closest choice) on stderr; exit 2."""
        wrong = _INVALID_CHOICE.search(message)
        if wrong is not None:
            from rr_actors.errors import _known_names  # an error's path only

            listed = wrong.group("known")  # `'a', 'b'` (or `a, b` on newer Pythons)
            known = re.findall(r"'([^']*)'", listed) or listed.split(", ")
            hint = _known_names(wrong.group("name"), known, shown=len(known))
            message = message[: wrong.start()] + f"invalid choice: {wrong.group('name')!r}{hint}"
        super().error(message)


def build_parser() -> argparse.ArgumentParser:
    """The `rr-actors` argument parser, one subparser per entry of `COMMANDS` (a
    subcommand's arguments are added when it is chosen: `parse_args` adds them)."""
    parser = _Parser(prog="rr-actors", description="Tools for rr_actors resource registrars.")
    parser.add_argument("--version", action=_Version, help="print the version")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")  # none: the help
    for command in COMMANDS:
        sub = subparsers.add_parser(
            command.name,
            help=command.help,
            description=command.help,
            arguments=command.add_arguments,
        )
        sub.set_defaults(run=command.run)
    return parser


def main(argv: Sequence[str] | None = None, out: TextIO | None = None) -> int:
    """Run `rr-actors` (the console script's entry point).

    Args:
        argv: the arguments without the program name (default: `sys.argv[1:]`).
        out: where results go (default: standard output). Errors go to standard error.

    Returns:
        The exit code: 0 on success; 1 when the backup cannot be read or a `certs` file is
        refused (the message names the file and the cause); 2 for a usage error, a missing
        extra (one line names it and how to install it), or no command (the help printed).
    """
    parser = build_parser()
    args, _ = parser.parse_known_args(argv)  # (the unknown: only where any are taken)
    if args.command is None:
        parser.print_help(out)
        return 2
    from rr_actors.errors import CatalogCorruptError, ConfigError, MissingExtraError

    try:
        code: int = args.run(args, out if out is not None else sys.stdout)
    except MissingExtraError as exc:  # one line, and what to install: nothing was done
        subject = f"rr-actors {args.command}" + (": " if exc.what else " ")
        print(f"{subject}{exc}", file=sys.stderr)  # noqa: T201 - CLI output
        return 2
    except (CatalogCorruptError, ConfigError) as exc:
        _error(f"rr-actors {args.command}: {exc}")
        return 1
    return code


def _error(line: str) -> None:
    """`line` on standard error: one line, wrapped at words on a terminal it does not fit
    (a file's name, its line and what is wrong with it can take more than 80 columns)."""
    from rr_actors._log import terminal_width, wrap

    width = terminal_width(sys.stderr)
    print(line if width is None else wrap(line, width), file=sys.stderr)  # noqa: T201 - CLI output


if __name__ == "__main__":
    sys.exit(main())
