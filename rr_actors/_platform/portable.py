"""The plain fallback of every platform trick: correct everywhere, only slower."""

from __future__ import annotations

__all__ = ["PortablePlatform"]


class PortablePlatform:
    """Every job done with the standard library only."""

    name = "portable"

    def release_free_memory(self) -> None:
        """Nothing: freed memory stays with the C allocator (it is reused)."""
