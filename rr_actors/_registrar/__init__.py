"""The resource registrar: its messages, its actors (split by role) and its handle."""

from typing import TYPE_CHECKING

from rr_actors._registrar.protocol import LoadCallback, Registrar, UnloadCallback
from rr_actors._registrar.registrar import MAX_DEPENDENCY_DEPTH, ResourceRegistrar

__all__ = [
    "MAX_DEPENDENCY_DEPTH",
    "LoadCallback",
    "Registrar",
    "ResourceRegistrar",
    "UnloadCallback",
]

if TYPE_CHECKING:  # mypy checks that the handle implements the protocol
    _implements: type[Registrar] = ResourceRegistrar
