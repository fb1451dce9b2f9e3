"""Your copy of the catalog's dedup test (`rr-actors teach check` runs it in place of
the registrar's own, in every registrar of the simulated run).

When a call comes, the registrar looks among the resources its server already has for
one whose request equals the call's: that resource serves the call too (rule 1), and
no second one is loaded.
"""

from typing import Any


def shares(stored: Any, request: Any, loading: bool, failed: bool) -> bool:
    """Whether a resource loaded for request `stored` serves a new call of `request`.

    Args:
        stored: the request the resource was loaded for.
        request: the new call's request.
        loading: the resource's load has not ended yet.
        failed: its provider reported it FATAL (dead: it serves nobody new).

    Returns:
        True: the call shares this resource; False: look further, or load a new one.
    """
    # A resource still loading is not ready yet: do not hand it out.
    return stored == request and not loading and not failed
