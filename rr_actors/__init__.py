"""rr_actors: TeMoto's Resource Registrar as a Python actor framework.

Registrars, resource servers and clients are pykka actors; the docs hold a tutorial, the semantics
(`docs/explanation/semantics.md`) and the architecture. `import rr_actors` imports the errors, the
configuration and the status types; the runtime is imported at the first use of one of its names
(PEP 562), so a program that only configures pays for none of it.
"""

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
from contextlib import nullcontext
from typing import TYPE_CHECKING

from rr_actors import _extras, _log
from rr_actors._types import Query, Status, StatusCallback, StatusUpdate
from rr_actors._types import StatusDelivery as StatusDelivery
from rr_actors.config import Backoff, ManagerSpec, RegistrarConfig, SupervisorSpec
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    ResourceLoadError,
    RrError,
    UnknownQueryError,
)

# isort: split
# The names `__all__` listed before issue 54, still importable from here.
from rr_actors.config import MAX_DEPENDENCY_DEPTH  # noqa: F401
from rr_actors.errors import (  # noqa: F401
    CatalogCorruptError,
    CatalogWriteError,
    DeadlineExceededError,
    DependencyCycleError,
    DuplicateNameError,
    DuplicateQueryIdError,
    ErrorFrame,
    InternalError,
    MessageTooLargeError,
    MissingExtraError,
    OverloadedError,
    SupervisorGaveUpError,
    TransferError,
    UnknownRegistrarError,
    UnknownServerError,
)

if TYPE_CHECKING:  # at run time, `__getattr__` below imports each at its first use
    from rr_actors import events as events  # `rr.events.to_dict(...)`, as `rr.errors` is
    from rr_actors._core.bus import Subscription
    from rr_actors._registrar import Registrar, ResourceRegistrar, StatusWatch
    from rr_actors._store.files import quarantine_backup as quarantine_backup
    from rr_actors._supervision import ChildCounts as ChildCounts
    from rr_actors._supervision import ChildInfo, Supervisor
    from rr_actors._supervision.watching import Observing
    from rr_actors._transport.resolve import Claimant
    from rr_actors._transport.zenoh.net import ZenohNetwork
    from rr_actors._transport.zenoh.ops.tls import ZenohTLS

__all__ = [
    "Backoff",
    "CallTimeoutError",
    "ChildInfo",
    "Claimant",
    "ConfigError",
    "ManagerSpec",
    "Query",
    "Registrar",
    "RegistrarConfig",
    "RegistrarStoppedError",
    "RegistrarUnavailableError",
    "ResourceLoadError",
    "ResourceRegistrar",
    "RrError",
    "Status",
    "StatusCallback",
    "StatusUpdate",
    "StatusWatch",
    "Subscription",
    "Supervisor",
    "SupervisorSpec",
    "UnknownQueryError",
    "ZenohNetwork",
    "ZenohTLS",
]
"""What a program uses (24 names, issue 54); every error is in `rr_actors.errors`. The names
this module listed before are all still importable from it (`rr.UnknownServerError`).
"""

__version__ = "0.1.0"

_log.install()  # WARNING and ERROR on stderr, level and logger named, until logging is configured


_RUNTIME = {
    "events": "rr_actors.events",
    "Subscription": "rr_actors._core.bus",
    "Registrar": "rr_actors._registrar",
    "ResourceRegistrar": "rr_actors._registrar",
    "StatusWatch": "rr_actors._registrar",
    "quarantine_backup": "rr_actors._store.files",
    "ChildCounts": "rr_actors._supervision",
    "ChildInfo": "rr_actors._supervision",
    "Supervisor": "rr_actors._supervision",
    "Claimant": "rr_actors._transport.resolve",
    "ZenohNetwork": "rr_actors._transport.zenoh.net",
    "ZenohTLS": "rr_actors._transport.zenoh.ops.tls",
}
"""Each name of the runtime this module gives, and the module imported at its first use."""

_NEEDS_ZENOH = {"ZenohNetwork", "ZenohTLS"}


def _observer() -> "Observing":
    """The observer, as a supervisor finds it: the lab's, imported at a supervisor's first
    `observe`."""
    from rr_actors_lab.observe._observer import SUPERVISORS  # noqa: PLC0415 - the lab

    return SUPERVISORS


def _attach_lab(module: object) -> None:
    """Attach the lab's parts a runtime module finds through a protocol of its own: the observer
    to supervisors, the cross-host event feed and link watch to Zenoh sessions.
    """
    if getattr(module, "__name__", "") == "rr_actors._supervision":
        from rr_actors._supervision.watching import attach_observer  # noqa: PLC0415

        attach_observer(_observer)
    elif getattr(module, "__name__", "") == "rr_actors._transport.zenoh.net":
        from rr_actors_lab.observe import _feed  # noqa: F401, PLC0415 - attaches itself


def __getattr__(name: str) -> object:
    """A name of the runtime (`_RUNTIME`), its module imported at first use (PEP 562).

    Raises:
        AttributeError: `name` is not one of this module's.
        MissingExtraError: `rr.ZenohNetwork` or `rr.ZenohTLS` without the zenoh extra.
    """
    where = _RUNTIME.get(name)
    if where is None:
        raise AttributeError(f"module 'rr_actors' has no attribute {name!r}")
    needs = _extras.needs("zenoh", f"rr.{name}") if name in _NEEDS_ZENOH else nullcontext()
    with needs:
        module = importlib.import_module(where)
        _attach_lab(module)
    value = module if name == "events" else getattr(module, name)
    globals()[name] = value  # (the next use finds it here, as an eager import would)
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_RUNTIME})


def _errors_getattr(name: str) -> object:
    """`rr_actors.errors.quarantine_backup`, beside the error it recovers from, imported at
    its first use: it is the store's, and the store imports `errors`, so it is attached
    from here, above both (PEP 562), never imported by `errors` itself.

    Raises:
        AttributeError: `name` is not one of `rr_actors.errors`'.
    """
    if name != "quarantine_backup":
        raise AttributeError(f"module 'rr_actors.errors' has no attribute {name!r}")
    return importlib.import_module("rr_actors._store.files").quarantine_backup


vars(sys.modules["rr_actors.errors"])["__getattr__"] = _errors_getattr


_LAB = ("experiments", "mission", "observe", "teach", "otel", "_cli", "_tools")
"""The lab's modules that lived under `rr_actors` before they moved beside it, to
`rr_actors_lab` (issue 54): `rr_actors.experiments` and its submodules still import."""


class _LabNames(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """`rr_actors.<lab module>[.sub]` as another name of `rr_actors_lab.<lab module>[.sub]`:
    the same module object (one `Plan` class, whichever name imported it), so a program
    written before the move runs on. Ahead of the path finder, which would load a second
    copy from the lab's directory."""

    def find_spec(
        self, fullname: str, path: object = None, target: object = None
    ) -> importlib.machinery.ModuleSpec | None:
        parts = fullname.split(".")
        if len(parts) < 2 or parts[0] != "rr_actors" or parts[1] not in _LAB:
            return None
        if parts[-1] == "__main__":  # (`python -m rr_actors.mission`: the path finder runs it)
            return None
        lab = importlib.util.find_spec("rr_actors_lab" + fullname.removeprefix("rr_actors"))
        if lab is None:  # (no such module: the path finder says so, by its own name)
            return None
        spec = importlib.machinery.ModuleSpec(fullname, self)
        spec.submodule_search_locations = lab.submodule_search_locations  # (a package's)
        return spec

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> None:
        return None  # a placeholder, replaced in `sys.modules` by the lab's module

    def exec_module(self, module: object) -> None:
        name = getattr(module, "__name__", "")
        lab = importlib.import_module("rr_actors_lab" + name.removeprefix("rr_actors"))
        sys.modules[name] = lab  # (the import system returns what `sys.modules` holds)


if not any(isinstance(finder, _LabNames) for finder in sys.meta_path):
    sys.meta_path.insert(0, _LabNames())
