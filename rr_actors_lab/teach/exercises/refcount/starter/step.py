"""Your copy of the registrar's last-release test (`rr-actors teach check` runs it in
place of the registrar's own, in every registrar of the simulated run).

A resource shared by equal requests has one consumer id per call that holds it. Each
`unload(query_id)` releases one of them; the registrar then asks this test whether the
resource itself goes: its provider's `unload` callback runs, and it is forgotten.
"""

from collections.abc import Collection


def unloads(left: Collection[str]) -> bool:
    """Whether this release unloads the resource.

    Args:
        left: the consumer ids (query ids) still on the resource after this release.

    Returns:
        True: unload it now; False: keep it loaded for those still holding it.
    """
    # Count the consumers: when the last one lets go, the resource goes.
    return len(left) <= 1
