"""What one `Reconcile` told a provider (`Listing`): data, built by `reconciling.py`.

```
 reconciling.listing(provider) ──► Listing(held, due, left_out, epoch) ──► Reconcile
 the provider's answer ──► settle_listed: flights.py (failed calls, kept for a retry),
                           releases.py (releases that failed as it died)
```
"""

from __future__ import annotations

import dataclasses

__all__ = ["Listing"]


@dataclasses.dataclass(frozen=True)
class Listing:
    """What one `Reconcile` told a provider, as it was when the list left.

    Its answer ("the ids of the list I do not know") is about the catalog as it was
    then: only records that were answered before it left are settled by it.

    Attributes:
        held: the ids listed (client records, calls due, calls that failed as the
            provider died), sorted.
        due: of those, the calls whose answer was on its way.
        left_out: ids whose release failed as the provider died, not listed: the
            provider releases them (`Releases.unreleased`).
        epoch: the list's number (`Holdings.epoch`); an answer recorded with this
            number or a later one came after the list left.
    """

    held: tuple[str, ...]
    due: frozenset[str]
    left_out: frozenset[str]
    epoch: int
