"""The optional extras of rr-actors, and the one-line error when one is missing.

    with needs("zenoh", "rr.ZenohNetwork"):      # an ImportError inside ──►
        from rr_actors._transport.zenoh.net import ZenohNetwork
                                                  MissingExtraError: rr.ZenohNetwork needs
                                                  an extra: pip install -e ".[zenoh]"

The command installs the extra into the running installation: `pip install -e
"<checkout>[extra]"` from a source checkout (`.` when it is the working directory), else
`pip install "rr-actors[extra]"`; with the message, at most 80 columns.
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
    "teach": "greenlet, msgspec, rich, the observe extra's: the classroom kit, its replay page",
    "title": "setproctitle: `ps` shows a manager process as `rr-actors: <name>`",
    "zenoh": "eclipse-zenoh, cryptography: registrars across hosts, mutual TLS, certs",
}
DISTRIBUTION = "rr-actors"


def _checkout() -> Path | None:
    """The source checkout rr_actors runs from (`pyproject.toml` beside the package), if so."""
    root = Path(__file__).resolve().parent.parent
    return root if (root / "pyproject.toml").is_file() else None


def install_command(extra: str) -> str:
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
        MissingExtraError: an import inside failed (its cause), or an inner `needs` raised
            (raised again naming this `what`).
    """
    try:
        yield
    except MissingExtraError as exc:
        raise MissingExtraError(what, exc.extra, exc.command) from exc
    except ImportError as exc:
        raise MissingExtraError(what, extra, install_command(extra)) from exc
