"""Import paths of a plan (`"package.module:attribute"`), searched first in the plan's directory.

Used while a plan is read, and again in the run and manager processes (the same paths).
"""

from __future__ import annotations

import functools
import importlib
import sys
from typing import Any

from rr_actors.errors import ConfigError

__all__ = ["import_object"]


def import_object(path: str, *, base_dir: str | None = None) -> Any:
    """Import `"package.module:attribute"` (the attribute may be dotted), `base_dir` first.

    Raises:
        ConfigError: the path is malformed, the module does not import (it raised, or
            exited; a `KeyboardInterrupt` goes through), or it has no such attribute.
    """
    module_name, colon, attribute = path.partition(":")
    if not colon or not module_name or not attribute:
        raise ConfigError(f"{path!r} is not an import path of the form 'package.module:name'")
    added = base_dir if base_dir is not None and base_dir not in sys.path else None
    if added is not None:  # first on `sys.path` while it imports
        sys.path.insert(0, added)
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"{path!r} does not import: {exc}") from exc
    except (Exception, SystemExit) as exc:  # a module that calls sys.exit() on import, too
        raise ConfigError(f"{path!r}: importing {module_name} raised {exc!r}") from exc
    finally:
        if added is not None and added in sys.path:
            sys.path.remove(added)
    try:
        return functools.reduce(getattr, attribute.split("."), module)
    except AttributeError:
        raise ConfigError(f"{path!r}: {module_name} has no attribute {attribute!r}") from None
