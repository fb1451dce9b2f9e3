"""The spellings that moved to the lab (`rr_actors_lab`), kept for one release.

```
 sup.observe(...)          ─► rr_actors_lab.observe.observe(sup, ...)
 sup.graph(format)         ─► rr_actors_lab.observe.graph(sup, format)
 import rr_actors.mission  ─► import rr_actors_lab.mission     (and experiments, observe,
                                                                 teach, otel: `alias`)
```

Each warns once per call site with a `DeprecationWarning` naming its new spelling, then
imports the lab's module *by name* at the call (`importlib`: the runtime imports nothing of
the lab, `tests/test_init.py` and the import contract hold it): with the runtime alone, the
call raises `MissingExtraError` naming the extra, not a bare `ModuleNotFoundError`. This
module, and the five alias modules it serves, go in the next release.
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable
from types import ModuleType

from rr_actors import _extras

__all__ = ["alias", "lab", "warn"]

LAB = "rr_actors_lab"


def warn(old: str, new: str, *, stacklevel: int = 3) -> None:
    """A `DeprecationWarning`: `old` is deprecated, `new` is its spelling now."""
    warnings.warn(
        f"{old} is deprecated and goes in the next release: use {new}",
        DeprecationWarning,
        stacklevel=stacklevel,
    )


def lab(module: str, what: str, extra: str) -> ModuleType:
    """The lab's `module` (`rr_actors_lab.<module>`), imported by name.

    Raises:
        MissingExtraError: it does not import (the lab, or the extra `extra` it needs, is
            not installed), naming `what` and `extra`.
    """
    with _extras.needs(extra, what):
        return importlib.import_module(f"{LAB}.{module}")


def alias(name: str) -> Callable[[str], object]:
    """The module-level `__getattr__` of the alias module `rr_actors.<lab module>`: each
    name (and submodule) of `rr_actors_lab.<lab module>`, warned about at its first use.

    The alias is a module of its own, not a package: `from rr_actors.mission import config`
    finds the lab's submodule, `import rr_actors.mission.config` is refused by Python itself
    ("'rr_actors.mission' is not a package"), so no second copy of a lab module ever loads.
    """
    moved = name.rpartition(".")[2]
    extra = {"observe": "observe", "teach": "teach", "otel": "otel"}.get(moved, "experiments")

    def __getattr__(attribute: str) -> object:  # noqa: N807 - a module's (PEP 562)
        if attribute.startswith("__"):
            raise AttributeError(f"module {name!r} has no attribute {attribute!r}")
        warn(f"{name}.{attribute}", f"{LAB}.{moved}.{attribute}")
        module = lab(moved, name, extra)
        try:
            return getattr(module, attribute)
        except AttributeError:
            try:
                return importlib.import_module(f"{LAB}.{moved}.{attribute}")
            except ModuleNotFoundError:
                raise AttributeError(
                    f"module {name!r} (now {LAB}.{moved}) has no attribute {attribute!r}"
                ) from None

    return __getattr__
