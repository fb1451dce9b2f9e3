"""Your copy of the registrar's status climb (`rr-actors teach check` runs it in place
of the registrar's own, in every registrar of the simulated run).

A status about a resource reaches each of its consumers. When a consumer holds that
resource as a *dependency* of a resource it serves itself (its `parent`), the status
must go on, to that parent resource's consumers, and so on to the top.
"""

from collections.abc import Collection

from rr_actors import Status


def climb(parent: str | None, resources: Collection[str], status: Status) -> list[str]:
    """Where a status delivered to a consumer id goes next.

    Args:
        parent: the id of the resource this consumer id is a dependency of, or None
            (a client's own call: nothing above it).
        resources: the ids of the resources this registrar serves (ask it with `in`).
        status: the status (`Status.OK`, `WARNING`, `ERROR`, `FATAL`).

    Returns:
        The ids of the resources to notify in turn.
    """
    # Only bad news is worth bothering the resources above with.
    if parent is not None and parent in resources and status is Status.FATAL:
        return [parent]
    return []
