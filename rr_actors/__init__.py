"""rr_actors: TeMoto's Resource Registrar as a Python actor framework.

Registrars, resource servers and clients are pykka actors; the docs hold a tutorial,
the semantics (`docs/explanation/semantics.md`) and the architecture.
"""

from typing import TYPE_CHECKING

from rr_actors import _extras, _log
from rr_actors import events as events  # `rr.events.to_dict(...)`, as `rr.errors` is
from rr_actors._core.bus import Subscription
from rr_actors._registrar import Registrar, ResourceRegistrar, StatusWatch
from rr_actors._store import quarantine_backup
from rr_actors._supervision import ChildInfo, Supervisor
from rr_actors._transport.resolve import Claimant
from rr_actors._types import Query, Status, StatusCallback, StatusUpdate
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
# The names `__all__` listed before it was cut to what a program uses (issue 54), still
# importable from here: a program written against them runs on.
from rr_actors._supervision import ChildCounts  # noqa: F401
from rr_actors.config import MAX_DEPENDENCY_DEPTH  # noqa: F401
from rr_actors.errors import (  # noqa: F401
    CatalogCorruptError,
    CatalogWriteError,
    DependencyCycleError,
    DuplicateNameError,
    DuplicateQueryIdError,
    ErrorFrame,
    InternalError,
    MessageTooLargeError,
    MissingExtraError,
    SupervisorGaveUpError,
    TransferError,
    UnknownRegistrarError,
    UnknownServerError,
)

if TYPE_CHECKING:  # at run time, `__getattr__` below imports it (and zenoh) at first use
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
    "quarantine_backup",
]
"""What a program uses (25 names, issue 54). The errors a caller catches most are here; every
error is in `rr_actors.errors`, `MAX_DEPENDENCY_DEPTH` in `rr_actors.config`,
`ChildCounts` beside `Supervisor.count_children`. The names this module listed before
are all still importable from it (`rr.UnknownServerError`, `rr.MAX_DEPENDENCY_DEPTH`)."""

__version__ = "0.1.0"

_log.install()  # WARNING and ERROR on stderr, level and logger named, until logging is configured


def __getattr__(name: str) -> object:
    """`rr.ZenohNetwork`, `rr.ZenohTLS`, imported at first use.

    So `import rr_actors` never imports zenoh or cryptography. Without the zenoh extra,
    a `MissingExtraError` (an `ImportError`) names it and the command that installs it.
    """
    if name == "ZenohNetwork":
        with _extras.needs("zenoh", "rr.ZenohNetwork"):
            from rr_actors._transport.zenoh.net import ZenohNetwork  # noqa: PLC0415 - lazily
        return ZenohNetwork
    if name == "ZenohTLS":
        with _extras.needs("zenoh", "rr.ZenohTLS"):
            from rr_actors._transport.zenoh.ops.tls import ZenohTLS  # noqa: PLC0415 - lazily
        return ZenohTLS
    raise AttributeError(f"module 'rr_actors' has no attribute {name!r}")
