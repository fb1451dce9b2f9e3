"""`python -m rr_actors`: one line saying where the command line is, exit status 2.

The `rr-actors` command line is the lab's (`rr_actors_lab`, docs/reference/cli.md): the
console script `rr-actors` runs it, and so does `python -m rr_actors_lab`. The runtime does
not run it for you: that would make the runtime's package import the lab, which it never
does (the import contract in pyproject.toml); a one-line message naming the module to run
costs a user one edit, once. `from rr_actors.__main__ import main` (and `build_parser`)
still give the lab's, with a `DeprecationWarning`, for one release.
"""

from __future__ import annotations

import sys

from rr_actors import _moved

MESSAGE = (
    "rr_actors is the runtime; the rr-actors command line is the lab's: "
    "run `rr-actors ...` or `python -m rr_actors_lab ...`"
)


def __getattr__(name: str) -> object:
    """`main` and `build_parser`: the lab's command line's, deprecated (one release).

    Raises:
        AttributeError: `name` is neither.
        MissingExtraError: the lab is not installed.
    """
    if name not in ("main", "build_parser"):
        raise AttributeError(f"module 'rr_actors.__main__' has no attribute {name!r}")
    _moved.warn(f"rr_actors.__main__.{name}", f"rr_actors_lab.__main__.{name}")
    return getattr(_moved.lab("_cli", f"rr_actors.__main__.{name}", "experiments"), name)


if __name__ == "__main__":
    sys.stderr.write(MESSAGE + "\n")
    raise SystemExit(2)
