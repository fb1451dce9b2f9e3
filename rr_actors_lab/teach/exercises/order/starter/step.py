"""Your copy of the registrar's teardown order (`rr-actors teach check` runs it in place
of the registrar's own, in every registrar of the simulated run).

A resource's load may call other registrars: those calls are its *dependencies* (rule 5),
held for as long as the resource is. When its last consumer lets go, the registrar tears
it down: it releases each dependency (an `unload` at the registrar that serves it) and
runs the resource's own `unload` callback. This step says in which order.
"""

from collections.abc import Sequence


def release_order(dependencies: Sequence[str]) -> list[str]:
    """The order of a resource's teardown.

    Args:
        dependencies: the query ids of the calls the resource holds as dependencies,
            the oldest first.

    Returns:
        Every dependency id and the word "unload" (the resource's own unload
        callback), each once, in the order they run: the ids before "unload" are
        released before it runs, those after it once it is done.
    """
    # Close the resource first, then give back what it used.
    return ["unload", *dependencies]
