"""Your copy of the provider's side of a reconcile (`rr-actors teach check` runs it in
place of the registrar's own, in every registrar of the simulated run).

After a restart, a consumer and a provider may disagree on which ids the consumer holds
there: the consumer restarted empty and holds nothing any more, or the provider restarted
empty and lost what it served. So the consumer sends the provider the ids it holds
there (`held`), and the provider compares them with the ids it holds for that consumer
(`mine`). It releases the ids the consumer no longer holds (each one's `unload` runs when
its resource has no consumer left), and answers with the ids it does not know, which the
consumer then tells its callers are lost (`FATAL`).
"""

from collections.abc import Set


def reconcile(mine: Set[str], held: Set[str], under_way: Set[str]) -> tuple[set[str], set[str]]:
    """The provider's side of a reconcile with one consumer.

    Args:
        mine: the query ids this provider holds for the consumer.
        held: the query ids the consumer says it holds here.
        under_way: the query ids whose loads are still under way here (not answered
            yet: the provider will answer them).

    Returns:
        (the ids to release here, the ids to answer as unknown to the consumer).
    """
    release = set(held - mine)  # what the consumer holds and I do not: let it go
    unknown = set(mine - held)  # what I hold and the consumer forgot: tell it
    return release, unknown
