"""Import paths of a plan (`"package.module:attribute"`), searched first in the plan's directory.

Used while a plan is read, and again in the run and manager processes (the same paths).
"""

from __future__ import annotations

import contextlib
import importlib
import sys
from collections.abc import Iterator
from typing import Any

from rr_actors.errors import ConfigError

__all__ = ["import_object", "search_path"]


@contextlib.contextmanager
def search_path(directory: str | None) -> Iterator[None]:
    """Put `directory` first on `sys.path` while the block runs (nothing if `None`)."""
    if directory is None or directory in sys.path:
        yield
        return
    sys.path.insert(0, directory)
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):
            sys.path.remove(directory)


def import_object(path: str, *, base_dir: str | None = None) -> Any:
    """Import `"package.module:attribute"` (the attribute may be dotted), `base_dir` first.

    Raises:
        ConfigError: the path is malformed, the module does not import (it raised, or
            exited: only `KeyboardInterrupt` goes through), or it has no such attribute.
    """
    module_name, colon, attribute = path.partition(":")
    if not colon or not module_name or not attribute:
        raise ConfigError(f"{path!r} is not an import path of the form 'package.module:name'")
    try:
        with search_path(base_dir):
            target: Any = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"{path!r} does not import: {exc}") from exc
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # a module that calls sys.exit() on import, too
        raise ConfigError(f"{path!r}: importing {module_name} raised {exc!r}") from exc
    for part in attribute.split("."):
        try:
            target = getattr(target, part)
        except AttributeError:
            raise ConfigError(f"{path!r}: {module_name} has no attribute {attribute!r}") from None
    return target
