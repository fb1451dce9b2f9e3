"""Unique names for the registrars and managers a test starts."""

from __future__ import annotations

import uuid


def named(prefix: str) -> str:
    """`<prefix>-<8 hex digits>`: a name no other test of the session uses."""
    return f"{prefix}-{uuid.uuid4().hex[:8]}"
