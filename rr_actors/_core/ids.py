"""Query ids: random UUID4 strings, made without building a `uuid.UUID`.

`str(uuid.uuid4())` builds a `UUID` in Python (its checks, its bit twiddling, then its
formatting). `new_id` gives the same text in one step: the hex digits of 16 bytes from
`runtime.urandom` (`os.urandom`; a simulation's seeded bytes), with the version digit
set to 4 and the variant digit to one of `89ab` (RFC 4122).
"""

from __future__ import annotations

from rr_actors._core import runtime

__all__ = ["new_id"]

_VARIANT = {digit: "89ab"[int(digit, 16) & 3] for digit in "0123456789abcdef"}
"""A random hex digit -> a variant digit (its two low bits kept, the high two set to 10)."""


def new_id() -> str:
    """A random UUID4 as a string (`str(uuid.uuid4())` gives the same form)."""
    h = runtime.urandom(16).hex()
    return f"{h[:8]}-{h[8:12]}-4{h[13:16]}-{_VARIANT[h[16]]}{h[17:20]}-{h[20:]}"
