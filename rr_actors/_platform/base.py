"""What a platform offers: each method is a job, done with a trick or plainly."""

from __future__ import annotations

from typing import Protocol

__all__ = ["Platform"]


class Platform(Protocol):
    """The platform-specific jobs rr_actors has; `portable` does each without tricks."""

    name: str
    """`"linux"` or `"portable"`."""

    def release_free_memory(self) -> None:
        """Hand the C heap's free pages back to the system now (an optimisation)."""
