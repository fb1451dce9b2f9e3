"""Supervision trees after Erlang/OTP's `supervisor`: policy on top of the process layer.

The handle (`Supervisor`, `supervisor.py`) is imported at the first use of one of its
names (PEP 562), so that a module of the package (the observer's protocol, `watching`)
can be imported without the whole tree: a manager process takes the observer's event
feed beside its Zenoh session, never a supervisor.
"""

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rr_actors._supervision.supervisor import ChildCounts, ChildInfo, Supervisor

__all__ = ["ChildCounts", "ChildInfo", "Supervisor"]


def __getattr__(name: str) -> object:
    """`ChildCounts`, `ChildInfo`, `Supervisor`, from `supervisor.py` at first use."""
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module("rr_actors._supervision.supervisor"), name)
    globals()[name] = value
    return value
