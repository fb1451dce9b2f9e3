"""The optional extras of rr-actors, and the one-line error when one is missing.

    with needs("zenoh", "rr.ZenohNetwork"):      # an ImportError inside ──►
        from rr_actors._transport.zenoh.net import ZenohNetwork
                                                  MissingExtraError: rr.ZenohNetwork needs
                                                  an extra: pip install -e ".[zenoh]"

The command in the message installs the extra into the installation that is running,
and names it as pip does: `pip install -e "<checkout>[extra]"` when rr_actors runs from
a source checkout (`.` when it is the working directory, as after the README's `pip
install -e ".[demo]"`), else `pip install "rr-actors[extra]"`. The command line prints
the error's one line and exits with 2 (`rr_actors._cli.main`): `rr-actors experiment
needs an extra: pip install -e ".[experiments]"` when a whole command needs it (an empty
`what`), `rr-actors demo: --hosts 2 needs an extra: ...` when an option does; 80 columns
at most either way (the extra named once, in the command: "needs the experiments extra"
took the line to 81-95).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from rr_actors.errors import MissingExtraError

__all__ = ["EXTRAS", "install_command", "needs"]

EXTRAS = {
    "demo": "matplotlib, rich: the mission's plot, its live progress line and tables",
    "experiments": "msgspec, matplotlib, rich: plans checked against their schema, plots",
    "observe": "Starlette, sse-starlette, uvicorn: the observer's web page",
    "teach": "greenlet, msgspec: the classroom kit's exercises, checked on the simulation",
    "title": "setproctitle: `ps` shows a manager process as `rr-actors: <name>`",
    "zenoh": "eclipse-zenoh, cryptography: registrars across hosts, mutual TLS, certs",
}
"""Each extra of `pyproject.toml` that a user installs, and what it brings."""

DISTRIBUTION = "rr-actors"


def _checkout() -> Path | None:
    """The source checkout rr_actors runs from (`pip install -e`, or on `sys.path`), if so.

    A checkout holds `pyproject.toml` beside the package; an installed wheel does not.
    """
    root = Path(__file__).resolve().parent.parent
    return root if (root / "pyproject.toml").is_file() else None


def install_command(extra: str) -> str:
    """The command that installs `extra` into this installation of rr-actors."""
    checkout = _checkout()
    if checkout is None:
        return f'pip install "{DISTRIBUTION}[{extra}]"'
    try:
        here = Path.cwd().resolve() == checkout.resolve()
    except OSError:  # the working directory was deleted
        here = False
    where = "." if here else os.fspath(checkout)
    return f'pip install -e "{where}[{extra}]"'


@contextlib.contextmanager
def needs(extra: str, what: str) -> Iterator[None]:
    """Turn an `ImportError` inside into a `MissingExtraError` naming `what` and `extra`.

    Raises:
        MissingExtraError: an import inside failed (the `ImportError` is its cause); one
            raised inside by an inner `needs` is raised again naming this `what`.
    """
    try:
        yield
    except MissingExtraError as exc:
        raise MissingExtraError(what, exc.extra, exc.command) from exc
    except ImportError as exc:
        raise MissingExtraError(what, extra, install_command(extra)) from exc
