"""Query ids: random UUID4 strings, made without building a `uuid.UUID`.

`str(uuid.uuid4())` builds a `UUID` in Python (its checks, its bit twiddling, then its
formatting): about half of what it costs goes there, which was 3% of a dedup-hit call's
instructions (docs/performance.md). `new_id` gives the same text (16 random bytes from
`os.urandom`, version 4, RFC 4122 variant) in one step.
"""

from __future__ import annotations

import os

__all__ = ["new_id"]

_CLEAR = ~(0xF000 << 64 | 0xC000 << 48)  # the version nibble, the variant's two bits
_SET = 0x4000 << 64 | 0x8000 << 48  # version 4, variant 10 (RFC 4122)


def new_id() -> str:
    """A random UUID4 as a string (`str(uuid.uuid4())` gives the same form)."""
    digits = f"{int.from_bytes(os.urandom(16), 'big') & _CLEAR | _SET:032x}"
    return f"{digits[:8]}-{digits[8:12]}-{digits[12:16]}-{digits[16:20]}-{digits[20:]}"
