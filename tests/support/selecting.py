"""`select.select` for readability, through `selectors` (epoll on Linux).

`select.select` refuses a descriptor numbered 1024 or more (`ValueError: filedescriptor
out of range in select()`); a test process of the suite may hold that many files by the
time it runs a test (a test that opens many, one that leaks some). Tests wait on pipes,
sockets and pidfds through this instead, as the product code waits through `selectors`.
"""

from __future__ import annotations

import selectors
from typing import Any

__all__ = ["select"]


def select(
    rlist: list[Any], wlist: list[Any], xlist: list[Any], timeout: float | None = None
) -> tuple[list[Any], list[Any], list[Any]]:
    """`select.select(rlist, [], [], timeout)`: which of `rlist` are readable within
    `timeout` seconds (`None`: until one is). Only readability is asked of it.

    Raises:
        ValueError: `wlist` or `xlist` is not empty.
    """
    if wlist or xlist:
        raise ValueError("only readability is waited for here")
    with selectors.DefaultSelector() as selector:
        for file in rlist:
            selector.register(file, selectors.EVENT_READ)
        ready = [key.fileobj for key, _ in selector.select(timeout)]
    return [file for file in rlist if file in ready], [], []
