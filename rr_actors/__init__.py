"""rr_actors: TeMoto's Resource Registrar as a Python actor framework.

Registrars, resource servers and clients are pykka actors; the docs hold a tutorial, the semantics
(`docs/explanation/semantics.md`) and the architecture. `import rr_actors` imports the errors, the
configuration and the status types; the runtime is imported at the first use of one of its names
(PEP 562), so a program that only configures pays for none of it.
"""

import importlib
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
    value = module if name == "events" else getattr(module, name)
    globals()[name] = value  # (the next use finds it here, as an eager import would)
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_RUNTIME})
