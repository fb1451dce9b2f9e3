"""The resource registrar: its messages, its actors (split by role) and its handle."""

from rr_actors._registrar.registrar import MAX_DEPENDENCY_DEPTH, ResourceRegistrar

__all__ = ["MAX_DEPENDENCY_DEPTH", "ResourceRegistrar"]
