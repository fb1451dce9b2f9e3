"""Imported once by a run's forkserver (its preload): the modules of the plan's setups.

    run process: preload_setups(plan) ── RR_ACTORS_PRELOAD={base_dir, modules} ──► forkserver
    forkserver: import rr_actors_lab.experiments._preload ── imports each module ── forks managers

CPython's forkserver imports its preload without the caller's `sys.path` (3.11-3.12), so
the modules and the plan's directory come in `RR_ACTORS_PRELOAD`; each is imported with
that directory first (one that raises is skipped: its manager reports it after the fork),
and the variable is removed so managers and programs do not inherit it.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import sys

from rr_actors_lab.experiments._procs import PRELOAD_VARIABLE

__all__ = ["preload"]


def preload() -> None:
    """Import the modules `PRELOAD_VARIABLE` names (if it is set), then remove it.

    Only the forkserver imports this module (by name), after `rr_actors_lab.experiments`
    is whole: no module of the package imports it, so a setup module that imports
    from the package finds every name.
    """
    named = os.environ.pop(PRELOAD_VARIABLE, None)
    if named is None:
        return
    wanted = json.loads(named)
    base_dir = wanted.get("base_dir")
    added = base_dir is not None and base_dir not in sys.path
    if added:
        sys.path.insert(0, base_dir)
    try:
        for module in wanted.get("modules", []):
            # skipped: its manager imports it after the fork and reports what it raised
            with contextlib.suppress(Exception, SystemExit):
                importlib.import_module(module)
    finally:
        if added and base_dir in sys.path:
            sys.path.remove(base_dir)


preload()
