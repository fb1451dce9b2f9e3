"""Deprecated: `python -m rr_actors` runs the lab's command line for one release, warning.

The `rr-actors` command line is the lab's (`rr_actors_lab`, docs/reference/cli.md): the
console script `rr-actors` runs it, and so does `python -m rr_actors_lab`. For one release
`python -m rr_actors` still does, with a `DeprecationWarning` naming the new spelling (as
`python -m rr_actors.mission` does), importing the lab by name (`_moved`: the runtime imports
nothing of the lab); without the lab it says the one line `MESSAGE` and exits 2.
`from rr_actors.__main__ import main` (and `build_parser`) still give the lab's, warning.
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
    import importlib.util
    import runpy

    if importlib.util.find_spec(_moved.LAB) is None:
        sys.stderr.write(MESSAGE + "\n")
        raise SystemExit(2)
    _moved.warn("python -m rr_actors", "python -m rr_actors_lab", stacklevel=2)
    runpy.run_module(_moved.LAB, run_name="__main__", alter_sys=True)
